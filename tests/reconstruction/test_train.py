"""reconstruction.network.train and `hemicube train` / `hemicube patterns show` on the mini rig (CPU, ~45 s)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import twin
from reconstruction.network.architecture import AcquisitionNet
import reconstruction.network.train as train_module
from reconstruction.network.train import (CHECKPOINT_JSON, TrainConfig, TrainError, export_patterns, is_pair_step,
                                  load_checkpoint, train)
from hemicube.cli import main
from twin.capture.patterns import load_patterns


@pytest.fixture(scope="module")
def run200(tmp_path_factory):
    """An uninterrupted 200-step run with the default config, through the CLI."""
    run = tmp_path_factory.mktemp("train") / "run200"
    assert main(["train", "--rig", "mini", "--steps", "200", "-o", str(run), "--no-progress"]) == 0
    return run


def _rows(run):
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_cli_train_writes_a_complete_run(run200, capsys):
    rows = _rows(run200)
    steps = [r["step"] for r in rows]
    assert steps == sorted(set(steps)) and steps[0] == 0 and steps[-1] == 200
    assert steps == [0, 50, 100, 150, 200]
    for r in rows:
        assert set(r) >= {"step", "train_loss", "heldout_loss", "wall_s", "lumitexels_per_s"}
        assert np.isfinite(r["heldout_loss"])
    assert rows[-1]["heldout_loss"] < rows[0]["heldout_loss"]
    assert rows[-1]["heldout_loss"] < rows[1]["heldout_loss"]  # still improving after the first 50 steps
    assert all(r["lumitexels_per_s"] > 0 for r in rows[1:])
    assert [r["wall_s"] for r in rows] == sorted(r["wall_s"] for r in rows)

    meta = json.loads((run200 / CHECKPOINT_JSON).read_text())
    assert meta["step"] == 200 and all((run200 / n).is_file() for n in meta["tensors"])
    # the earlier saves' shard files are gone once a later checkpoint names its own
    assert sorted(p.name for p in run200.glob("checkpoint-*.safetensors")) == sorted(meta["tensors"])
    assert meta["config"]["steps"] == 200 and isinstance(meta["rng"]["torch"], list)
    assert (run200 / "loss.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    summary = json.loads((run200 / "metrics.json").read_text())
    assert summary["steps"] == 200
    assert summary["final_heldout_loss"] == pytest.approx(rows[-1]["heldout_loss"])
    assert summary["iterations_per_s"] > 0 and summary["lumitexels_per_s"] > 0
    assert summary["command_line"]

    rig = twin.load_rig("mini")
    ps = load_patterns(run200 / "patterns.npz")
    assert ps.num_patterns == 64 and ps.num_leds == rig.num_leds and ps.rig == "mini"
    ps.check_rig(rig)
    assert ps.names[:4] == ("learned_00+", "learned_00-", "learned_01+", "learned_01-")
    assert all(ps.names[2 * k][:-1] == ps.names[2 * k + 1][:-1] and ps.names[2 * k].endswith("+")
               and ps.names[2 * k + 1].endswith("-") for k in range(32))
    lv = ps.levels.astype(int)
    bottom = np.asarray(rig.is_bottom)
    assert np.all(lv[:, bottom] == 0)
    assert np.all(lv[..., 0] == lv[..., 1]) and np.all(lv[..., 0] == lv[..., 2])
    assert np.all(np.minimum(lv[0::2], lv[1::2]) == 0)  # each LED lit in at most one frame of a pair
    assert lv.max() > 0 and "step 200" in ps.note


def test_export_matches_the_quantised_weights():
    rig = twin.load_rig("mini")
    cfg = TrainConfig()
    torch.manual_seed(3)
    model = AcquisitionNet(cfg.network_config(int((~np.asarray(rig.is_bottom)).sum())))
    ps = export_patterns(model, rig)
    w = ps.weights[..., 0]
    signed = w[0::2] - w[1::2]  # (32, L)
    q = model.patterns.quantised_weights()[0].detach().numpy()
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    np.testing.assert_allclose(signed[:, upper], q, atol=1e-6)


def test_pair_steps_are_evenly_spread():
    assert sum(is_pair_step(i, 0.5) for i in range(200)) == 100
    assert [is_pair_step(i, 0.5) for i in range(4)] == [False, True, False, True]
    assert not any(is_pair_step(i, 0.0) for i in range(10)) and all(is_pair_step(i, 1.0) for i in range(10))


def test_resume_reproduces_an_uninterrupted_run(run200, tmp_path):
    run = tmp_path / "resumed"
    assert main(["train", "--rig", "mini", "--steps", "100", "-o", str(run), "--no-progress"]) == 0
    assert json.loads((run / CHECKPOINT_JSON).read_text())["step"] == 100
    assert main(["train", "--rig", "mini", "--steps", "200", "-o", str(run), "--no-progress"]) == 0
    meta_a, ta = load_checkpoint(run200)
    meta_b, tb = load_checkpoint(run)
    assert meta_b["step"] == 200 and meta_a["rng"] == meta_b["rng"]
    assert set(ta) == set(tb) and any(k.startswith("optim.") for k in ta)
    for k in ta:  # model parameters, BatchNorm buffers and Adam moments: bit for bit
        assert torch.equal(ta[k], tb[k]), k
    assert [r["step"] for r in _rows(run)] == [0, 50, 100, 150, 200]
    np.testing.assert_array_equal(load_patterns(run / "patterns.npz").levels,
                                  load_patterns(run200 / "patterns.npz").levels)
    summary = json.loads((run / "metrics.json").read_text())
    assert summary["resumed_from"] == 100 and summary["steps_this_invocation"] == 100


def test_changed_config_is_refused(run200, capsys):
    before = (run200 / CHECKPOINT_JSON).read_bytes()
    with pytest.raises(TrainError, match="different config.*lr"):
        train(TrainConfig(rig="mini", steps=200, lr=2e-3), run200, progress=False)
    assert main(["train", "--rig", "mini", "--steps", "300", "--seed", "7", "-o", str(run200), "--no-progress"]) == 2
    assert "different config" in capsys.readouterr().err
    assert (run200 / CHECKPOINT_JSON).read_bytes() == before  # untouched


def test_patterns_show_and_measurements(run200, tmp_path, capsys):
    out = tmp_path / "x.png"
    assert main(["patterns", "show", str(run200 / "patterns.npz"), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out1 = tmp_path / "one.png"
    assert main(["patterns", "show", str(run200 / "patterns.npz"), "-o", str(out1), "--index", "3", "--rig", "mini"]) == 0
    assert out1.is_file()

    rig = twin.load_rig("mini")
    ps = load_patterns(run200 / "patterns.npz")
    P = 5
    pos = np.zeros((P, 3)) + np.asarray(rig.sample.origin)
    pos[:, 0] += np.linspace(-20, 20, P)
    nrm = np.tile(np.asarray(rig.sample.normal, float), (P, 1))
    tan = np.tile(np.asarray(rig.sample.x_axis, float), (P, 1))
    B = twin.measurements(rig, pos, nrm, tan, [[0.5] * 3] * P, [[2.0] * 3] * P, [0.1] * P, [0.2] * P, patterns=ps)
    B = np.asarray(B)
    assert B.shape == (P, 64, 3) and np.all(np.isfinite(B)) and np.all(B >= 0) and B.max() > 0

    from twin.capture.plan import build_patterns  # what `hemicube capture --patterns` does with the file

    plan = build_patterns(rig, ps)
    assert plan.names[:64] == ps.names and np.array_equal(plan.levels[:64], ps.levels)


def test_time_limit_chunks_resume_to_the_uninterrupted_run(run200, tmp_path, capsys):
    """--time-limit 0: each call runs one step, checkpoints and stops; re-running the same command
    resumes, and the chunked run ends bit for bit where the uninterrupted one does (GPU chunks rely on it)."""
    run = tmp_path / "chunked"
    args = ["train", "--rig", "mini", "--steps", "200", "-o", str(run), "--no-progress"]
    assert main(args + ["--time-limit", "0"]) == 0
    assert "stopped on the time limit" in capsys.readouterr().out
    summary = json.loads((run / "metrics.json").read_text())
    assert summary["stopped_on_time_limit"] and summary["steps"] == 1 and summary["target_steps"] == 200
    assert json.loads((run / CHECKPOINT_JSON).read_text())["step"] == 1
    assert [r["step"] for r in _rows(run)] == [0, 1]  # the chunk's end is evaluated
    assert main(args + ["--time-limit", "0"]) == 0  # a second chunk: one more step
    assert json.loads((run / CHECKPOINT_JSON).read_text())["step"] == 2
    assert main(args + ["--time-limit", "1e9"]) == 0  # the limit is no part of the config
    summary = json.loads((run / "metrics.json").read_text())
    assert not summary["stopped_on_time_limit"] and summary["resumed_from"] == 2 and summary["steps"] == 200
    meta_a, ta = load_checkpoint(run200)
    meta_b, tb = load_checkpoint(run)
    assert meta_a["rng"] == meta_b["rng"] and set(ta) == set(tb)
    for k in ta:
        assert torch.equal(ta[k], tb[k]), k
    full = {r["step"]: r["heldout_loss"] for r in _rows(run200)}
    rows = _rows(run)
    assert [r["step"] for r in rows] == [0, 1, 2, 50, 100, 150, 200]
    assert all(r["heldout_loss"] == full[r["step"]] for r in rows if r["step"] in full)


def test_checkpoint_shards_stay_small_and_move_between_folders(run200, tmp_path, monkeypatch, capsys):
    """A checkpoint in files of at most CHECKPOINT_SHARD_BYTES of tensors each (16 MiB for a lent
    machine's files), a tensor larger than that cut into pieces; a run moved to another folder (another machine)
    resumes from its shards to the uninterrupted run bit for bit; a changed shard is refused in one line."""
    import shutil

    _, full = load_checkpoint(run200)
    limit = max(t.nbytes for t in full.values()) // 3  # the largest tensors must be cut
    monkeypatch.setattr(train_module, "CHECKPOINT_SHARD_BYTES", limit)
    first = tmp_path / "machine_a" / "run"
    args = ["train", "--rig", "mini", "--steps", "200", "--no-progress"]
    assert main(args + ["--steps", "100", "-o", str(first)]) == 0
    meta = json.loads((first / CHECKPOINT_JSON).read_text())
    assert meta["version"] == 2 and len(meta["tensors"]) > 3 and meta["split"]
    for name in meta["tensors"]:  # each file: at most `limit` bytes of tensors plus the safetensors header
        assert (first / name).stat().st_size <= limit + 64 * 1024, name
    moved = tmp_path / "machine_b" / "run"
    shutil.copytree(first, moved)
    orphan = moved / "checkpoint-000000150-0002-000.safetensors"  # what a save killed before its JSON leaves
    orphan.write_bytes(b"partial")
    assert load_checkpoint(moved)[0]["step"] == 100  # the JSON still names a whole checkpoint
    assert main(args + ["-o", str(moved)]) == 0
    meta_b, tb = load_checkpoint(moved)
    assert meta_b["step"] == 200 and set(tb) == set(full)
    for k in full:  # the shard size changes no bit of the training
        assert torch.equal(full[k], tb[k]), k
    assert sorted(p.name for p in moved.glob("checkpoint-*.safetensors")) == sorted(meta_b["tensors"])
    assert not set(meta["tensors"]) & set(meta_b["tensors"])  # every save writes new names

    bad = dict(meta, split={**meta["split"], next(iter(meta["split"])): [7, 7, 7]})  # a JSON edited by hand
    (first / CHECKPOINT_JSON).write_text(json.dumps(bad))
    with pytest.raises(TrainError, match="do not make its shape"):
        load_checkpoint(first)
    (first / CHECKPOINT_JSON).write_text(json.dumps(meta))

    shard = first / meta["tensors"][1]
    data = bytearray(shard.read_bytes())
    data[-1] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(TrainError, match=rf"names {shard.name}, which is missing or has another sha256"):
        load_checkpoint(first)
    capsys.readouterr()
    assert main(args + ["-o", str(first)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another sha256" in err[0]


def test_a_failed_save_leaves_no_shard(tmp_path, monkeypatch):
    """A save that fails part-way (a full disk) removes the shards it wrote; no checkpoint names them."""
    import safetensors.torch

    real, calls = safetensors.torch.save_file, []

    def failing(tensors, path, metadata=None):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        real(tensors, path, metadata=metadata)

    monkeypatch.setattr(train_module, "CHECKPOINT_SHARD_BYTES", 256 * 1024)
    monkeypatch.setattr(safetensors.torch, "save_file", failing)
    run = tmp_path / "run"
    with pytest.raises(OSError, match="No space left"):
        train(TrainConfig(rig="mini", steps=1), run, progress=False)
    assert len(calls) == 2 and not list(run.glob("checkpoint*")) and load_checkpoint(run) is None
