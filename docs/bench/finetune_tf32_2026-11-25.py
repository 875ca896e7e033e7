"""TF32 against float32 fine-tuning on the paper rig (docs/performance.md, "Fine-tuning in TF32"), as run on an H100:

    python docs/bench/finetune_tf32_2026-11-25.py 65536 > finetune_tf32_paper_h100_65536_2026-11-25.json

The shipped paper-rig network, `hemicube bench reconstruct`'s synthetic texels (seed 0), the paper's fixed 350 steps,
float32, then TF32 matrix products, then float32 again; per-texel objective of pass 3 on the kept lines and the
held-out line's relative error, each evaluated in float32. A record of how the numbers were measured.
"""
import sys, time, json, numpy as np, torch, twin
from reconstruction.bench import _texels
from reconstruction.pipeline import load_network
from reconstruction.latents import decode
from reconstruction.finetune import FinetuneConfig, finetune, simulate_lines
n = int(sys.argv[1]); out = {}
rig = twin.load_rig("paper"); dev = "cuda:0"
model = load_network("pretrained", rig, dev)
learned, lines, pos, W, _ = _texels(rig, model, n, 0, dev, exact=False)
z = decode(model, learned, device=dev)
res = {}
for name, tf32 in (("float32", False), ("tf32", True), ("float32_again", False)):
    torch.backends.cuda.matmul.allow_tf32 = tf32
    torch.cuda.synchronize(); torch.cuda.reset_peak_memory_stats()
    t = time.perf_counter()
    ft = finetune(model, z, lines, W, FinetuneConfig(source="paper", holdout=(0,), device=dev))
    torch.cuda.synchronize(); dt = time.perf_counter() - t
    torch.backends.cuda.matmul.allow_tf32 = False
    sim = simulate_lines(model, ft.latent, W, batch=16384)
    # per-texel objective of pass 3 on the kept lines, evaluated in float32
    e = ((np.sqrt(np.maximum(sim[:, 1:], 0) + 1e-6) - np.sqrt(np.maximum(lines[:, 1:], 0) + 1e-6)) ** 2).sum((1, 2))
    held = np.abs(sim[:, 0] - lines[:, 0]).sum(1) / np.maximum(np.abs(lines[:, 0]).sum(1), 1e-12)
    res[name] = {"seconds": dt, "objective": {k: list(v) for k, v in ft.objective.items()},
                 "texel_objective_median": float(np.median(e)), "texel_objective_mean": float(e.mean()),
                 "heldout_line_rel_err_median": float(np.median(held)),
                 "peak_torch_allocated_gb": torch.cuda.max_memory_allocated() / 2**30, "e": e}
a, b, c = res["float32"]["e"], res["tf32"]["e"], res["float32_again"]["e"]
for r in res.values(): r.pop("e")
res["texel_objective_rel_diff_tf32_vs_float32_median"] = float(np.median(np.abs(b - a) / np.maximum(a, 1e-12)))
res["texel_objective_rel_diff_float32_rerun_median"] = float(np.median(np.abs(c - a) / np.maximum(a, 1e-12)))
res["texels"] = n; res["device"] = torch.cuda.get_device_name(0); res["torch"] = torch.__version__
print(json.dumps(res, indent=1))
