"""Training under torchrun (reconstruction.network.distributed, docs/scale-out.md): a 2-process gloo run matches a
1-process run with the same global batch, and a checkpoint written by rank 0 is resumed by every rank.

The processes are real: `python -m torch.distributed.run --standalone --nproc_per_node=2 -m hemicube.cli train`.
Dropout and the measurement noise are 0 here (they are per-rank draws, docs/scale-out.md); the data are
the global batch's slices, the encoder's BatchNorm uses the global batch's statistics.

Tolerances (float32 on the CPU). The per-window train losses (Eq. 3, the global batch's mean) agree to 2e-4
relative: the sums are split over two processes and the variance over two all-reduces. Parameters: per tensor,
|theta_2 - theta_1| <= 2% of how far the 1-process run moved it (|theta_1 - theta_0|); measured <= 0.4%.
Excluded: the biases of the Linear layers that feed a BatchNorm. BatchNorm subtracts them again, so their true
gradient is 0 and what each run computes is rounding noise; Adam turns noise of either sign into steps of
size lr, so those biases (and the running means that include them, hence the eval-mode held-out loss) differ
between any two runs that round differently. They do not change the training-mode output."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ARGS = ["train", "--rig", "mini", "--batch", "16", "--dropout", "0", "--measurement-noise", "0", "--eval-every", "2",
        "--checkpoint-every", "2", "--no-progress"]


def _run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r


def _hemicube(*args) -> list[str]:
    return [sys.executable, "-m", "hemicube.cli", *args]


def _torchrun(n: int, *args) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={n}",
            "-m", "hemicube.cli", *args]


def _rows(run: Path) -> list[dict]:
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]


def _model(run: Path) -> dict:
    from reconstruction.network.train import load_checkpoint

    return {k[6:]: v for k, v in load_checkpoint(run)[1].items() if k.startswith("model.")}


def _pre_bn_biases(model) -> set[str]:
    names, mods = set(), dict(model.named_modules())
    for name, m in mods.items():
        if isinstance(m, torch.nn.Sequential):
            kids = list(m.named_children())
            for (a, ma), (_, mb) in zip(kids, kids[1:]):
                if isinstance(ma, torch.nn.Linear) and isinstance(mb, torch.nn.BatchNorm1d):
                    names.add(f"{name}.{a}.bias")
    return names


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("ddp")
    _run(_hemicube(*ARGS, "--steps", "4", "-o", "one"), d)
    _run(_torchrun(2, *ARGS, "--steps", "2", "-o", "two"), d)          # a first chunk ...
    r = _run(_torchrun(2, *ARGS, "--steps", "4", "-o", "two"), d)      # ... resumed by both ranks
    return d / "one", d / "two", r


def test_two_process_run_reports_like_one(runs):
    one, two, r = runs
    a, b = json.loads((one / "metrics.json").read_text()), json.loads((two / "metrics.json").read_text())
    assert set(a) == set(b) and a["world_size"] == 1 and b["world_size"] == 2 and b["backend"] == "gloo"
    assert b["steps"] == 4 and b["resumed_from"] == 2
    assert r.stdout.count("trained 4 steps") == 1, "rank 0 alone reports"
    ra, rb = _rows(one), _rows(two)
    assert [x["step"] for x in ra] == [x["step"] for x in rb] == [0, 2, 4]
    assert [set(x) for x in ra] == [set(x) for x in rb]
    assert rb[0]["heldout_loss"] == ra[0]["heldout_loss"]  # the same initial weights, the same held-out set
    for x, y in zip(ra[1:], rb[1:]):
        for k in ("train_loss", "train_swap_loss"):
            assert y[k] == pytest.approx(x[k], rel=2e-4), k
    for f in ("patterns.npz", "loss.png", "checkpoint.json"):
        assert (two / f).is_file()


def test_two_process_parameters_match_one(runs):
    import twin
    from reconstruction.network.architecture import AcquisitionNet
    from reconstruction.network.train import TrainConfig

    one, two, _ = runs
    rig = twin.load_rig("mini")
    torch.manual_seed(0)  # the seed both runs built their initial weights from
    init = AcquisitionNet(TrainConfig(dropout=0.0, measurement_noise=0.0)
                          .network_config(int((~np.asarray(rig.is_bottom)).sum())))
    skip = _pre_bn_biases(init)
    assert skip, "the encoder has Linear -> BatchNorm1d pairs"
    a, b, s0 = _model(one), _model(two), init.state_dict()
    worst = 0.0
    for k, v in a.items():
        if k in skip or "running" in k or "num_batches" in k:
            continue
        moved = float((v - s0[k]).norm())
        assert moved > 0, k
        worst = max(worst, float((b[k] - v).norm()) / moved)
    assert worst <= 0.02, worst


def test_global_batchnorm_alone_is_batchnorm():
    from reconstruction.network.distributed import GlobalBatchNorm1d, globalise_batchnorm

    torch.manual_seed(3)
    net = torch.nn.Sequential(torch.nn.Linear(5, 4), torch.nn.BatchNorm1d(4))
    ref = {k: v.clone() for k, v in net.state_dict().items()}
    x = torch.randn(7, 5)
    y_ref = net(x)
    net.load_state_dict(ref)
    globalise_batchnorm(net)
    assert isinstance(net[1], GlobalBatchNorm1d) and set(net.state_dict()) == set(ref)
    assert torch.equal(net(x), y_ref)


def test_batch_must_split_evenly(tmp_path):
    r = subprocess.run(_torchrun(2, *ARGS[:4], "15", *ARGS[5:], "--steps", "1", "-o", "odd"), cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "multiple of the 2 processes" in r.stdout + r.stderr
