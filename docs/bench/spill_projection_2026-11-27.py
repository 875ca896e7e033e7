"""Issue #14 (docs/accuracy.md, "Open", fifteenth session): the per-texel mixture model, as nuisance columns. Fits one
pipeline run's fit inputs, then fits them again with each texel's photo groups (per view and colour) given, as extra
linear unknowns beside its albedos, the specular photos predicted from the first fit for every 8-neighbour whose
specular peak mean(rho_s) / (alpha_x alpha_y) exceeds RATIO (4) times its own: the spill of a brighter neighbour's
highlight through the footprint, with a free share. Variable projection: the columns are projected out of the photos
and their bases with the photos' Gauss-Newton weights, and those texels' photo residuals are linearised at the photos
(f'(M) (M_hat - M)); the second fit starts from the first's numbers.

    python docs/bench/spill_projection_2026-11-27.py DUMP CAPTURE      (MODE=each|sum, RATIO=4)

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py; needs the scratch hooks of
docs/bench/spill_projection_2026-11-27.patch applied to reconstruction/fitting.py (git apply, at 88f19fa).
MODE=each: one column per such neighbour; sum: their sum as one column. Prints the first and the second fit, split by
the stock texel's distance to ink or foil ([alpha_x %, alpha_y %, median log alpha ratio]). A record of how the
numbers were measured, not part of the pipeline.
"""
import json
import os
import sys
import time

import torch

import reconstruction.fitting as fitting
from paper_edges import Edges

torch.set_num_threads(int(os.environ.get("THREADS", "1")))
dump, cap = sys.argv[1], sys.argv[2]
RATIO = float(os.environ.get("RATIO", "4"))
E_ = Edges(dump, cap)
R = E_.R


def run():
    res, maps, m = E_.fit()
    tangent = m.get("tangent_deg")
    return res, {**{k: round(m[k]["median"], 3) for k in ("alpha_x_pct", "alpha_y_pct", "rho_d_pct", "rho_s_pct",
                                                          "normal_deg")},
                 "tangent": round(tangent.get("median", float("nan")), 3) if isinstance(tangent, dict) else None,
                 "by": E_.by_class(maps, 2)}


t=time.time()
res1, s1 = run()
print(json.dumps({"dump": os.path.basename(dump), "pass": 1, "s": round(time.time()-t,1), **s1}), flush=True)
last = fitting._LAST[0]
q1, spec = last["q"], last["spec"]
peak = res1.rho_s.mean(1) / (res1.alpha_x * res1.alpha_y)
P = peak.reshape(R, R)
n = R * R
cols = []  # per texel: list of neighbour indices
nb = []
for i in range(n):
    r, c = divmod(i, R); lst = []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if (dr or dc) and 0 <= r + dr < R and 0 <= c + dc < R and P[r + dr, c + dc] > RATIO * P[r, c]:
                lst.append((r + dr) * R + c + dc)
    nb.append(lst)
MODE = os.environ.get("MODE", "each")
if MODE == "sum":
    m = 1
else:
    m = max(1, max(len(l) for l in nb))
print("texels with columns", sum(1 for l in nb if l), "max", m, flush=True)
Ns = []
for S in spec:
    K = S.shape[2]
    N = torch.zeros(3, n, m, K)
    for i, l in enumerate(nb):
        for k, j in enumerate(l):
            N[:, i, 0 if MODE == "sum" else k] += S[:, j]
    Ns.append(N)
fitting._SPILL[0] = Ns
fitting._START[0] = q1
t=time.time()
res2, s2 = run()
print(json.dumps({"dump": os.path.basename(dump), "pass": 2, "ratio": RATIO, "mode": MODE, "s": round(time.time()-t,1), **s2}), flush=True)
