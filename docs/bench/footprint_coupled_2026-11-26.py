"""Issue #14: the footprint in the fit's residuals (docs/accuracy.md, "Open", paper), as run.

    python docs/bench/footprint_coupled_2026-11-26.py SAMPLE OUT [MODE]

runs `hemicube validate`'s end-to-end function (mini rig, capture seed 1, CPU) on SAMPLE in one process with the
GGX fit (reconstruction.fitting.fit_ggx) followed by a coupled refinement, and prints the goal rows as JSON.
MODE: "coupled" (default) or "base" (the pipeline unchanged, same process layout, for the same-run baseline).

The coupled refinement. Start: the pipeline's fit (per-texel LM, propagation, joint roughness prior, joint
albedos). Unknowns per texel i, z_i (17): x_i = [u, v, m, c, s] (the joint prior's tensor coordinates,
fitting._to_tensor), the primary view's albedos (rho_d, rho_s) (shared with the lumitexels) and the secondary
view's own pair. Residuals:
    lumitexel  (f(a_i D_i + b_i S_i) - f(m_i)) / sqrt(3 L)                       uncoupled, as the pipeline's
    photos     sqrt(lam / 3K) (f(Y_i) - f(M_i)),  Y_i[c] = sum_{j in 3x3(i)} W_ij[c] P_j[c]
with P_j = a_j WD_j + b_j WS_j texel j's predicted photos from its own lobe at its centre (each view its own
albedos) and W the view's per-colour footprint weights (indicator images of the texel cells through the CFA,
the bilinear demosaic and the bilinear lookup at each texel's pixel; the mini rig's colour matrices are the
identity, so the colours do not mix). Objective
    F = sum_i |r_i|^2 / sigma^2 + sum_{i~j} w_ij |a_i - a_j|^2 / tau^2 + sum_{i~j} w_ij |rho_s_i - rho_s_j|^2 / (tau rho_ij)^2
(the pipeline's joint prior on the log-alpha tensor numbers and its rho_s prior, the same colour weights from the
start's rho_d, sigma^2 the pipeline's joint_sigma2). Solved by Levenberg-Marquardt on all texels at once: the
lumitexels' 17 x 17 Gauss-Newton blocks explicit per texel, the photos' Jacobian kept per texel (n, 17, 3K) and
the normal operator applied matrix-free in PCG (J v: per-texel rows, then the 3x3 stencil; J^T u: the transposed
stencil, then the rows), plus the prior's Laplacian; preconditioner the exact block diagonal. Albedos are clamped
to their boxes after each step. A record of how the numbers were measured, not part of the pipeline.
"""
import os, sys, json, time, math
from pathlib import Path
import numpy as np
import torch


def pixel_cells(rig, grid, cam, dx=0.0, dy=0.0):
    """(H, W) row and column of the texel cell that the ray through each pixel's point (x + dx, y + dy) meets on
    the sample plane (unclipped, float)."""
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W]
    p = cam.plane_points(np.stack([xs.ravel() + dx, ys.ravel() + dy], 1).astype(np.float64), rig.sample.origin,
                         rig.sample.normal) - np.asarray(rig.sample.origin)
    u, v = p @ np.asarray(rig.sample.x_axis), p @ np.asarray(rig.sample.y_axis)
    i = np.floor((v + grid.size_mm / 2) / grid.texel_mm).reshape(H, W)
    j = np.floor((u + grid.size_mm / 2) / grid.texel_mm).reshape(H, W)
    return i, j


