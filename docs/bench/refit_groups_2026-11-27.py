"""Issue #14 (docs/accuracy.md, "Open"): the GGX fit of one pipeline run's inputs again, with its photo groups changed,
scored against the capture's true maps (the map medians `hemicube validate` reports).

    python docs/bench/refit_groups_2026-11-27.py DUMP CAPTURE VARIANT

DUMP: the fit's inputs pickled by `DUMP=... python docs/bench/footprint_coupled_2026-11-26.py SAMPLE OUT` (its
CAPTURE is OUT/capture). VARIANT: "all" (the pipeline's groups), "learned_only" (the primary group without its 63
line photos), "lines_only_primary" (without its learned-pattern photos), "no_secondary" (the secondary view's group
left out), "sec_xN" (the secondary view's photos repeated N times: its group's weight in the loss times about N),
"lamX" (FitConfig.lambda_lines = X), "winsorK" (fit, then each photo value's residual in the loss's log1p space
clipped at K robust sigmas of its group, 1.4826 x its MAD, and fit again: one round of a Huber-like reweighting; env
LAM sets lambda_lines for it). Prints one JSON line. A record of how the numbers were measured, not part of the
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
from dataclasses import replace
cfg = replace(d["config"], lambda_lines=float(os.environ.get("LAM", d["config"].lambda_lines)))
if variant.startswith("lam"):
    cfg = replace(cfg, lambda_lines=float(variant[3:]))
t = time.perf_counter()
res = fitting.fit_ggx(rig, d["positions"], d["lumitexels"], lines=lines, line_weights=W, secondary=sec,
                      grid_shape=d["grid_shape"], config=cfg)
if variant.startswith("winsor"):
    k = float(variant[6:])
    prob = fitting._problem(rig, d["positions"], d["lumitexels"], lines, W, d["grid_shape"], cfg, sec)
    geom = {q: torch.as_tensor(getattr(res, q), dtype=torch.float32) for q in ("normal", "tangent", "alpha_x", "alpha_y")}
    with torch.no_grad():
        val = fitting._grey(prob, geom)
        pb = fitting._photo_bases(prob, geom, val)
        hats = fitting._predicted(pb, fitting._projected(prob, val, pb)[2])
    clipped = []
    for g, M_hat in zip(prob.photos, hats):
        fh = fitting._f(M_hat, cfg.loss, g.scale)
        r = g.M_f - fh  # (3, n, K): measured minus predicted
        sig = 1.4826 * (r - r.median()).abs().median()
        Mf = fh + r.clamp(-k * sig, k * sig)
        clipped.append((torch.expm1(Mf) if cfg.loss == "log1p" else Mf * g.scale).permute(1, 2, 0).numpy())
    lines, sec = clipped[0], (clipped[1], sec[1])
    res = fitting.fit_ggx(rig, d["positions"], d["lumitexels"], lines=lines, line_weights=W, secondary=sec,
                          grid_shape=d["grid_shape"], config=cfg)
m = map_errors(truth, fitting.to_maps(res, (R, R), grid.size_mm), mask=mask)
print(json.dumps({"dump": os.path.basename(dump), "variant": variant, "lambda_lines": cfg.lambda_lines, "s": round(time.perf_counter() - t, 1),
                  **{k: round(m[k]["median"], 3) for k in ("normal_deg", "tangent_deg", "alpha_x_pct", "alpha_y_pct",
                                                           "rho_d_pct", "rho_s_pct")}}), flush=True)
