"""The GGX fit before and after reconstruction.fit_sums on the same paper-rig texels on one GPU (issue #12): time,
the device's used memory, the per-texel losses and the fitted roughness. A measurement script, not part of the
package. The fit before is commit 2ad922d's, saved beside the current one first:

    git show 2ad922d:reconstruction/fitting.py > reconstruction/_fitting_orig.py
    PYTHONPATH=. python docs/bench/fit_sums_vs_before_2026-11-25.py 16384     # writes $OUT/cmp12_16384.json

Output of the run on an H100, 2026-11-25: fit_sums_vs_before_paper_h100_16384_2026-11-25.json ("new_warm" is the
first call, with the kernels' compilation)."""
import json, os, sys, time
sys.path.insert(0, os.getcwd())
import numpy as np, torch, twin
from reconstruction import bench as B, fitting as F, _fitting_orig as O
from reconstruction.pipeline import load_network
from reconstruction.latents import decode
from reconstruction.finetune import FinetuneConfig, finetune, decode_rgb
from twin.bench import PeakDeviceMemory
out = os.environ.get("OUT", "/tmp/out"); dev = "cuda:0"
n = int(sys.argv[1]) if len(sys.argv) > 1 else 16384
rig = twin.load_rig("paper"); model = load_network("pretrained", rig, dev)
learned, lines, pos, W, _ = B._texels(rig, model, n, 0, dev, exact=False)
z = decode(model, learned, device=dev)
ft = finetune(model, z, lines, W, FinetuneConfig(holdout=(0,), device=dev))
lumi = decode_rgb(model, ft.latent)
res = {"texels": n, "device": torch.cuda.get_device_name(0)}
fits = {}
for name, M in (("new_warm", F), ("new", F), ("old", O)):
    torch.cuda.empty_cache(); torch.cuda.reset_peak_memory_stats()
    with PeakDeviceMemory(dev) as mem:
        torch.cuda.synchronize(); t = time.perf_counter()
        fit = M.fit_ggx(rig, pos, lumi, lines=lines, line_weights=W, config=M.FitConfig(device=dev))
        torch.cuda.synchronize(); dt = time.perf_counter() - t
    fits[name] = fit
    res[name] = {"s": dt, "peak_used_mib": mem.peak_mib, "max_alloc_mib": torch.cuda.max_memory_allocated() / 2**20,
                 "init_s": fit.info["init_seconds"], "s_per_iteration": fit.info["seconds_per_iteration"],
                 "median_loss": float(np.median(fit.info["texel_loss"])), "mean_loss": float(np.mean(fit.info["texel_loss"])),
                 "history": fit.history}
    print(name, {k: v for k, v in res[name].items() if k != "history"}, flush=True)
a, b = fits["new"], fits["old"]
la, lb = a.info["texel_loss"], b.info["texel_loss"]
res["median_rel_loss_diff_new_vs_old"] = float(np.median((la - lb) / lb))
res["median_loss_ratio_new_over_old"] = float(np.median(la) / np.median(lb))
for k in ("alpha_x", "alpha_y"):
    d = np.abs(np.log(getattr(a, k) / getattr(b, k)))
    res[f"{k}_abs_log_ratio_median_p99"] = [float(np.median(d)), float(np.quantile(d, 0.99))]
print(json.dumps({k: v for k, v in res.items() if not isinstance(v, dict)}, indent=1))
json.dump(res, open(f"{out}/cmp12_{n}.json", "w"), indent=1)