def footprint(rig, grid, cam, uv, identity=False):
    """(nb (9, N) long, w (9, N, 3) float64): texel i's photo in colour c = sum_o w[o, i, c] P[nb[o, i], c]
    (the 3 x 3 neighbours, clamped at the grid's edge). From footprint_experiments_2026-11-25.py."""
    from reconstruction.alignment import bilinear
    from twin.camera.bayer import cfa_index, demosaic
    R = grid.resolution
    N = R * R
    # each pixel is the mean of S x S stratified rays over its area (twin.camera.imaging: the capture's
    # supersampling), so a pixel near a cell's edge sees both cells: its share of each cell class
    S = int(os.environ.get("FP_SUPERSAMPLE", "4"))
    sub = (np.arange(S) + 0.5) / S - 0.5
    cells = [tuple(np.clip(a, 0, R - 1).astype(int) for a in pixel_cells(rig, grid, cam, dx, dy))
             for dy in sub for dx in sub]
    ch = cfa_index(cam.sensor.bayer, cam.height, cam.width)
    r = np.arange(N) // R
    s_ = np.arange(N) % R
    bad = ~np.isfinite(uv).all(1)
    uvc = np.where(bad[:, None], 0.0, uv)
    w = np.zeros((3, 3, N, 3))
    for c in range(3):
        for a in range(3):
            for b in range(3):
                ind = np.mean([(ii % 3 == a) & (jj % 3 == b) for ii, jj in cells], axis=0) * (ch == c)
                resp = demosaic(ind, cam.sensor.bayer)[..., c]
                val = bilinear(resp[..., None], uvc[:, 0], uvc[:, 1])[:, 0]
                dr = (a - r) % 3
                dr = np.where(dr == 2, -1, dr)
                ds = (b - s_) % 3
                ds = np.where(ds == 2, -1, ds)
                w[dr + 1, ds + 1, np.arange(N), c] = val
    w[:, :, bad] = 0.0
    w[1, 1, bad] = 1.0  # no pixel: the texel's own light (the photos there are whatever extraction left)
    nb = np.zeros((3, 3, N), np.int64)
    for dr in (-1, 0, 1):
        for ds in (-1, 0, 1):
            nb[dr + 1, ds + 1] = np.clip(r + dr, 0, R - 1) * R + np.clip(s_ + ds, 0, R - 1)
    if identity or os.environ.get("IDENTITY"):
        w[:] = 0.0
        w[1, 1] = 1.0
    return torch.as_tensor(nb.reshape(9, N)), torch.as_tensor(w.reshape(9, N, 3))


class Stencil:
    def __init__(self, nb, w):
        self.nb, self.w = nb, w  # (9, n), (9, n, 3)
        self.wT = w.permute(0, 2, 1)[..., None]  # (9, 3, n, 1)

    def apply(self, P):  # P (3, n, K) -> Y (3, n, K)
        Y = torch.zeros_like(P)
        for o in range(9):
            Y += self.wT[o] * P[:, self.nb[o]]
        return Y

    def transpose(self, S, square=False):  # S (3, n, K) -> sum_i w_ij S_i at j
        out = torch.zeros_like(S)
        for o in range(9):
            w = self.wT[o] ** 2 if square else self.wT[o]
            out.index_add_(1, self.nb[o], w * S)
        return out


CG_MAX, CG_TOL = int(os.environ.get("CG_MAX", "150")), float(os.environ.get("CG_TOL", "1e-6"))


