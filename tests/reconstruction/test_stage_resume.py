"""Killed fine-tuning and a killed fit resume (the checkpoints of reconstruction.stages.finetune.finetune and
reconstruction.stages.fitting.direct._fit_direct): stopped after any of their saves (a batch of a pass; a chunk, a
propagation round, a step of the joint prior) and run again on the state saved, through the stage folder's files
(reconstruction/output.py, reconstruction.pipeline._Checkpoint), they end with the same numbers, to the bit, as a
run that was never stopped. A tampered state is not used; a state of another problem is refused in one line.
Fine-tuning's test is in tests/test_finetune.py (its fixtures), with the checkpoint defined here."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruction.stages.fitting import direct
from reconstruction.stages.fitting import FitConfig, fit_ggx
from reconstruction.output import FIT_STATE, ReconstructionFolder
from reconstruction.pipeline import _Checkpoint

from tests.reconstruction.test_fitting import _targets, weak_beside_glossy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

R, C = 4, 6
CFG = FitConfig(iterations=6, batch=6)  # 4 chunks


class _Killed(Exception):
    pass


class _Stopping(_Checkpoint):
    """The stage folder's checkpoint, which stops the fit (as a kill would) right after its save number `at`."""

    def __init__(self, folder, at=None, stage="fit_state"):
        super().__init__(ReconstructionFolder(folder), stage, "key")
        self.stages.dir.mkdir(parents=True, exist_ok=True)
        self.at, self.phases = at, []

    def save(self, state):
        super().save(state)
        self.phases.append(state["phase"])
        if len(self.phases) == self.at:
            raise _Killed


@pytest.fixture(scope="module")
def problem(mini):
    """A weak rough lobe beside a glossy ink (tests/test_fitting.py's joint-prior grid, smaller), noisy lines."""
    p, _ = weak_beside_glossy(mini, (R, C), 50.0, 3, 0.3)
    pos = p["position"]
    m, lines, w = _targets(mini, p)
    rng = np.random.default_rng(3)
    return pos, m, (lines * (1 + 0.004 * rng.standard_normal(lines.shape))).astype(np.float32), w


def _fit(mini, problem, checkpoint=None):
    pos, m, lines, w = problem
    return fit_ggx(mini, pos, m, lines=lines, line_weights=w, grid_shape=(R, C), config=CFG, checkpoint=checkpoint)


def _same(a, b):
    for k in ("normal", "tangent", "alpha_x", "alpha_y", "rho_d", "rho_s"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert np.array_equal(a.history, b.history)
    assert a.info["joint_steps"] == b.info["joint_steps"] and a.info["propagation_restarts"] == b.info[
        "propagation_restarts"]


@pytest.mark.slow
def test_a_killed_fit_resumes_to_the_same_numbers(mini, problem, tmp_path, monkeypatch):
    monkeypatch.setattr(direct, "CHECKPOINT_SECONDS", 0.0)  # a save after every chunk
    whole = _fit(mini, problem)
    record = _Stopping(tmp_path / "all")
    _same(_fit(mini, problem, record), whole)  # saving changes nothing
    phases = record.phases
    assert phases[:4] == ["chunks"] * 3 + ["propagation"] and "joint" in phases, phases
    # stopped after a chunk, after the chunks, after a propagation round, inside the joint prior, at its end
    for at in sorted({2, 4, phases.index("joint"), phases.index("joint") + 1, len(phases)}):
        folder = tmp_path / f"kill{at}"
        with pytest.raises(_Killed):
            _fit(mini, problem, _Stopping(folder, at))
        spent = ReconstructionFolder(folder).finished_stage("fit_state", "key")["seconds"]
        again = _Stopping(folder)
        _same(_fit(mini, problem, again), whole)
        assert again.loaded == phases[at - 1]
        # the killed run's seconds up to its last save carry over: a stage resumed in another call reports the
        # time its result took (reconstruction.pipeline's timings), not the last call's share
        assert again.earlier == spent > 0


def test_a_tampered_or_foreign_state(mini, problem, tmp_path, monkeypatch):
    monkeypatch.setattr(direct, "CHECKPOINT_SECONDS", 0.0)
    folder = tmp_path / "s"
    with pytest.raises(_Killed):
        _fit(mini, problem, _Stopping(folder, 2))
    state = folder / FIT_STATE
    data = bytearray(state.read_bytes())
    data[-40] ^= 1
    state.write_bytes(bytes(data))
    fresh = _Stopping(folder)
    _same(_fit(mini, problem, fresh), _fit(mini, problem))  # its checksum fails: the fit starts over
    assert fresh.loaded is None

    class Foreign:
        def load(self):
            return {"phase": "chunks", "chunks_done": 1, "q": np.zeros((5, 5), np.float32), "history": np.zeros(6)}

        def save(self, state):
            pass

    with pytest.raises(ValueError, match="does not belong to this fit"):
        _fit(mini, problem, Foreign())

    class ForeignMask(Foreign):  # the right numbers, but a propagation mask of another texel count
        def load(self):
            return {"phase": "propagation", "chunks_done": 4, "q": np.zeros((R * C, 5), np.float32),
                    "history": np.zeros(6), "restarted": [3], "changed": np.zeros(R * C + 1, bool)}

    with pytest.raises(ValueError, match="does not belong to this fit"):
        _fit(mini, problem, ForeignMask())
    with pytest.raises(ValueError, match="keeps no unfinished state"):
        ReconstructionFolder(folder).write_state("alignment", {"phase": "x"})
    pos, m, lines, w = problem
    with pytest.raises(ValueError, match="direct method only"):
        fit_ggx(mini, pos, m, lines=lines, line_weights=w, grid_shape=(R, C),
                config=FitConfig(method="neural", iterations=1), checkpoint=Foreign())

