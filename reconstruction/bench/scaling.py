"""`hemicube bench train-scaling`: training throughput over 1, 2, ... processes under torchrun (DDP,
reconstruction.network.distributed; docs/scale-out.md), at the same global batch.

Each process count runs the real command, `python -m torch.distributed.run --standalone --nproc_per_node=N -m
hemicube.cli train --rig R --device D --steps S --batch B --eval-every E -o W/trainN` (NCCL on CUDA, one GPU a
process; gloo on the CPU), from the same seed. Per count: the training loop's lumitexels/s and iterations/s (the
run's metrics.json, over the global batch), the process's wall time, and the speed-up against the 1-process run,
which is the baseline: it runs first, whatever the list says. Each process runs one CPU thread unless
OMP_NUM_THREADS says otherwise (torchrun's own setting for several processes), so that on the CPU the counts compare
processes, not threads.

Check: at the same number of samples seen (every evaluation step; the global batch is the same), each run's held-out
loss (paper Eq. 3 on the fixed held-out set) is the 1-process run's within `loss_rtol`: the runs train the same
network. Not to the bit: the per-rank dropout masks and measurement noise are independent draws (pass dropout 0 and
measurement noise 0 to remove them), and the global batch's sums are split over the processes.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from reconstruction.bench.common import device_name, log_tail, positive_int, software

LOSS_RTOL = 0.05
# small sizes that run on a CPU in seconds (`--tiny`): the mini rig, 1 and 2 gloo processes, dropout and noise off
TINY = {"rig_name": "mini", "processes": (1, 2), "steps": 4, "batch": 16, "eval_every": 2,
        "dropout": 0.0, "measurement_noise": 0.0}


def bench_train_scaling(rig_name="paper", device="cpu", processes=(1, 2), steps=200, batch=1024, eval_every=50,
                        dropout=None, measurement_noise=None, loss_rtol=LOSS_RTOL, workdir=None) -> dict:
    """`workdir`: where the runs go (kept); None: a temporary folder, removed. dropout, measurement_noise: None
    keeps `hemicube train`'s defaults (paper §6)."""
    import tempfile

    from twin.bench import finish_checks

    for name, v in (("steps", steps), ("batch", batch), ("eval_every", eval_every)):
        positive_int(name, v)
    counts = sorted({1, *processes})
    for n in counts:
        positive_int("processes", n)
        if batch % n:
            raise ValueError(f"the global batch ({batch}) must split evenly over {n} processes")
    if workdir is None:
        with tempfile.TemporaryDirectory(prefix="hemicube-bench-train-") as tmp:
            return bench_train_scaling(rig_name, device, counts, steps, batch, eval_every, dropout,
                                       measurement_noise, loss_rtol, tmp)
    work = Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    args = ["train", "--rig", rig_name, "--device", device, "--steps", str(steps), "--batch", str(batch),
            "--eval-every", str(eval_every), "--checkpoint-every", str(steps), "--no-progress",
            *([] if dropout is None else ["--dropout", str(dropout)]),
            *([] if measurement_noise is None else ["--measurement-noise", str(measurement_noise)])]
    runs = {n: _train(n, args, work / f"train{n}", device) for n in counts}
    base = runs[1]
    per = {}
    for n, r in runs.items():
        per[str(n)] = {k: r[k] for k in ("exit_code", "seconds", "lumitexels_per_s", "iterations_per_s",
                                         "final_heldout_loss", "backend")}
        if r["lumitexels_per_s"] and base["lumitexels_per_s"]:
            per[str(n)]["speedup"] = r["lumitexels_per_s"] / base["lumitexels_per_s"]
            per[str(n)]["efficiency"] = per[str(n)]["speedup"] / n
    res = {"bench": "train-scaling", "rig": rig_name, "device": device_name(device), "device_arg": device,
           "steps": steps, "global_batch": batch, "eval_every": eval_every, "dropout": dropout,
           "measurement_noise": measurement_noise, "command": ["torchrun", "--nproc_per_node=N", "-m",
                                                               "hemicube.cli", *args],
           "software": software(), "processes": per,
           "seconds": {f"train_{n}": r["seconds"] for n, r in runs.items()}}
    checks = [{"check": f"train_{n}_exit_code", "exit_code": r["exit_code"], "passed": r["exit_code"] == 0,
               **({"log_tail": r["log_tail"]} if "log_tail" in r else {})} for n, r in runs.items()]
    checks += [_same_losses(n, r["heldout"], base["heldout"], batch, loss_rtol) for n, r in runs.items() if n != 1]
    return finish_checks(res, checks)


def _train(n: int, args: list[str], out: Path, device: str) -> dict:
    """One torchrun launch of `hemicube train` with n processes; its record, from the run's own metrics."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    if device.startswith("cuda"):  # NVLink multicast off (docs/scale-out.md)
        env.update(NCCL_NVLS_ENABLE="0", TORCH_SYMM_MEM_DISABLE_MULTICAST="1")
    log = out.parent / f"{out.name}.log"
    t = time.perf_counter()
    with open(log, "wb") as f:
        rc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={n}",
                             "-m", "hemicube.cli", *args, "-o", str(out)], stdout=f, stderr=subprocess.STDOUT,
                            env=env).returncode
    rec = {"exit_code": rc, "seconds": time.perf_counter() - t, "lumitexels_per_s": None,
           "iterations_per_s": None, "final_heldout_loss": None, "backend": None, "heldout": {}}
    if rc != 0:
        rec["log_tail"] = log_tail(log)
    else:
        m = json.loads((out / "metrics.json").read_text())
        rec.update({k: m.get(k) for k in ("lumitexels_per_s", "iterations_per_s", "final_heldout_loss", "backend")})
        rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines() if x.strip()]
        rec["heldout"] = {r["step"]: r["heldout_loss"] for r in rows}
    return rec


def _same_losses(n: int, got: dict, ref: dict, batch: int, rtol: float) -> dict:
    """The n-process run's held-out loss against the 1-process run's at every evaluation both made."""
    steps = sorted(set(got) & set(ref))
    rel = [abs(got[s] - ref[s]) / abs(ref[s]) for s in steps if ref[s]]
    worst = max(rel, default=float("inf"))
    return {"check": f"train_{n}_heldout_loss_vs_1_process", "rtol": rtol, "evaluations": len(steps),
            "samples_seen": [s * batch for s in steps], "max_rel_diff": worst, "passed": bool(steps) and worst <= rtol}