def coupled_refine(F, prob, res, stencils, grid_shape, sigma2, steps=15, log=print):
    """The coupled Levenberg-Marquardt (module docstring). F: reconstruction.fitting. Returns (FitResult, info)."""
    t0 = time.perf_counter()
    c = prob.config
    R, C = grid_shape
    n, L = prob.n, prob.leds
    dev = prob.pos.device
    dt = torch.float64
    full = prob.part(torch.arange(n, device=dev))
    target_f = full.target_f.double()  # (n, L, 3)
    ratio = prob.ratio.double()
    lo, hi = (math.log(v) for v in c.alpha_range)
    groups = list(prob.photos)
    assert len(groups) == 2 and groups[0].camera == c.camera
    frame = prob.frame

    # start: the pipeline's maps -> numbers
    nrm = torch.as_tensor(res.normal, device=dev)
    tan = torch.as_tensor(res.tangent, device=dev)
    N_, X_, Y_ = frame
    cz = (nrm * N_).sum(-1)
    t0b = F._base_tangent(nrm, frame)
    theta = torch.atan2((tan * torch.linalg.cross(nrm, t0b, dim=-1)).sum(-1), (tan * t0b).sum(-1))
    q0 = torch.stack([(nrm * X_).sum(-1) / cz, (nrm * Y_).sum(-1) / cz, theta,
                      torch.log(torch.as_tensor(res.alpha_x)), torch.log(torch.as_tensor(res.alpha_y))], 1)
    x0 = F._to_tensor(q0.double())
    rd0 = torch.as_tensor(res.rho_d, dtype=dt)
    rs0 = torch.as_tensor(res.rho_s, dtype=dt)
    with torch.no_grad():
        geom = F._log_geometry(q0.float(), frame)
        v2 = F._grey(prob, geom, groups[1].camera)
        WD2, WS2 = F._photo_pair(full, groups[1], v2)
        a2, b2 = F._own_albedos(full, groups[1], WD2, WS2)
    z = torch.cat([x0, rd0, rs0, a2.double(), b2.double()], 1)  # (n, 17)
    A_OFF = [(5, 8), (11, 14)]  # albedo columns of each group

    # the prior (the pipeline's: colour weights from the start's rho_d)
    wts = F._colour_weights(rd0, (R, C), 1.0 / c.alpha_prior ** 2)
    grey = rs0.mean(1).reshape(R, C)
    scale = [((grey[1:] + grey[:-1]) / 2).clamp_min(0.05) ** 2, ((grey[:, 1:] + grey[:, :-1]) / 2).clamp_min(0.05) ** 2]
    wts_s = (wts[0] / scale[0], wts[1] / scale[1])
    deg_a, deg_s = F._degree(wts, (R, C)).reshape(-1), F._degree(wts_s, (R, C)).reshape(-1)

    def prior_op(v):
        out = torch.zeros_like(v)
        out[:, 2:5] = F._laplacian(v[:, 2:5], wts, (R, C))
        out[:, 8:11] = F._laplacian(v[:, 8:11], wts_s, (R, C))
        return out

    def prior_val(z):
        return float((z * prior_op(z)).sum())

    def fix_iso(z):
        z = z.clone()
        d = torch.hypot(z[:, 3], z[:, 4])
        small = d < 1e-3
        z[small, 3] = torch.where(z[small, 3] >= 0, 1e-3, -1e-3).to(z.dtype)
        z[small, 4] = 0.0
        return z

    def clamp(z):
        z = z.clone()
        for g, (ao, bo) in enumerate(A_OFF):
            z[:, ao:ao + 3] = z[:, ao:ao + 3].clamp(0.0, 1.0)
            z[:, bo:bo + 3] = z[:, bo:bo + 3].clamp(0.0, c.rho_s_max)
        return fix_iso(z)

    def q_of(z):
        q = F._from_tensor(z[:, :5])
        q[:, 3:5] = q[:, 3:5].clamp(lo, hi)
        return q

    def photo_parts(val_by_cam, z):
        out = []
        for gi, (g, st) in enumerate(zip(groups, stencils)):
            ao, bo = A_OFF[gi]
            WD, WS = (x.double() for x in F._photo_pair(full, g, val_by_cam[g.camera]))
            A, B = z[:, ao:ao + 3], z[:, bo:bo + 3]
            P = A.T[:, :, None] * WD + B.T[:, :, None] * WS
            Y = st.apply(P)
            s = math.sqrt(g.lam / (3 * WD.shape[2]))
            r = s * (F._f(Y, c.loss, g.scale) - g.M_f.double())
            out.append((WD, WS, P, Y, r, s))
        return out

    def lumi_r(val, z):
        D, S = (x.double() for x in F._split(full, val))
        m_hat = z[:, 5:8, None].transpose(1, 2) * D + z[:, 8:11, None].transpose(1, 2) * S
        return D, S, m_hat, (F._f(m_hat, c.loss, prob.scale_m) - target_f) / math.sqrt(3 * L)

    def objective(z):
        with torch.no_grad():
            geom = F._log_geometry(q_of(z).float(), frame)
            vals = {g.camera: F._grey(prob, geom, g.camera) for g in groups}
            _, _, _, rl = lumi_r(vals[c.camera], z)
            data = float(rl.square().sum()) + sum(float(p[4].square().sum()) for p in photo_parts(vals, z))
        return data / sigma2 + prior_val(z), data

    def linearise(z):
        x = z[:, :5]
        q = q_of(z)
        d = torch.hypot(x[:, 3], x[:, 4]).clamp_min(1e-30)
        cos, sin = x[:, 3] / d, x[:, 4] / d
        dq = torch.zeros(n, 5, 5, dtype=dt)
        dq[:, 0, 0] = dq[:, 1, 1] = dq[:, 3, 2] = dq[:, 4, 2] = 1.0
        dq[:, 2, 3], dq[:, 2, 4] = -sin / (2 * d), cos / (2 * d)
        dq[:, 3, 3], dq[:, 3, 4], dq[:, 4, 3], dq[:, 4, 4] = cos, sin, -cos, -sin
        with torch.no_grad():
            geom, d_frame, d_log_alpha = F._frame_derivatives(prob, q.float())
            grey = {}
            for g in groups:
                val, dD, dS = F._grey(prob, geom, g.camera, (d_frame, d_log_alpha))
                # to the tensor coordinates: d/dx_k = sum_j dq_j/dx_k d/dq_j
                grey[g.camera] = (val, torch.einsum("njl,njk->nkl", dD.double(), dq),
                                  torch.einsum("njl,njk->nkl", dS.double(), dq))
        vals = {k: v[0] for k, v in grey.items()}
        # lumitexels: explicit 17 x 17 blocks (only x, a, b of the primary are touched)
        val, dD, dS = grey[c.camera]
        D, S, m_hat, rl = lumi_r(val, z)
        fp = F._df(m_hat, c.loss, prob.scale_m) / math.sqrt(3 * L)  # (n, L, 3)
        a, b = z[:, 5:8], z[:, 8:11]
        Jg = fp[:, None] * (dD[..., None] * (a[:, None] * ratio[0])[:, None] + dS[..., None] * (b[:, None] * ratio[1])[:, None])
        Ja, Jb = fp * D, fp * S  # (n, L, 3): column a_c touches channel c only
        H = torch.zeros(n, 17, 17, dtype=dt)
        gvec = torch.zeros(n, 17, dtype=dt)
        H[:, :5, :5] = torch.einsum("njlc,nklc->njk", Jg, Jg)
        ch = torch.arange(3)
        H[:, :5, 5:8] = torch.einsum("njlc,nlc->njc", Jg, Ja)
        H[:, :5, 8:11] = torch.einsum("njlc,nlc->njc", Jg, Jb)
        H[:, 5:8, :5] = H[:, :5, 5:8].transpose(1, 2)
        H[:, 8:11, :5] = H[:, :5, 8:11].transpose(1, 2)
        H[:, 5 + ch, 5 + ch] = (Ja * Ja).sum(1)
        H[:, 5 + ch, 8 + ch] = H[:, 8 + ch, 5 + ch] = (Ja * Jb).sum(1)
        H[:, 8 + ch, 8 + ch] = (Jb * Jb).sum(1)
        gvec[:, :5] = torch.einsum("njlc,nlc->nj", Jg, rl)
        gvec[:, 5:8] = (Ja * rl).sum(1)
        gvec[:, 8:11] = (Jb * rl).sum(1)
        data = float(rl.square().sum())
        del Jg, Ja, Jb
        Hl = H.clone()  # the lumitexels' blocks alone (the operator's uncoupled part)
        # photos: per-texel rows dP (3, n, 17, K), the stencil, f'
        rows = []
        for gi, (g, st, (WD, WS, P, Y, r, s)) in enumerate(zip(groups, stencils, photo_parts(vals, z))):
            ao, bo = A_OFF[gi]
            _, dDg, dSg = grey[g.camera]
            dWD = F._project(g, dDg.float(), prob.ratio[0]).double()  # (3, n, 5, K)
            dWS = F._project(g, dSg.float(), prob.ratio[1]).double()
            A, B = z[:, ao:ao + 3], z[:, bo:bo + 3]
            K = WD.shape[2]
            dP = torch.zeros(3, n, 17, K, dtype=dt)
            dP[:, :, :5] = A.T[:, :, None, None] * dWD + B.T[:, :, None, None] * dWS
            for cc in range(3):
                dP[cc, :, ao + cc] = WD[cc]
                dP[cc, :, bo + cc] = WS[cc]
            fpp = s * F._df(Y, c.loss, g.scale)  # (3, n, K)
            data += float(r.square().sum())
            dPt = dP.permute(1, 0, 3, 2).reshape(n, 3 * K, 17).contiguous()  # (n, 3K, 17): bmm's layout
            del dP
            rows.append((dPt, fpp, st))
            gvec += rows_T(dPt, st.transpose(fpp * r))
            wq = rows_flat(st.transpose(fpp.square(), square=True))  # (n, 3K)
            H += torch.bmm(dPt.transpose(1, 2) * wq[:, None], dPt)
        return H, Hl, gvec, rows, data

    def rows_flat(u):  # (3, n, K) -> (n, 3K)
        return u.permute(1, 0, 2).reshape(u.shape[1], -1)

    def rows_T(dPt, u):  # sum over the rows of dP^T u: (n, 17)
        return torch.bmm(dPt.transpose(1, 2), rows_flat(u)[..., None])[..., 0]

    def photo_op(rows, v):
        out = torch.zeros_like(v)
        for dPt, fpp, st in rows:
            Pv = torch.bmm(dPt, v[..., None])[..., 0].reshape(n, 3, -1).permute(1, 0, 2)
            Jv = fpp * st.apply(Pv)
            out += rows_T(dPt, st.transpose(fpp * Jv))
        return out

    z = clamp(z)
    with torch.no_grad():
        geom = F._log_geometry(q_of(z).float(), frame)
        vals = {g.camera: F._grey(prob, geom, g.camera) for g in groups}
        parts = [float(lumi_r(vals[c.camera], z)[3].square().sum())] + [float(p[4].square().sum())
                                                                         for p in photo_parts(vals, z)]
    log(f"coupled: start data parts / sigma2 (lumitexels, primary, secondary) {[p / sigma2 for p in parts]}; "
        f"pipeline texel_loss sum / sigma2 {float(np.sum(res.info['texel_loss'])) / sigma2:.6g}")
    Fz, data = objective(z)
    if os.environ.get("CHECK_GRAD"):  # the data term's directional derivative, analytic against central differences
        H, Hl, gvec, rows, d0 = linearise(z)
        gen = torch.Generator().manual_seed(0)
        for name, cols in (("u,v", [0, 1]), ("m", [2]), ("c,s", [3, 4]), ("rho_d", [5, 6, 7]), ("rho_s", [8, 9, 10]),
                           ("secondary albedos", list(range(11, 17)))):
            v = torch.zeros_like(z)
            v[:, cols] = torch.randn(n, len(cols), generator=gen, dtype=dt)
            for eps in (1e-2, 1e-3):
                num = (objective(z + eps * v)[1] - objective(z - eps * v)[1]) / (2 * eps)
                Hv = float((v * ((Hl @ v[..., None])[..., 0] + photo_op(rows, v))).sum())
                num2 = (objective(z + eps * v)[1] + objective(z - eps * v)[1] - 2 * d0) / eps ** 2
                log(f"grad check {name} eps {eps}: analytic {2 * float((gvec * v).sum()):.6g} numeric {num:.6g}; "
                    f"curvature GN {2 * Hv:.6g} numeric {num2:.6g}")
    F0, mu, nu, kept, cg_total = Fz, c.lm_damping, 2.0, 0, 0
    log(f"coupled: start F {Fz:.6g} data/sigma2 {data / sigma2:.6g} sigma2 {sigma2:.4g}")
    for step in range(steps):
        tl = time.perf_counter()
        H, Hl, gvec, rows, _ = linearise(z)
        log(f"linearise {time.perf_counter() - tl:.1f} s")
        g = gvec / sigma2 + prior_op(z)
        Hs = H / sigma2
        dg = torch.diagonal(Hs, dim1=1, dim2=2)
        while True:
            damp = mu * (dg + 1e-6 * dg.sum(1, keepdim=True)) + 1e-12
            pre = Hs + torch.diag_embed(damp)
            pre[:, 2 + torch.arange(3), 2 + torch.arange(3)] += deg_a[:, None]
            pre[:, 8 + torch.arange(3), 8 + torch.arange(3)] += deg_s[:, None]
            Minv = torch.linalg.inv(pre)

            def op(v):
                return ((Hl @ v[..., None])[..., 0] + photo_op(rows, v)) / sigma2 + damp * v + prior_op(v)

            b = -g
            xs = torch.zeros_like(b)
            rr = b.clone()
            zz = (Minv @ rr[..., None])[..., 0]
            p = zz.clone()
            rz, rr0, it = float((rr * zz).sum()), float((rr * rr).sum()), 0
            tc = time.perf_counter()
            while it < CG_MAX and float((rr * rr).sum()) > CG_TOL * rr0:
                Ap = op(p)
                al = rz / float((p * Ap).sum())
                xs += al * p
                rr -= al * Ap
                zz = (Minv @ rr[..., None])[..., 0]
                rz, rzo = float((rr * zz).sum()), rz
                p = zz + (rz / rzo) * p
                it += 1
            tc = time.perf_counter() - tc
            cg_total += it
            tl = time.perf_counter()
            zn = clamp(z + xs)
            Fn, datan = objective(zn)
            # F = data / sigma2 + prior is twice the quadratic that g and op describe
            pred = 2 * (-float((g * xs).sum()) - 0.5 * float((xs * op(xs)).sum()) + float((damp * xs * xs).sum()) / 2)
            rho = (Fz - Fn) / max(pred, 1e-300)
            log(f"cg {tc:.1f} s, objective {time.perf_counter() - tl:.1f} s")
            log(f"coupled step {step} mu {mu:.3g} cg {it} F {Fn:.6g} (from {Fz:.6g}) gain ratio {rho:.3f}")
            if math.isfinite(Fn) and Fn < Fz:
                break
            mu *= nu  # Nielsen's update (Madsen, Nielsen & Tingleff 2004)
            nu *= 2
            if mu > 1e10:
                break
        if not (math.isfinite(Fn) and Fn < Fz):
            break
        gain = (Fz - Fn) / Fz
        z, Fz, kept = zn, Fn, kept + 1
        mu, nu = mu * max(1 / 3, 1 - (2 * rho - 1) ** 3), 2.0
        if gain < c.tolerance:
            break
    q = q_of(z).float()
    geom = F._log_geometry(q, frame)
    out = F.FitResult(normal=geom["normal"].numpy(), tangent=geom["tangent"].numpy(),
                      alpha_x=geom["alpha_x"].numpy(), alpha_y=geom["alpha_y"].numpy(),
                      rho_d=z[:, 5:8].float().numpy(), rho_s=z[:, 8:11].float().numpy(),
                      history=res.history, seconds=res.seconds + time.perf_counter() - t0,
                      info={**res.info, "coupled_steps": kept, "coupled_cg": cg_total,
                            "coupled_objective": [F0, Fz], "coupled_seconds": time.perf_counter() - t0})
    return out


