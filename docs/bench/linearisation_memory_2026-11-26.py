"""Peak torch memory and time of one Gauss-Newton system (reconstruction.fitting._normal_equations) of N synthetic
texels with both views' photos, with _linearisation as at 0007355 and now (2026-11-26, issue #12). It needs 0007355's
reconstruction/fitting.py copied beside the current one as reconstruction/fitting_old.py (not kept in the repository).
Usage: python docs/bench/linearisation_memory_2026-11-26.py RIG N DEVICE; raw: linearisation_memory_paper_h100_16384_2026-11-26.json"""
import json, sys, time
import numpy as np
import torch
import twin
from reconstruction import fitting, fitting_old

rig_name, n, dev = sys.argv[1], int(sys.argv[2]), sys.argv[3]
rig = twin.load_rig(rig_name)
upper = np.flatnonzero(~np.asarray(rig.is_bottom))
L = upper.size
rng = np.random.default_rng(0)
s = rig.sample
uv = rng.uniform(-20, 20, (n, 2))
pos = (np.asarray(s.origin) + uv[:, :1] * np.asarray(s.x_axis) + uv[:, 1:] * np.asarray(s.y_axis)).astype(np.float32)
lumi = rng.uniform(0.0, 2.0, (n, L, 3)).astype(np.float32)
K1, K2 = 127, 64
lines = rng.uniform(0.1, 2.0, (n, K1, 3)).astype(np.float32)
W1 = rng.uniform(0.0, 1.0, (K1, L, 3)).astype(np.float32)
sec = rng.uniform(0.1, 2.0, (n, K2, 3)).astype(np.float32)
W2 = rng.uniform(0.0, 1.0, (K2, L, 3)).astype(np.float32)
out = {"rig": rig_name, "texels": n, "device": torch.cuda.get_device_name(0) if dev == "cuda" else "cpu"}
res = {}
for name, mod in (("0007355", fitting_old), ("now", fitting), ("0007355 again", fitting_old), ("now again", fitting)):
    prob = mod._problem(rig, pos, lumi, lines, W1, None, mod.FitConfig(device=dev), secondary=(sec, W2))
    q = torch.zeros(n, 5, device=dev)
    q[:, 3:5] = np.log(0.1)
    if dev == "cuda":
        torch.cuda.synchronize(); torch.cuda.empty_cache(); torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    t = time.perf_counter()
    A, g, loss = mod._normal_equations(prob, q)
    if dev == "cuda":
        torch.cuda.synchronize()
    dt = time.perf_counter() - t
    peak = (torch.cuda.max_memory_allocated() - base) / 2 ** 30 if dev == "cuda" else None
    res[name] = {"seconds": dt, "peak_gib_above_inputs": peak, "A": A.double().cpu(), "loss": loss.double().cpu()}
    out[name] = {"seconds": round(dt, 4), "peak_torch_gib_above_inputs": peak}
    del prob, A, g, loss
out["max_abs_diff_A_rel"] = float((res["now"]["A"] - res["0007355"]["A"]).abs().max() / res["0007355"]["A"].abs().max())
out["max_abs_diff_loss"] = float((res["now"]["loss"] - res["0007355"]["loss"]).abs().max())
print(json.dumps(out, indent=1))
# the two must compute the same system (they run the same operations in another order): exit non-zero if not
if out["max_abs_diff_A_rel"] > 1e-6 or out["max_abs_diff_loss"] > 1e-6 * float(res["0007355"]["loss"].abs().max()):
    sys.exit("the two _linearisation variants computed different systems")
