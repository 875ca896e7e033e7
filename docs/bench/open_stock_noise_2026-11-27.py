"""Issue #14 (docs/accuracy.md, "Open", fifteenth session): the open stock's photo errors per texel (5 or more texels
from ink or foil): their robust spread by the photo's level, their skew, and their correlation between neighbouring
texels along the grid's rows and columns, per view (each texel's own gain divided out first).

    python docs/bench/open_stock_noise_2026-11-27.py DUMP CAPTURE

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py. A record of how the numbers were measured.
"""
import sys

import numpy as np
import torch

from paper_edges import Edges

torch.set_num_threads(1)
E_ = Edges(sys.argv[1], sys.argv[2])
d, R, cams, exact = E_.d, E_.R, E_.cams, E_.exact
dist = E_.dist.reshape(-1)
sel = dist >= 5
for label, M, wu, cam in (("primary", d["lines"], d["line_weights"], cams[0]), ("secondary", d["secondary"][0], d["secondary"][1], cams[1])):
    E = exact(wu, cam)
    r = (M[sel] / E[sel] - 1)
    r = r - np.median(r, axis=1, keepdims=True)  # each texel's own gain out (PRNU, albedo texture)
    sd = 1.4826 * np.median(np.abs(r - np.median(r, 0)), 0)  # (K, 3) robust sd per photo
    lvl = np.median(E[sel], 0)
    o = np.argsort(lvl.mean(1))
    q = len(o) // 4
    print(label, "robust sd % by photo level quartile (dim -> bright):", [round(float(sd[o[i*q:(i+1)*q]].mean()*100), 3) for i in range(4)],
          "level quartile medians:", [round(float(np.median(lvl[o[i*q:(i+1)*q]])), 2) for i in range(4)])
    # skew: mean minus median per photo
    sk = (r.mean(0) - np.median(r, 0))
    print("   mean - median per photo (% RMS):", round(float(np.sqrt((sk**2).mean())*100), 3), " mean over photos", round(float(sk.mean()*100), 4))
    # spatial correlation of residual between horizontal neighbours in the open stock
    full = np.full((R*R,) + r.shape[1:], np.nan); full[sel] = r
    F = full.reshape(R, R, -1)
    for name, (a, b) in (("along a row (x)", (F[:, :-1], F[:, 1:])), ("along a column (y)", (F[:-1], F[1:])),
                         ("two apart along x", (F[:, :-2], F[:, 2:])), ("two apart along y", (F[:-2], F[2:])),
                         ("diagonal", (F[:-1, :-1], F[1:, 1:]))):
        a, b = a.reshape(-1, F.shape[2]), b.reshape(-1, F.shape[2])
        ok = np.isfinite(a).all(1) & np.isfinite(b).all(1)
        print(f"   correlation {name}: {np.corrcoef(a[ok].ravel(), b[ok].ravel())[0, 1]:.3f}")
