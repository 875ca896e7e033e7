"""Issue #14 (docs/accuracy.md, "Open", sixteenth session): which property of paper@9003's stock photo errors moves
its fitted alpha. Refits one pipeline run's fit inputs (before step 12's refit) with the photos of the stock two or
more texels from ink or foil (d2+) rebuilt from the exact ones and the measured errors, changed as MODE says; the ink
and the texels next to it (d0, d1) keep their measured photos unless MODE says otherwise.

    python docs/bench/stock_errors_2026-11-27.py DUMP CAPTURE MODE [ARG]

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py. MODE:
  gains          no fit: each texel's static gain per view and colour (median over photos of measured / exact), its
                 spread per distance class and the spread of the two views' difference;
  base           the measured photos as they are;
  static_both    the d2+ texels' static gains divided out of both views (an oracle: PRNU through demosaic and lookup);
  static_ratio   only the secondary view's gain relative to the primary's divided out;
  synth [S]      every texel: exact photos with iid 0.5% noise, times a static gain per texel, view and colour of
                 relative sd S (none without S);
  real           d2+: exact x (1 + the measured relative error, static gain out); d0, d1: iid 0.5% noise;
  texels         the same with the errors permuted among the d2+ texels, per photo and colour;
  photos         the same with each texel's errors permuted among its photos;
  signs          the same with each error's sign drawn at random;
  demean         the same with the mean error over the d2+ texels taken out per photo and colour;
  shrink F       the measured photos, the d2+ errors against exact scaled by F (F = 0.71: the noise of twice the
                 frames where the stock is measured).
Prints one JSON line. A record of how the numbers were measured, not part of the pipeline.
"""
import json
import sys

import numpy as np
import torch

from paper_edges import Edges

torch.set_num_threads(1)
E = Edges(sys.argv[1], sys.argv[2])
mode, arg = sys.argv[3], (sys.argv[4] if len(sys.argv) > 4 else None)
d = E.d
views = [(d["lines"], E.exact(d["line_weights"], E.cams[0])), (d["secondary"][0], E.exact(d["secondary"][1], E.cams[1]))]
stock2 = (E.dist >= 2).reshape(-1)
rng = np.random.default_rng(0)


def gain(M, X):
    return np.median(M / np.maximum(X, 1e-6), axis=1, keepdims=True)  # (N, 1, 3)


if mode == "gains":
    (Mp, Xp), (Ms, Xs) = views
    lp, ls = np.log(gain(Mp, Xp))[:, 0], np.log(gain(Ms, Xs))[:, 0]
    for name, c in E.classes.items():
        s = c.reshape(-1)
        diff = ls[s] - lp[s]
        pct = lambda a: [round(float(x) * 100, 3) for x in a.std(0)]  # noqa: E731
        print(json.dumps({"class": name, "n": int(s.sum()), "primary_sd_pct": pct(lp[s]), "secondary_sd_pct": pct(ls[s]),
                          "views_difference_sd_pct": pct(diff),
                          "difference_colour_correlation": [round(float(x), 2) for x in np.corrcoef(diff.T)[0, 1:]]}))
    sys.exit()

photos = []
for v, (M, X) in enumerate(views):
    M = M.copy()
    g = gain(M, X)
    if mode == "static_both":
        M[stock2] /= g[stock2]
    elif mode == "static_ratio":
        if v == 1:
            M[stock2] *= (gain(*views[0]) / g)[stock2]
    elif mode == "synth":
        M = X * (1 + 0.005 * rng.standard_normal(X.shape))
        if arg is not None:
            M *= 1 + float(arg) * rng.standard_normal((len(X), 1, 3))
    elif mode == "shrink":
        M[stock2] = X[stock2] + float(arg) * (M[stock2] - X[stock2])
    elif mode in ("real", "texels", "photos", "signs", "demean"):
        r = M / np.maximum(X, 1e-6) - 1
        r = r - np.median(r, axis=1, keepdims=True)  # the static gain out
        rs = r[stock2]
        if mode == "texels":
            for k in range(rs.shape[1]):
                for c in range(3):
                    rs[:, k, c] = rs[rng.permutation(len(rs)), k, c]
        elif mode == "photos":
            for i in range(len(rs)):
                rs[i] = rs[i, rng.permutation(rs.shape[1])]
        elif mode == "signs":
            rs = np.abs(rs) * np.sign(rng.standard_normal(rs.shape))
        elif mode == "demean":
            rs = rs - rs.mean(axis=0, keepdims=True)
        full = 0.005 * rng.standard_normal(r.shape)
        full[stock2] = rs
        M = X * (1 + full)
    elif mode != "base":
        raise SystemExit(f"unknown mode {mode!r}")
    photos.append(M.astype(np.float32))
_, maps, m = E.fit(*photos)
print(json.dumps({"dump": sys.argv[1].rsplit("/", 1)[-1], "mode": mode, "arg": arg,
                  **{k: round(m[k]["median"], 2) for k in ("alpha_x_pct", "alpha_y_pct", "rho_s_pct")},
                  "by_distance": E.by_class(maps)}), flush=True)
