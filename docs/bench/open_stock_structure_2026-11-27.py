"""Issue #14 (docs/accuracy.md, "Open", fifteenth session): how large paper's stock lobe is in each photo, and the
photos' error common to every open-stock texel (5 or more texels from ink or foil), per photo.

    python docs/bench/open_stock_structure_2026-11-27.py DUMP CAPTURE

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py (the capture's folder beside its reconstruction/).
Prints, per view: the per-photo median of measured / exact - 1 over the open stock, its correlation with the photo's
specular fraction and level, a split-half estimate of the structure common to the texels (the covariance of two
random halves' per-photo medians), the specular fraction's size and spread over the photos, and the correlation of
the primary view's per-photo error with its exposures. A record of how the numbers were measured.
"""
import json
import os
import sys

import numpy as np
import torch

from paper_edges import Edges
from twin.capture.plan import indices_of
from twin.capture.session import CaptureSession, photo_stem

torch.set_num_threads(1)
dump, cap = sys.argv[1], sys.argv[2]
E_ = Edges(dump, cap)
d, cams, exact = E_.d, E_.cams, E_.exact
dist = E_.dist.reshape(-1)
n = len(d["positions"])
for label, M, wu, cam in (("primary", d["lines"], d["line_weights"], cams[0]), ("secondary", d["secondary"][0], d["secondary"][1], cams[1])):
    E = exact(wu, cam)
    Es = exact(wu, cam, rho_d=np.zeros((n, 3), np.float32))  # specular part
    sel = dist >= 5
    r = M[sel] / E[sel] - 1            # (m, K, 3)
    sf = (Es[sel] / E[sel])            # specular fraction
    med = np.median(r, axis=0)         # (K, 3) per photo and channel
    rng = np.random.default_rng(0); perm = rng.permutation(r.shape[0]); h = r.shape[0] // 2
    m1, m2 = np.median(r[perm[:h]], 0), np.median(r[perm[h:]], 0)
    print(" split halves: rms of each", round(float(np.sqrt((m1**2).mean())*100),3), round(float(np.sqrt((m2**2).mean())*100),3),
          "covariance (common structure^2) -> rms", round(float(np.sqrt(max(((m1-m1.mean())*(m2-m2.mean())).mean(),0)))*100,3),
          "corr", round(float(np.corrcoef(m1.ravel(), m2.ravel())[0,1]),2))
    spec_var = np.median(sf, axis=0); print(" spec fraction per photo: median", round(float(np.median(spec_var))*100,2), "% , rms variation over photos", round(float(spec_var.std())*100,3), "%")
    fr = np.median(sf, axis=0)
    lvl = np.median(E[sel], axis=0)
    print(label, "texels", int(sel.sum()))
    print(" per-photo median dev (%): mean", round(float(med.mean()*100),3), "rms", round(float(np.sqrt((med**2).mean())*100),3))
    for c in range(3):
        cc = np.corrcoef(med[:, c], fr[:, c])[0, 1]; cl = np.corrcoef(med[:, c], np.log(lvl[:, c]))[0, 1]
        # regress dev on spec fraction
        A = np.stack([np.ones_like(fr[:, c]), fr[:, c]], 1); coef = np.linalg.lstsq(A, med[:, c], rcond=None)[0]
        print(f"  ch{c}: corr(dev, spec frac) {cc:.2f}  corr(dev, log level) {cl:.2f}  dev = {coef[0]*100:.3f}% + {coef[1]*100:.3f}% x specfrac; specfrac range {fr[:,c].min():.3f}-{fr[:,c].max():.3f}")
    # the top-5 spec-fraction photos' dev
    o = np.argsort(-fr.mean(1))[:8]
    print("  top spec photos dev %:", [round(float(med[k].mean()*100), 3) for k in o], "frac", [round(float(fr[k].mean()), 3) for k in o])
sess = CaptureSession.open(cap)
recon = json.load(open(os.path.dirname(cap) + "/reconstruction/reconstruction.json"))
h = recon["holdout_line"]
ix = indices_of(sess)
order = [ix.lines[k] for k in range(64) if k != h] + list(ix.learned)
exps = np.array([sess.photos[photo_stem(k, 0)]["exposures_s"] for k in order])  # (K, frames)
E = exact(d["line_weights"], cams[0]); sel = dist >= 5
r = d["lines"][sel] / E[sel] - 1
med = np.median(r, 0).mean(1)
lvl = np.median(E[sel], 0).mean(1)
tmin, tmax = exps.min(1), exps.max(1)
print("exposures per photo", exps.shape, "distinct tmin", len(set(np.round(tmin, 9))))
for name, x in (("log tmin", np.log(tmin)), ("log tmax", np.log(tmax)), ("log level", np.log(lvl)), ("log level*tmax", np.log(lvl * tmax)), ("log level*tmin", np.log(lvl * tmin))):
    print(f"  corr(dev, {name}) {np.corrcoef(med, x)[0,1]:.2f}")
# group by tmin
for t in sorted(set(np.round(tmin, 9))):
    g = np.round(tmin, 9) == t
    print(f"  tmin {t:.3g}: {g.sum()} photos, mean dev {med[g].mean()*100:.3f}%, level*tmin median {np.median(lvl[g]*tmin[g]):.3g}")
