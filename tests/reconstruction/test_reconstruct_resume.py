"""A reconstruction killed after fine-tuning resumes from its finished stages (reconstruction.output's stage folder).

One uninterrupted run (A) and one whose process is SIGKILLed while it fits (B, the real CLI in its own process; its
fit is made to wait so that the kill lands there), then B run again: it must reuse alignment, extraction and
fine-tuning (their files verified, not recomputed) and give A's bytes. Then the stage keys: a tampered stage file
is recomputed, another setting starts over. Mini rig, the session's `ramps` capture, a 12^2 grid (seconds a stage).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from reconstruction.output import ReconstructionFolder, stages_folder
from reconstruction.pipeline import ReconstructConfig, reconstruct

CONFIG = ReconstructConfig(resolution=12)
# every run here on one torch thread, the CLI's processes too, since their bytes are compared with run A's: on CI's
# two cores shared with other test processes, torch's default threads made this module's runs many times slower
pytestmark = pytest.mark.usefixtures("one_torch_thread")
ONE_THREAD = {"OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
# the CLI, with the fit made to wait (so a kill lands in it, after fine-tuning was kept)
WAITING_FIT = ("import sys, time; import reconstruction.stages.fitting as f; "
               "f.fit_ggx = lambda *a, **k: time.sleep(3600); "
               "from hemicube.cli import main; sys.exit(main(sys.argv[1:]))")


def _stage_names(folder: Path) -> set:
    try:
        return set(json.loads((folder / "stages.json").read_text()))
    except (OSError, ValueError):
        return set()


@pytest.fixture(scope="module")
def run_a(one_torch_thread, validate_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("resume") / "A"
    reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    return out


def _files(folder: Path) -> dict:
    return ReconstructionFolder(folder).summary()["files"]


def test_killed_while_fitting_resumes_after_fine_tuning(validate_dir, run_a, tmp_path):
    out = tmp_path / "B"
    stages = stages_folder(out)
    proc = subprocess.Popen([sys.executable, "-c", WAITING_FIT, "reconstruct", str(validate_dir / "capture"), "-o",
                             str(out), "--resolution", "12", "--no-progress"], env=dict(os.environ, **ONE_THREAD),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    # in the fit: fine-tuning is kept and its checkpoint forgotten (a kill between the two leaves the checkpoint too)
    while time.time() < deadline and _stage_names(stages) != {"alignment", "extraction", "finetune"} \
            and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert _stage_names(stages) == {"alignment", "extraction", "finetune"}, "the kill must land after fine-tuning"
    assert not out.exists()  # nothing half-built where the result goes
    leftovers = [p for p in stages.iterdir() if p.name.startswith(".B.")]  # atomic_folder's scratch is the stage folder
    assert leftovers, "the killed run's half-built folder is there to be cleaned"
    mtimes = {p.name: p.stat().st_mtime_ns for p in stages.iterdir()}
    kept = json.loads((stages / "stages.json").read_text())

    recon = reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    summary = ReconstructionFolder(out).summary()
    assert summary["resumed"] == ["alignment", "extraction", "finetune"]
    assert ReconstructionFolder(out).verify() == []
    assert not stages.exists() and sorted(p.name for p in out.parent.iterdir()) == ["B"]  # stages and leftovers gone
    # the stage files were verified and reused, not rewritten: the finished folder holds those very files
    assert {f: (out / f).stat().st_mtime_ns for f in mtimes if (out / f).exists()} == \
        {f: t for f, t in mtimes.items() if (out / f).exists()}
    a, b = _files(run_a), _files(out)
    assert a == b and len(a) > 4  # same bytes as the uninterrupted run: alignment, measurements, latents, maps
    # a resumed stage reports the seconds it took in the run that finished it
    assert recon.timings["finetune_s"] == kept["finetune"]["extra"]["seconds"] > 0
    assert summary["timings_s"]["alignment_s"] == kept["alignment"]["extra"]["seconds"]


def test_a_tampered_stage_is_recomputed_and_other_settings_start_over(validate_dir, run_a, tmp_path, monkeypatch):
    import reconstruction.stages.fitting as fitting

    out = tmp_path / "C"
    stages = stages_folder(out)

    def stop(*a, **k):
        raise RuntimeError("stopped in the fit")

    monkeypatch.setattr(fitting, "fit_ggx", stop)
    with pytest.raises(RuntimeError, match="stopped in the fit"):
        reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    assert _stage_names(stages) == {"alignment", "extraction", "finetune"} and not out.exists()
    path = stages / "measurements.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    monkeypatch.undo()
    reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    # the extraction ran again (its file failed its checksum) and gave the same bytes, so fine-tuning's key held
    assert ReconstructionFolder(out).summary()["resumed"] == ["alignment", "finetune"]
    assert _files(out) == _files(run_a)

    monkeypatch.setattr(fitting, "fit_ggx", stop)
    with pytest.raises(RuntimeError):
        reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    monkeypatch.undo()
    other = ReconstructConfig(resolution=12, holdout_line=3)
    reconstruct(validate_dir / "capture", out, other, progress=False)
    assert ReconstructionFolder(out).summary()["resumed"] == ["alignment", "extraction"]  # fine-tuning's key differs


def test_a_run_that_finished_no_stage_leaves_nothing(validate_dir, tmp_path, monkeypatch):
    import reconstruction.stages.alignment as alignment

    def fail(*a, **k):
        raise RuntimeError("no alignment")

    monkeypatch.setattr(alignment, "align_views", fail)
    with pytest.raises(RuntimeError, match="no alignment"):
        reconstruct(validate_dir / "capture", tmp_path / "D", CONFIG, progress=False)
    assert list(tmp_path.iterdir()) == []  # no output, no stage folder, no half-built folder


def test_killed_between_keeping_fine_tuning_and_forgetting_its_checkpoint(validate_dir, run_a, tmp_path, monkeypatch):
    """A kill after fine-tuning's stage is kept but before its checkpoint is forgotten leaves both: the run
    resumes from the kept stage and gives the uninterrupted run's bytes."""
    out = tmp_path / "E"

    def killed(self, stage):
        raise RuntimeError(f"killed before forgetting {stage}")

    monkeypatch.setattr(ReconstructionFolder, "forget_stage", killed)
    with pytest.raises(RuntimeError, match="killed before forgetting finetune_state"):
        reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    assert _stage_names(stages_folder(out)) == {"alignment", "extraction", "finetune", "finetune_state"}
    monkeypatch.undo()
    reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    assert ReconstructionFolder(out).summary()["resumed"] == ["alignment", "extraction", "finetune"]
    assert _files(out) == _files(run_a)


