"""Issue #14 (docs/accuracy.md, "Open", fifteenth session): is the open stock's per-photo error common to its texels
what biases its alpha? Refits one pipeline run's fit inputs with every texel's photos divided by (1 + the open stock's
median relative deviation from the exact photos), per photo and colour ("flat"), optionally with the stock within
1-4 texels of ink or foil given exact photos first ("d14_flat"; the division then applies to those too).

    python docs/bench/open_stock_flattened_2026-11-27.py DUMP CAPTURE MODE [MODE ...]

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py; photo weight 400. Prints one JSON line a mode, with
[alpha_x %, alpha_y %, median log alpha ratio] by distance class. A record of how the numbers were measured.
"""
import json
import os
import sys

import numpy as np
import torch

from paper_edges import Edges

torch.set_num_threads(1)
dump, cap = sys.argv[1], sys.argv[2]
E_ = Edges(dump, cap)
d, cams, exact = E_.d, E_.cams, E_.exact
dist = E_.dist.reshape(-1)
ex_p, ex_s = exact(d["line_weights"], cams[0]), exact(d["secondary"][1], cams[1])
open_ = dist >= 5


def common(M, E):  # per photo and channel: the median relative deviation over the open stock
    return np.median(M[open_] / E[open_] - 1, axis=0)


classes = {k: v for k, v in E_.classes.items() if k != "d0"}
for mode in sys.argv[3:]:
    lines, sec = d["lines"].copy(), d["secondary"][0].copy()
    edge = (dist >= 1) & (dist <= 4)
    if "d14" in mode:
        lines[edge], sec[edge] = ex_p[edge], ex_s[edge]
    if "flat" in mode:  # the open stock's per-photo common deviation divided out of every texel's photos
        lines = lines / (1 + common(d["lines"], ex_p))[None]
        sec = sec / (1 + common(d["secondary"][0], ex_s))[None]
    _, maps, m = E_.fit(lines, sec)
    print(json.dumps({"dump": os.path.basename(dump), "mode": mode,
                      **{k: round(m[k]["median"], 2) for k in ("alpha_x_pct", "alpha_y_pct", "rho_s_pct")},
                      "by": E_.by_class(maps, 1, classes)}), flush=True)