def replay(dump, capture_dir):
    """The refinement alone on a DUMP of the fit's inputs, scored against the capture's true maps (the maps rows)."""
    import pickle
    import twin
    import reconstruction.fitting as fitting
    from reconstruction.extraction import TextureGrid
    from reconstruction.metrics import map_errors, resample_maps, truth_coverage
    from twin.capture.session import CaptureSession
    d = pickle.load(open(dump, "rb"))
    rig = twin.load_rig("mini")
    grid = TextureGrid(*d["grid"])
    R = grid.resolution
    session = CaptureSession.open(capture_dir)
    true_maps = session.ground_truth_maps()
    truth = resample_maps(true_maps, grid.size_mm, R)
    mask = truth_coverage(true_maps, grid.size_mm, R)

    def score(res, tag):
        m = map_errors(truth, fitting.to_maps(res, (R, R), grid.size_mm), mask=mask)
        print(tag, json.dumps({k: round(m[k]["median"], 4) for k in ("normal_deg", "tangent_deg", "alpha_x_pct",
                                                                      "alpha_y_pct", "rho_d_pct", "rho_s_pct")}),
              flush=True)
    score(d["res"], "pipeline")
    config = d["config"]
    cams = [rig.camera(config.camera), rig.camera(config.secondary_camera)]
    st = [Stencil(*footprint(rig, grid, cams[0], d["pixel_primary"].astype(np.float64))),
          Stencil(*footprint(rig, grid, cams[1], d["pixel_secondary"].astype(np.float64),
                             identity=os.environ.get("FP_VIEWS") == "primary"))]
    prob = fitting._problem(rig, d["positions"], d["lumitexels"], d["lines"], d["line_weights"], d["grid_shape"],
                            config, d["secondary"])
    t = time.perf_counter()
    out = coupled_refine(fitting, prob, d["res"], st, (R, R), d["res"].info["joint_sigma2"],
                         steps=int(os.environ.get("COUPLED_STEPS", "15")),
                         log=lambda s: print(s, file=sys.stderr, flush=True))
    print("coupled seconds", time.perf_counter() - t)
    score(out, "coupled")
    return out


