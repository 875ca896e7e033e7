"""Issue #14 (docs/accuracy.md, "Open", fifteenth session): a sharper demosaic only where a much brighter
neighbour's light spills in. Refits one pipeline run's fit inputs (bilinear demosaic) with some texels' photos, in
both views, replaced by those of a second run of the same capture seed whose HDR merge demosaiced by Malvar-He-Cutler
2004 (`docs/bench/footprint_experiments_2026-11-25.py SAMPLE OUT mhc`: the same raw frames, so the same noise).

    python docs/bench/demosaic_hybrid_2026-11-27.py DUMP CAPTURE MHC_RUN MODE [MODE ...]

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py (the bilinear run); MHC_RUN: the Malvar-He-Cutler
run's output folder (its reconstruction/measurements.npz). The lumitexels stay the bilinear run's. MODE: base (none
replaced), all, d1 / d12 (the stock texels one / one or two texels from ink or foil, chosen from the truth: an
oracle), flag_RATIO_GROW (chosen from the bilinear fit itself: texels with an 8-neighbour whose fitted specular peak
mean(rho_s) / (alpha_x alpha_y) exceeds RATIO times their own, dilated GROW times). Fit with lambda_lines 400.
Prints one JSON line a mode. A record of how the numbers were measured, not part of the pipeline.
"""
import json, os, pickle, sys
from dataclasses import replace
import numpy as np, torch
from scipy import ndimage
import twin
import reconstruction.fitting as fitting
from reconstruction.extraction import TextureGrid
from reconstruction.metrics import map_errors, resample_maps, truth_coverage
from twin.capture.session import CaptureSession
torch.set_num_threads(1)
dump, cap, mrun, modes = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
d = pickle.load(open(dump, "rb"))
rig = twin.load_rig("mini")
grid = TextureGrid(*d["grid"]); R = grid.resolution
true_maps = CaptureSession.open(cap).ground_truth_maps()
truth = resample_maps(true_maps, grid.size_mm, R)
mask = truth_coverage(true_maps, grid.size_mm, R)
stock = truth.alpha[..., 0] > 0.3
dist = ndimage.distance_transform_cdt(stock, metric="chessboard")
CL = {"d0": ~stock, "d1": dist == 1, "d2": dist == 2, "d3-4": (dist >= 3) & (dist <= 4), "d5+": dist >= 5}
m = np.load(mrun + "/reconstruction/measurements.npz"); h = json.load(open(mrun + "/reconstruction/reconstruction.json"))["holdout_line"]
keep = [k for k in range(64) if k != h]
Lm = np.concatenate([m["lines"][:, keep], m["learned_photos"][:, 0]], 1); Sm = m["learned_photos"][:, 1]
res = d["res"]
peak = (res.rho_s.mean(1) / (res.alpha_x * res.alpha_y)).reshape(R, R)
def flagged(ratio, grow):
    P = np.pad(peak, 1)
    f = np.zeros((R, R), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                f |= P[1 + dr:1 + dr + R, 1 + dc:1 + dc + R] > ratio * peak
    return ndimage.binary_dilation(f, iterations=grow) if grow else f
for mode in modes:
    lines, sec = d["lines"].copy(), d["secondary"][0].copy()
    if mode == "base": sel = np.zeros((R, R), bool)
    elif mode == "all": sel = np.ones((R, R), bool)
    elif mode == "d1": sel = dist == 1
    elif mode == "d12": sel = (dist >= 1) & (dist <= 2)
    elif mode.startswith("flag"):
        _, r, g = mode.split("_"); sel = flagged(float(r), int(g))
    s = sel.reshape(-1)
    lines[s], sec[s] = Lm[s], Sm[s]
    cfg = replace(d["config"], lambda_lines=400.0)
    out = fitting.fit_ggx(rig, d["positions"], d["lumitexels"], lines=lines, line_weights=d["line_weights"],
                          secondary=(sec, d["secondary"][1]), grid_shape=d["grid_shape"], config=cfg)
    maps = fitting.to_maps(out, (R, R), grid.size_mm)
    me = map_errors(truth, maps, mask=mask)
    ex = np.abs(maps.alpha / truth.alpha - 1) * 100; sg = np.log(maps.alpha / truth.alpha).mean(-1)
    by = {k: [round(float(np.median(ex[..., 0][c])), 1), round(float(np.median(ex[..., 1][c])), 1), round(float(np.median(sg[c])), 3)] for k, c in CL.items()}
    fl = {k: round(float(sel[c].mean()), 2) for k, c in CL.items()}
    print(json.dumps({"dump": os.path.basename(dump), "mode": mode, "n_sel": int(sel.sum()), "sel_frac": fl,
                      **{k: round(me[k]["median"], 2) for k in ("alpha_x_pct", "alpha_y_pct", "rho_d_pct", "rho_s_pct", "normal_deg")},
                      **({"tangent": round(me["tangent_deg"]["median"], 2)} if "tangent_deg" in me and me["tangent_deg"].get("count") else {}), "by": by}), flush=True)