def test_fine_tuning_on_the_learned_photos_too(validate_dir, run_a, tmp_path, monkeypatch):
    """`finetune_photos="lines+learned"` is part of fine-tuning's stage key, and fits the primary view's
    learned-pattern photos beside the lines: its latents explain those photos better than the lines-only latents of
    run A (reference §4's objective, a sum of squared differences of square roots), with the same held-out line."""
    import numpy as np

    import reconstruction.stages.fitting as fitting
    import twin
    from reconstruction.stages.finetune import simulate_lines
    from reconstruction.pipeline import load_network

    def stop(*a, **k):
        raise RuntimeError("stopped in the fit")

    out = tmp_path / "F"
    monkeypatch.setattr(fitting, "fit_ggx", stop)
    with pytest.raises(RuntimeError, match="stopped"):
        reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    monkeypatch.undo()
    reconstruct(validate_dir / "capture", out, ReconstructConfig(resolution=12, finetune_photos="lines+learned"),
                progress=False)
    both, lines = ReconstructionFolder(out), ReconstructionFolder(run_a)
    assert both.summary()["resumed"] == ["alignment", "extraction"]  # fine-tuning's key differs
    assert both.summary()["holdout_line"] == lines.summary()["holdout_line"]
    meas = both.measurements()
    model = load_network("pretrained", twin.load_rig("mini"))

    def misfit(folder):
        sim = simulate_lines(model, folder.latent_passes()["pass3"], meas.learned_weights)
        return float(np.square(np.sqrt(sim + 1e-6) - np.sqrt(np.maximum(meas.learned_photos[:, 0], 0) + 1e-6)).sum())

    assert misfit(both) < 0.8 * misfit(lines)  # measured: 101 against 143
    with pytest.raises(ValueError, match="finetune_photos must be one of"):
        ReconstructConfig(finetune_photos="learned")


# the CLI with the second fit (the refit of the texels next to a brighter highlight, ReconstructConfig.spill_ratio)
# made to wait after leaving a mark, so that a kill lands in it, after the first fit finished
WAITING_REFIT = ("import sys, time; from pathlib import Path; import reconstruction.stages.fitting as f; real = f.fit_ggx; "
                 "calls = []\n"
                 "def fit(*a, **k):\n"
                 "    calls.append(1)\n"
                 "    if len(calls) == 1:\n"
                 "        return real(*a, **k)\n"
                 "    Path(sys.argv[1]).write_text('refit'); time.sleep(3600)\n"
                 "f.fit_ggx = fit\n"
                 "from hemicube.cli import main; sys.exit(main(sys.argv[2:]))")


def test_killed_while_refitting_resumes_and_gives_the_same_bytes(validate_dir, run_a, tmp_path):
    """A run killed in the refit goes on from the first fit's checkpoint (it does not start the fit over) and ends
    with the uninterrupted run's bytes; its summary counts the refitted texels."""
    assert ReconstructionFolder(run_a).summary()["spill_texels"] > 0, "ramps at 12^2 must have texels to refit"
    out, mark = tmp_path / "G", tmp_path / "refit.mark"
    proc = subprocess.Popen([sys.executable, "-c", WAITING_REFIT, str(mark), "reconstruct", str(validate_dir / "capture"),
                             "-o", str(out), "--resolution", "12", "--no-progress"],
                            env=dict(os.environ, **ONE_THREAD), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and not mark.exists() and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert mark.exists(), "the kill must land in the refit"
    assert {"alignment", "extraction", "finetune", "fit_state"} <= _stage_names(stages_folder(out))
    recon = reconstruct(validate_dir / "capture", out, CONFIG, progress=False)
    summary = ReconstructionFolder(out).summary()
    assert summary["resumed"][:3] == ["alignment", "extraction", "finetune"]
    assert summary["resumed"][3].startswith("fitting (")  # the first fit's checkpoint, not a fit from the start
    assert summary["spill_texels"] == ReconstructionFolder(run_a).summary()["spill_texels"]
    assert recon.timings["refit_s"] > 0 and _files(out) == _files(run_a)
