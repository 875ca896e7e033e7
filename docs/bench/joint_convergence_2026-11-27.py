"""Issue #14, step 15 (docs/accuracy.md): where paper's stock roughness went wrong, measured on one pipeline run's fit
inputs. A record of how the numbers in docs/bench/joint_convergence_mini_cpu_2026-11-27.txt were measured (main
d72db1b's fit, and the changed one for the last line), not part of the pipeline.

    python docs/bench/joint_convergence_2026-11-27.py DUMP CAPTURE MODE [ARG ...]

DUMP, CAPTURE: docs/bench/paper_edges.py. MODE:
  steps STEPS,TOL ...   the joint prior's loop given STEPS trials and tolerance TOL (the earlier phases unchanged);
  cut K ...             the prior's links cut around the stock texels within K of ink or foil (from the truth);
  photos VARIANT ...    links cut at 2 (the d3+ stock an island); the photos: measured, exact, exact+mean (exact with
                        the island's per-photo mean error), measured-mean, island_as / _flip / _shuf / _within / _iid
                        (exact outside the island, its errors as measured, sign-flipped per texel, permuted among its
                        texels per photo, among each texel's photos, or iid at their robust sd); CFG='{"propagation":
                        0}' or '{"alpha_prior": 0.0707}' passes FitConfig fields;
  landscape             links cut at 2: the island's objective at the solution found with its measured photos, at the
                        one found with exact photos elsewhere, and shifted in mean log alpha;
  information           the Gauss-Newton information of the stock's common mean log alpha, texels at >= K = 1, 2, 3, 5
                        from ink, and each texel's own (its normal free).
The island-alone and damping-per-texel runs used a scratch copy of the loop (its rules are step 15's, with a mask of
texels to hold fixed); the changed fit is reconstruction.fitting itself (MODE steps 20,1e-5 on the new code).
"""
import json
import os
import sys
from dataclasses import replace

import numpy as np
import torch

import reconstruction.fitting as fitting
from paper_edges import Edges

torch.set_num_threads(int(os.environ.get("THREADS", "2")))
E = Edges(sys.argv[1], sys.argv[2])
d, mode, args = E.d, sys.argv[3], sys.argv[4:]
KEYS = ("alpha_x_pct", "alpha_y_pct", "rho_s_pct", "rho_d_pct")
orig_cw, orig_joint = fitting._colour_weights, fitting._joint_roughness
island = (E.stock & (E.dist >= 3)).reshape(-1)
isl = torch.as_tensor(np.flatnonzero(island))


def report(tag, err, maps):
    print(tag, json.dumps({k: round(err[k]["median"], 3) for k in KEYS}), json.dumps(E.by_class(maps)), flush=True)


def cut(K):
    keep = torch.as_tensor(~E.stock | (E.dist > K))

    def cw(rho_d, grid_shape, lam):
        wd, wr = orig_cw(rho_d, grid_shape, lam)
        k = keep.to(wd.dtype)
        return wd * k[1:] * k[:-1], wr * k[:, 1:] * k[:, :-1]
    fitting._colour_weights = cw
    return cw


if mode == "steps":
    for spec in args:
        steps, tol = spec.split(",")

        def wrapped(prob, q, rho_d, grid_shape, resume=None, save=None, steps=int(steps), tol=float(tol)):
            out, info = orig_joint(replace(prob, config=replace(prob.config, iterations=steps, tolerance=tol)), q,
                                   rho_d, grid_shape, resume, save)
            print("joint", spec, "kept", info["joint_steps"], "tried", len(info["joint_trials"]), "F0,F",
                  info["joint_objective"], "last trials", info["joint_trials"][-4:], flush=True)
            return out, info
        fitting._joint_roughness = wrapped
        res, maps, err = E.fit()
        report(spec, err, maps)
elif mode == "cut":
    for K in args:
        cut(int(K))
        res, maps, err = E.fit()
        report(f"cut {K}", err, maps)
