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
import json
import os
import sys

import numpy as np
import torch
from scipy import ndimage

from paper_edges import Edges
from reconstruction.pipeline import spill_texels

torch.set_num_threads(1)
dump, cap, mrun, modes = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
E_ = Edges(dump, cap)
d, R, dist = E_.d, E_.R, E_.dist
m = np.load(mrun + "/reconstruction/measurements.npz")
h = json.load(open(mrun + "/reconstruction/reconstruction.json"))["holdout_line"]
keep = [k for k in range(64) if k != h]
Lm = np.concatenate([m["lines"][:, keep], m["learned_photos"][:, 0]], 1)
Sm = m["learned_photos"][:, 1]
for mode in modes:
    lines, sec = d["lines"].copy(), d["secondary"][0].copy()
    if mode == "base":
        sel = np.zeros((R, R), bool)
    elif mode == "all":
        sel = np.ones((R, R), bool)
    elif mode == "d1":
        sel = dist == 1
    elif mode == "d12":
        sel = (dist >= 1) & (dist <= 2)
    elif mode.startswith("flag"):  # the pipeline's rule (ReconstructConfig.spill_ratio) on the bilinear fit
        _, r, g = mode.split("_")
        sel = spill_texels(d["res"], (R, R), float(r))
        sel = ndimage.binary_dilation(sel, iterations=int(g)) if int(g) else sel
    s = sel.reshape(-1)
    lines[s], sec[s] = Lm[s], Sm[s]
    _, maps, me = E_.fit(lines, sec)
    print(json.dumps({"dump": os.path.basename(dump), "mode": mode, "n_sel": int(sel.sum()),
                      "sel_frac": {k: round(float(sel[c].mean()), 2) for k, c in E_.classes.items()},
                      **{k: round(me[k]["median"], 2) for k in ("alpha_x_pct", "alpha_y_pct", "rho_d_pct", "rho_s_pct",
                                                                "normal_deg")},
                      **({"tangent": round(me["tangent_deg"]["median"], 2)}
                         if "tangent_deg" in me and me["tangent_deg"].get("count") else {}),
                      "by": E_.by_class(maps, 1)}), flush=True)
