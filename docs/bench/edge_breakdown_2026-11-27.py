"""Issue #14 (docs/accuracy.md, "Open", fourteenth session): where on paper's stock the alpha error is, and which
texels' photos cause it. Refits one pipeline run's fit inputs with some texels' photos replaced by the exact ones,
and splits every score by the texel's distance to the nearest ink or foil texel.

    python docs/bench/edge_breakdown_2026-11-27.py DUMP CAPTURE MODE [MODE ...]

DUMP: the fit's inputs pickled by `DUMP=... python docs/bench/footprint_coupled_2026-11-26.py SAMPLE OUT` (its
CAPTURE is OUT/capture); the fit is run with the pipeline's configuration for four frames (lambda_lines 400, what
`hemicube validate` gives to the last digit on the same captures). MODE:
  photos             the measured photos against the exact ones, per photo group and distance class (no fit);
  base               the pipeline's fit of the measured photos;
  swap_SEL_VIEWS     the same with the photos of the texels SEL replaced by the exact photos, in the primary view (p),
                     the secondary view (s) or both (ps); SEL: all, d1 (stock texels next to ink or foil), d12 (one
                     or two texels from it), d2 (two texels from it), not1 (every texel but d1);
  weight_K_W         (needs the scratch hooks of docs/bench/edge_experiments_2026-11-27.patch applied to
                     reconstruction/fitting.py) the stock texels within K of ink or foil (chosen from the truth: an
                     oracle) with their data weighted W in the joint prior of roughness and albedos;
  view_K_VIEWS_W     (the same hooks) their photos of the primary (p), the secondary (s) or both views (ps) weighted W
                     in every stage of the fit.
With the hooks, the environment also sets the joint prior: TAU (FitConfig.alpha_prior, 0.1), ANISO (the prior's
weight on the anisotropy's two numbers relative to the mean log alpha's, 1) and ISO=1 (the joint prior started from
each texel's mean log alpha, isotropic).
"Exact": the forward model at the texel centre with the true maps as the metrics resample them (`twin.measurements`,
the capture's LED weights, both cameras). Stock: true alpha > 0.3 (paper's stock is 0.45-0.52, its ink and foil below
0.1); a stock texel's distance is the chessboard distance in texels to the nearest texel that is not stock; "d0" is
the ink and foil. Prints one JSON line a mode. A record of how the numbers were measured, not part of the pipeline.
"""
import json
import os
import sys

import numpy as np
import torch

import reconstruction.fitting as fitting
from paper_edges import Edges

torch.set_num_threads(int(os.environ.get("THREADS", "1")))
dump, cap, modes = sys.argv[1], sys.argv[2], sys.argv[3:]
E_ = Edges(dump, cap)
d, stock, dist, CLASSES, cams = E_.d, E_.stock, E_.dist, E_.classes, E_.cams
ex_p, ex_s = E_.exact(d["line_weights"], cams[0]), E_.exact(d["secondary"][1], cams[1])
nl = 63  # the kept line photos come first in the primary group


def photos_table():
    out = {}
    for label, M, E in (("primary lines", d["lines"][:, :nl], ex_p[:, :nl]),
                        ("primary learned", d["lines"][:, nl:], ex_p[:, nl:]),
                        ("secondary learned", d["secondary"][0], ex_s)):
        r = M / np.maximum(E, 1e-6) - 1
        row = {}
        for k in ("d1", "d2", "d3-4", "d5+"):
            v = r[CLASSES[k].reshape(-1)]
            row[k] = {"median_pct": round(float(np.median(v)) * 100, 3),
                      "structured_rms_pct": round(float(np.sqrt(np.mean(np.median(v, axis=0) ** 2))) * 100, 3),
                      "robust_sd_pct": round(float(1.4826 * np.median(np.abs(v - np.median(v)))) * 100, 3)}
        out[label] = row
    return out


def fit(mode):
    lines, sec = d["lines"].copy(), d["secondary"][0].copy()
    if mode.startswith("swap_"):
        _, which, views = mode.split("_")
        sel = {"all": np.ones_like(stock), "d1": dist == 1, "d12": (dist >= 1) & (dist <= 2),
               "not1": dist != 1, "d14": (dist >= 1) & (dist <= 4), "d2": dist == 2}[which].reshape(-1)
        if "p" in views:
            lines[sel] = ex_p[sel]
        if "s" in views:
            sec[sel] = ex_s[sel]
    elif mode.startswith("weight_"):
        if not hasattr(fitting, "_DATA_WEIGHT"):
            raise SystemExit("weight_K_W needs docs/bench/edge_experiments_2026-11-27.patch applied")
        _, k, w = mode.split("_")
        fitting._DATA_WEIGHT[0] = torch.as_tensor(np.where(stock & (dist <= int(k)), float(w), 1.0).reshape(-1))
    elif mode.startswith("view_"):
        if not hasattr(fitting, "_TW"):
            raise SystemExit("view_K_VIEWS_W needs docs/bench/edge_experiments_2026-11-27.patch applied")
        _, k, views, w = mode.split("_")
        tw = torch.as_tensor(np.where(stock & (dist <= int(k)), float(w), 1.0).reshape(-1), dtype=torch.float32)
        fitting._TW[0] = [tw if "p" in views else None, tw if "s" in views else None]
    elif mode != "base":
        raise SystemExit(f"unknown mode {mode!r}")
    if hasattr(fitting, "_ANISO"):
        fitting._ANISO[0], fitting._ISO_START[0] = float(os.environ.get("ANISO", "1")), os.environ.get("ISO") == "1"
    _, maps, m = E_.fit(lines, sec, alpha_prior=float(os.environ.get("TAU", "0.1")))
    by = {k: {"n": int(CLASSES[k].sum()), "alpha_x_pct": ax, "alpha_y_pct": ay, "log_alpha_bias": bias}
          for k, (ax, ay, bias) in E_.by_class(maps, 2).items()}
    if hasattr(fitting, "_DATA_WEIGHT"):
        fitting._DATA_WEIGHT[0], fitting._TW[0] = None, None
    return {**{k: round(m[k]["median"], 3) for k in ("alpha_x_pct", "alpha_y_pct", "rho_d_pct", "rho_s_pct",
                                                     "normal_deg")}, "by_distance": by}


for mode in modes:
    rec = photos_table() if mode == "photos" else fit(mode)
    env = {k: os.environ[k] for k in ("TAU", "ANISO", "ISO") if k in os.environ}
    print(json.dumps({"dump": os.path.basename(dump), "mode": mode, **env, **rec}), flush=True)
