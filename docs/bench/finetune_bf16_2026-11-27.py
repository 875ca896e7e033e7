"""bfloat16 fine-tuning on the paper rig, an experiment (issue #12: "mixed precision where it measurably does not
hurt"; the median per-texel objective within 1% of float32's): every pass's energy and gradient under
torch.autocast(bfloat16) (the decoder's products on the tensor cores with an 8-bit mantissa, reductions in
float32, the latents and Adam in float32), against TF32 (the pipeline's default) and float32.

    python docs/bench/finetune_bf16_2026-11-27.py 65536 > finetune_bf16_paper_h100_65536_2026-11-27.json

The texels and noise are those of docs/bench/finetune_tf32_schedule_2026-11-26.py (`hemicube bench reconstruct`'s
synthetic texels, seed 0, 1% multiplicative noise on the lines, line 0 held out); each run's median per-texel
pass-3 objective is evaluated in float32 on the kept lines; exits 1 when float32's two runs differ. Runs on the CPU
too (n = 64) to check the script.
"""
import json
import sys
import time

import numpy as np
import torch

from bench_setup import finetune_texels
from reconstruction import finetune as F

n = int(sys.argv[1])
dev = "cuda" if torch.cuda.is_available() else "cpu"
rig, model, lines, W, z, hold = finetune_texels("paper", n, dev)
keep = [i for i in range(lines.shape[1]) if i not in hold]
original = F._adam_run


def bf16_run(*args):
    with torch.autocast(device_type=dev, dtype=torch.bfloat16):
        return original(*args)


def sync():
    if dev == "cuda":
        torch.cuda.synchronize()


res = {}
for mode, precision, run in (("tf32_warmup", "tf32", original), ("float32", "float32", original),
                             ("tf32", "tf32", original), ("bf16", "tf32", bf16_run), ("float32_again", "float32",
                                                                                     original)):
    F._adam_run = run
    sync()
    t = time.perf_counter()
    ft = F.finetune(model, z, lines, W, F.FinetuneConfig(holdout=hold, device=dev, precision=precision))
    sync()
    dt = time.perf_counter() - t
    F._adam_run = original
    sim = F.simulate_lines(model, ft.latent, W, batch=16384)[:, keep]
    e = ((np.sqrt(np.maximum(sim, 0) + 1e-6) - np.sqrt(np.maximum(lines[:, keep], 0) + 1e-6)) ** 2).sum((1, 2))
    res[mode] = {"seconds": dt, "pass_seconds": ft.seconds,
                 "iterations": {k: int(sum(vs)) for k, vs in ft.iterations.items()},
                 "median_texel_objective": float(np.median(e)), "e": e}
a = res["float32"]["e"]
for mode, r in res.items():
    e = r.pop("e")
    r["median_objective_rel_diff"] = float((np.median(e) - np.median(a)) / np.median(a))
res.update(rig="paper", texels=n, device=torch.cuda.get_device_name(0) if dev == "cuda" else "cpu",
           torch=torch.__version__)
print(json.dumps(res, indent=1))
# the baseline computes the same thing each time: float32 run twice gives the same objective (exit 1 otherwise)
sys.exit(0 if res["float32_again"]["median_objective_rel_diff"] == 0.0 else 1)
