"""Issue #14 (docs/accuracy.md, "Open", fifteenth session): is the open stock's per-photo error common to its texels
what biases its alpha? Refits one pipeline run's fit inputs with every texel's photos divided by (1 + the open stock's
median relative deviation from the exact photos), per photo and colour ("flat"), optionally with the stock within
1-4 texels of ink or foil given exact photos first ("d14_flat"; the division then applies to those too).

    python docs/bench/open_stock_flattened_2026-11-27.py DUMP CAPTURE MODE [MODE ...]

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py; photo weight 400. Prints one JSON line a mode, with
[alpha_x %, alpha_y %, median log alpha ratio] by distance class. A record of how the numbers were measured.
"""
import os, pickle, sys, json
from dataclasses import replace
import numpy as np, torch
from scipy import ndimage
torch.set_num_threads(1)
import twin
import reconstruction.fitting as fitting
from reconstruction.data import LUMITEXEL_SCALE
from reconstruction.extraction import TextureGrid
from reconstruction.metrics import map_errors, resample_maps, truth_coverage
from reconstruction.validation import _map_params
from twin.capture.session import CaptureSession
dump, cap = sys.argv[1], sys.argv[2]
d = pickle.load(open(dump, "rb")); rig = twin.load_rig("mini")
grid = TextureGrid(*d["grid"]); R = grid.resolution
tm = CaptureSession.open(cap).ground_truth_maps()
truth = resample_maps(tm, grid.size_mm, R); mask = truth_coverage(tm, grid.size_mm, R)
stock = truth.alpha[..., 0] > 0.3
dist = ndimage.distance_transform_cdt(stock, metric="chessboard").reshape(-1)
upper = np.flatnonzero(~np.asarray(rig.is_bottom))
def exact(wu, camera):
    W = np.zeros((wu.shape[0], len(rig.is_bottom), 3), np.float32); W[:, upper] = wu
    return twin.measurements(rig, d["positions"].astype(np.float32), patterns=W, camera=camera, convention="physical",
                             visibility=True, device="cpu", transparency=np.zeros(len(d["positions"])), **_map_params(truth)) * np.float32(LUMITEXEL_SCALE)
cams = list(rig.cameras)[:2]
ex_p, ex_s = exact(d["line_weights"], cams[0]), exact(d["secondary"][1], cams[1])
open_ = dist >= 5
def common(M, E):  # per photo and channel: the median relative deviation over the open stock
    return np.median(M[open_] / E[open_] - 1, axis=0)
CL = {"d1": dist == 1, "d2": dist == 2, "d3-4": (dist >= 3) & (dist <= 4), "d5+": dist >= 5}
for mode in sys.argv[3:]:
    lines, sec = d["lines"].copy(), d["secondary"][0].copy()
    edge = (dist >= 1) & (dist <= 4)
    if "d14" in mode:
        lines[edge], sec[edge] = ex_p[edge], ex_s[edge]
    if "flat" in mode:  # the open stock's per-photo common deviation divided out of every texel's photos
        lines = lines / (1 + common(d["lines"], ex_p))[None]
        sec = sec / (1 + common(d["secondary"][0], ex_s))[None]
    cfg = replace(d["config"], lambda_lines=400.0)
    res = fitting.fit_ggx(rig, d["positions"], d["lumitexels"], lines=lines, line_weights=d["line_weights"],
                          secondary=(sec, d["secondary"][1]), grid_shape=d["grid_shape"], config=cfg)
    maps = fitting.to_maps(res, (R, R), grid.size_mm)
    m = map_errors(truth, maps, mask=mask)
    ex = np.abs(maps.alpha / truth.alpha - 1) * 100; sg = np.log(maps.alpha / truth.alpha).mean(-1)
    by = {k: [round(float(np.median(ex[..., 0].reshape(-1)[c])), 1), round(float(np.median(ex[..., 1].reshape(-1)[c])), 1), round(float(np.median(sg.reshape(-1)[c])), 3)] for k, c in CL.items()}
    print(json.dumps({"dump": os.path.basename(dump), "mode": mode, **{k: round(m[k]["median"], 2) for k in ("alpha_x_pct", "alpha_y_pct", "rho_s_pct")}, "by": by}), flush=True)
