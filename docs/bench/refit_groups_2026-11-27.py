"""Issue #14 (docs/accuracy.md, "Open"): the GGX fit of one pipeline run's inputs again, with its photo groups changed,
scored against the capture's true maps (the map medians `hemicube validate` reports).

    python docs/bench/refit_groups_2026-11-27.py DUMP CAPTURE VARIANT

DUMP: the fit's inputs pickled by `DUMP=... python docs/bench/footprint_coupled_2026-11-26.py SAMPLE OUT` (its
CAPTURE is OUT/capture). VARIANT: "all" (the pipeline's groups), "learned_only" (the primary group without its 63
line photos), "lines_only_primary" (without its learned-pattern photos), "no_secondary" (the secondary view's group
left out), "sec_xN" (the secondary view's photos repeated N times: its group's weight in the loss times about N),
"lamX" (FitConfig.lambda_lines = X). Prints one JSON line. A record of how the numbers were measured, not part of the
pipeline.
"""
import sys, json, pickle, time, os
import numpy as np, torch
import twin
import reconstruction.fitting as fitting
from reconstruction.extraction import TextureGrid
from reconstruction.metrics import map_errors, resample_maps, truth_coverage
from twin.capture.session import CaptureSession
torch.set_num_threads(int(os.environ.get("THREADS", "1")))
dump, cap, variant = sys.argv[1], sys.argv[2], sys.argv[3]
d = pickle.load(open(dump, "rb"))
rig = twin.load_rig("mini")
grid = TextureGrid(*d["grid"]); R = grid.resolution
session = CaptureSession.open(cap)
true_maps = session.ground_truth_maps()
truth = resample_maps(true_maps, grid.size_mm, R); mask = truth_coverage(true_maps, grid.size_mm, R)
lines, W, sec = d["lines"], d["line_weights"], d["secondary"]
nl = 63
if variant == "learned_only":      # the primary group without the line photos
    lines, W = lines[:, nl:], W[nl:]
elif variant == "lines_only_primary":
    lines, W = lines[:, :nl], W[:nl]
elif variant == "no_secondary":
    sec = None
elif variant.startswith("sec_x"):  # the secondary view's photos repeated: its group's weight times n
    n_rep = int(variant[5:])
    sec = (np.concatenate([sec[0]] * n_rep, axis=1), np.concatenate([sec[1]] * n_rep, axis=0))
cfg = d["config"]
if variant.startswith("lam"):
    from dataclasses import replace
    cfg = replace(cfg, lambda_lines=float(variant[3:]))
t = time.perf_counter()
res = fitting.fit_ggx(rig, d["positions"], d["lumitexels"], lines=lines, line_weights=W, secondary=sec,
                      grid_shape=d["grid_shape"], config=cfg)
m = map_errors(truth, fitting.to_maps(res, (R, R), grid.size_mm), mask=mask)
print(json.dumps({"dump": os.path.basename(dump), "variant": variant, "s": round(time.perf_counter() - t, 1),
                  **{k: round(m[k]["median"], 3) for k in ("normal_deg", "tangent_deg", "alpha_x_pct", "alpha_y_pct",
                                                           "rho_d_pct", "rho_s_pct")}}), flush=True)