elif mode == "photos":
    cut(2)
    exp_, exs = E.exact(d["line_weights"], E.cams[0]), E.exact(d["secondary"][1], E.cams[1])
    rng = np.random.default_rng(0)

    def mean_err(M, X):
        return np.mean(M[island] / X[island] - 1, axis=0)
    ep, es = mean_err(d["lines"], exp_), mean_err(d["secondary"][0], exs)
    print("island mean error per photo RMS %: primary lines", round(float(np.sqrt(np.mean(ep[:63] ** 2))) * 100, 4),
          "primary learned", round(float(np.sqrt(np.mean(ep[63:] ** 2))) * 100, 4), "secondary",
          round(float(np.sqrt(np.mean(es ** 2))) * 100, 4), flush=True)

    def island_variant(kind):
        out = []
        for M, X in ((d["lines"], exp_), (d["secondary"][0], exs)):
            with np.errstate(divide="ignore", invalid="ignore"):
                r = (M / X - 1)[isl.numpy()]
            if kind == "flip":
                r = r * rng.choice([-1.0, 1.0], size=(len(isl), 1, 1))
            elif kind == "shuf":
                r = np.stack([r[rng.permutation(len(isl)), k] for k in range(r.shape[1])], 1)
            elif kind == "within":
                r = np.take_along_axis(r, np.argsort(rng.random(r.shape), axis=1), axis=1)
            elif kind == "iid":
                r = rng.normal(size=r.shape) * (1.4826 * np.median(np.abs(r - np.median(r))))
            Y = X.copy()
            Y[isl.numpy()] = X[isl.numpy()] * (1 + r)
            out.append(Y)
        return tuple(out)
    variants = {"measured": lambda: (d["lines"], d["secondary"][0]), "exact": lambda: (exp_, exs),
                "exact+mean": lambda: (exp_ * (1 + ep), exs * (1 + es)),
                "measured-mean": lambda: (d["lines"] / (1 + ep), d["secondary"][0] / (1 + es)),
                **{"island_" + k: (lambda k=k: island_variant(k)) for k in ("as", "flip", "shuf", "within", "iid")}}
    extra = json.loads(os.environ.get("CFG", "{}"))
    for name in args:
        L, S = variants[name]()
        res, maps, err = E.fit(lines=L.astype(np.float32), secondary=S.astype(np.float32), **extra)
        report(name, err, maps)
elif mode in ("landscape", "information"):
    got = {}

    def jw(prob, q, rho_d, grid_shape, resume=None, save=None):
        out, info = orig_joint(prob, q, rho_d, grid_shape, resume, save)
        got.update(prob=prob, q_in=q.clone(), out=out, rho_d=rho_d, sigma2=info["joint_sigma2"])
        return out, info
    fitting._joint_roughness = jw
    if mode == "information":
        res, maps, err = E.fit()
        prob, x, s2 = got["prob"], fitting._to_tensor(got["out"]), got["sigma2"]
        H = torch.cat([fitting._tensor_system(prob.part(i), x[i].float())[0].double()
                       for i in fitting._chunks(prob, prob.config.batch)]) / s2
        dist, stock = torch.as_tensor(E.dist.reshape(-1)), torch.as_tensor(E.stock.reshape(-1))
        for K in (1, 2, 3, 5):
            h = H[stock & (dist >= K)]
            A, B, C = h[:, 2:, 2:], h[:, 2:, :2], h[:, :2, :2]
            S_i = A - B @ torch.linalg.solve(C, B.transpose(1, 2))
            cov = torch.linalg.inv(S_i.sum(0))
            print(f"K>={K} texels {len(h)}: sd of the common mean log alpha {float(cov[0, 0]) ** 0.5:.4f}, anisotropy "
                  f"{float(cov[1, 1]) ** 0.5:.4f} {float(cov[2, 2]) ** 0.5:.4f}; per texel alone sd(m) median "
                  f"{float(S_i[:, 0, 0].median()) ** -0.5:.3f}", flush=True)
    else:
        cw = cut(2)
        exp_, exs = E.exact(d["line_weights"], E.cams[0]), E.exact(d["secondary"][1], E.cams[1])
        E.fit()
        P, xm, qin_m, rho_d, s2 = got["prob"], fitting._to_tensor(got["out"]), got["q_in"], got["rho_d"], got["sigma2"]
        L, S = d["lines"].copy(), d["secondary"][0].copy()
        L[~island], S[~island] = exp_[~island], exs[~island]
        E.fit(lines=L, secondary=S)
        xa = fitting._to_tensor(got["out"])
        weights = cw(rho_d, (E.R, E.R), 1 / P.config.alpha_prior ** 2)

        def island_F(x):
            with torch.no_grad():
                loss = fitting._loss(P.part(isl), fitting._from_tensor(x[isl].float())).double()
            a = x[:, 2:5].double()
            return float(loss.sum()) / s2, float((a * fitting._laplacian(a, weights, (E.R, E.R))).sum())
        base = island_F(xm)
        print("measured solution: island data", round(base[0], 1), "prior(all)", round(base[1], 1))
        xs = xm.clone()
        xs[isl] = xa[isl]
        v = island_F(xs)
        print("island at the exact-elsewhere solution:", round(v[0] - base[0], 1), round(v[1] - base[1], 1))
        for dl in (-0.2, -0.1, 0.1, 0.2, 0.3):
            xs = xm.clone()
            xs[isl, 2] += dl
            v = island_F(xs)
            print("shift", dl, round(v[0] - base[0], 1), round(v[1] - base[1], 1))
