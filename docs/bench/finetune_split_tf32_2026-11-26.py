"""Split-precision ("3xTF32") against float32 and plain TF32 fine-tuning on the paper rig (FinetuneConfig.precision,
reconstruction.network.split_tf32_linear), as run on an H100 (docs/performance.md, "Split-precision fine-tuning"). The
option it measures was slower than float32 and was taken out again: run it at commit 6bf0afa, where it exists.

    python docs/bench/finetune_split_tf32_2026-11-26.py 65536 > finetune_split_tf32_paper_h100_65536_2026-11-26.json

As docs/bench/finetune_tf32_2026-11-25.py: the shipped paper-rig network, `hemicube bench reconstruct`'s synthetic
texels (seed 0), the paper's fixed 350 steps; runs float32, split_tf32 (the decoder's products split, the rest
float32), tf32 (torch's global TF32 flag on for every matrix product, as the 2026-11-25 run), then float32 again;
per-texel objective of pass 3 on the kept lines and the held-out line's relative error, each evaluated in float32.
Per run also the median relative difference of the per-texel objective from float32's and median_objective_rel_diff
= (median e(run) - median e(float32)) / median e(float32). Runs on the CPU too (cuda:0 when there is one), e.g. with
n = 64, to check the script. A record of how the numbers were measured.
"""
import sys, time, json, numpy as np, torch, twin
from reconstruction.bench import _texels
from reconstruction.pipeline import load_network
from reconstruction.latents import decode
from reconstruction.finetune import FinetuneConfig, finetune, simulate_lines
n = int(sys.argv[1])
rig = twin.load_rig("paper"); dev = "cuda:0" if torch.cuda.is_available() else "cpu"
cuda = dev.startswith("cuda")
model = load_network("pretrained", rig, dev)
learned, lines, pos, W, _ = _texels(rig, model, n, 0, dev, exact=False)
z = decode(model, learned, device=dev)
res = {}
for name, tf32, precision in (("float32", False, "float32"), ("split_tf32", False, "split_tf32"),
                              ("tf32", True, "float32"), ("float32_again", False, "float32")):
    torch.backends.cuda.matmul.allow_tf32 = tf32
    if cuda:
        torch.cuda.synchronize(); torch.cuda.reset_peak_memory_stats()
    t = time.perf_counter()
    ft = finetune(model, z, lines, W, FinetuneConfig(source="paper", holdout=(0,), device=dev, precision=precision))
    if cuda:
        torch.cuda.synchronize()
    dt = time.perf_counter() - t
    torch.backends.cuda.matmul.allow_tf32 = False
    sim = simulate_lines(model, ft.latent, W, batch=16384)
    # per-texel objective of pass 3 on the kept lines, evaluated in float32
    e = ((np.sqrt(np.maximum(sim[:, 1:], 0) + 1e-6) - np.sqrt(np.maximum(lines[:, 1:], 0) + 1e-6)) ** 2).sum((1, 2))
    held = np.abs(sim[:, 0] - lines[:, 0]).sum(1) / np.maximum(np.abs(lines[:, 0]).sum(1), 1e-12)
    res[name] = {"seconds": dt, "precision": precision, "allow_tf32": tf32,
                 "objective": {k: list(v) for k, v in ft.objective.items()},
                 "texel_objective_median": float(np.median(e)), "texel_objective_mean": float(e.mean()),
                 "heldout_line_rel_err_median": float(np.median(held)),
                 "peak_torch_allocated_gb": torch.cuda.max_memory_allocated() / 2**30 if cuda else None, "e": e}
a = res["float32"]["e"]
for name, r in res.items():
    e = r.pop("e")
    r["texel_objective_rel_diff_vs_float32_median"] = float(np.median(np.abs(e - a) / np.maximum(a, 1e-12)))
    r["median_objective_rel_diff"] = float((np.median(e) - np.median(a)) / np.median(a))
# the 2026-11-25 script's summary fields, and the same for split_tf32
runs = list(res)
res["texel_objective_rel_diff_tf32_vs_float32_median"] = res["tf32"]["texel_objective_rel_diff_vs_float32_median"]
res["texel_objective_rel_diff_split_tf32_vs_float32_median"] = \
    res["split_tf32"]["texel_objective_rel_diff_vs_float32_median"]
res["texel_objective_rel_diff_float32_rerun_median"] = \
    res["float32_again"]["texel_objective_rel_diff_vs_float32_median"]
res["median_objective_rel_diff"] = {k: res[k]["median_objective_rel_diff"] for k in runs}
res["texels"] = n; res["device"] = torch.cuda.get_device_name(0) if cuda else "cpu"; res["torch"] = torch.__version__
print(json.dumps(res, indent=1))