if __name__ == "__main__" and sys.argv[1] == "replay":
    torch.set_num_threads(int(os.environ.get("THREADS", "2")))
    replay(sys.argv[2], sys.argv[3])
    sys.exit(0)

if __name__ == "__main__":
    sample, outdir = sys.argv[1], Path(sys.argv[2])
    mode = sys.argv[3] if len(sys.argv) > 3 else "coupled"
    torch.set_num_threads(int(os.environ.get("THREADS", "2")))
    import reconstruction.extraction as ex
    import reconstruction.fitting as fitting
    import reconstruction.pipeline as pipeline
    stash, timing = {}, {}
    orig_extract = ex.extract

    def extract(session, rig, grid, alignment, **kw):
        m = orig_extract(session, rig, grid, alignment, **kw)
        stash["meas"], stash["grid"] = m, grid
        return m
    ex.extract = extract
    orig_fit = fitting.fit_ggx

    def fit_ggx(rig, positions, lumitexels, *, lines=None, line_weights=None, secondary=None, grid_shape=None,
                config=fitting.FitConfig(), checkpoint=None):
        t = time.perf_counter()
        res = orig_fit(rig, positions, lumitexels, lines=lines, line_weights=line_weights, secondary=secondary,
                       grid_shape=grid_shape, config=config, checkpoint=checkpoint)
        timing["pipeline_fit_s"] = time.perf_counter() - t
        if os.environ.get("DUMP"):  # the fit's inputs and the pipeline's result, to rerun the refinement alone
            import pickle
            n = len(positions)
            lumi = lumitexels(torch.arange(n)) if callable(lumitexels) else lumitexels
            lumi = lumi.detach().cpu().numpy() if torch.is_tensor(lumi) else np.asarray(lumi)
            with open(os.environ["DUMP"], "wb") as fh:
                pickle.dump(dict(positions=positions, lumitexels=lumi, lines=lines, line_weights=line_weights,
                                 secondary=secondary, grid_shape=grid_shape, config=config, res=res,
                                 pixel_primary=stash["meas"].pixel_primary,
                                 pixel_secondary=stash["meas"].pixel_secondary,
                                 grid=(stash["grid"].resolution, stash["grid"].size_mm)), fh)
        if mode == "base":
            return res
        t = time.perf_counter()
        meas, grid = stash["meas"], stash["grid"]
        cams = [rig.camera(config.camera), rig.camera(config.secondary_camera)]
        st = [Stencil(*footprint(rig, grid, cams[0], meas.pixel_primary.astype(np.float64))),
              Stencil(*footprint(rig, grid, cams[1], meas.pixel_secondary.astype(np.float64)))]
        print("footprint centre weight median", [float(np.median(s.w[4, :, k])) for s in st for k in range(3)],
              file=sys.stderr)
        prob = fitting._problem(rig, positions, lumitexels, lines, line_weights, grid_shape, config, secondary)
        out = coupled_refine(fitting, prob, res, st, tuple(int(v) for v in grid_shape), res.info["joint_sigma2"],
                             steps=int(os.environ.get("COUPLED_STEPS", "15")),
                             log=lambda s: print(s, file=sys.stderr, flush=True))
        timing["coupled_s"] = time.perf_counter() - t
        return out
    fitting.fit_ggx = fit_ggx
    pipeline_fit = getattr(pipeline, "fit_ggx", None)
    import twin
    from hemicube.validate import end_to_end
    t = time.time()
    metrics, rows, _ = end_to_end(twin.load_rig("mini"), sample, "cpu", outdir, None, 1, False)
    print(json.dumps({"sample": sample, "mode": mode, "s": time.time() - t, **timing,
                      "rows": [(r["metric"], round(float(r["value"]), 4), r["passed"]) for r in rows]}))
