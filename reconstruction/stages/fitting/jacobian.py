"""The Gauss-Newton system of the direct method's residuals (paper §7.2; ours): J J^T, J r and the loss per texel,
with the Jacobian that FitConfig.jacobian asks for (_system).

"analytic": the grey bases' derivatives along the 5 numbers from one Warp launch per camera
(twin.optics.jvp.basis_jvp, with the local frame's derivatives of reconstruction.stages.fitting.geometry), the
closed-form albedos' own by the implicit function theorem (variable projection, Golub & Pereyra 1973), the chain
rule through the photos' weights and the loss's transform; the lumitexels' rows are summed into the system in Warp
(reconstruction.stages.fitting.sums) and never stored. "forward": forward differences of the residuals, five more
evaluations of the forward model a step, the same-run baseline of `hemicube bench fit-jacobian`. The joint prior's
system in the log roughness tensor's coordinates follows by the chain rule (_tensor_system).
"""
from __future__ import annotations

import math

import torch

from reconstruction.stages.fitting import sums as fit_sums
from reconstruction.stages.fitting.config import GEOMETRY_SIZE
from reconstruction.stages.fitting.geometry import _frame_derivatives, _from_tensor, _log_geometry
from reconstruction.stages.fitting.model import (_albedo_sums, _grey, _photo_dterms, _photo_pair, _photo_residuals,
                                                 _photo_terms, _predicted, _project, _project_normal_rows, _projected,
                                                 _residuals, _split)
from reconstruction.stages.fitting.problem import _df, _Problem


def _system(prob: _Problem, q: torch.Tensor) -> tuple:
    """(J J^T (n, 5, 5), J r (n, 5), the loss r.r (n,)): the Gauss-Newton system of _residuals at the numbers q, with
    the Jacobian that FitConfig.jacobian asks for."""
    if prob.config.jacobian == "analytic":
        return _normal_equations(prob, q)
    return _difference_system(prob, q)


def _normal_equations(prob: _Problem, q: torch.Tensor) -> tuple:
    """(J J^T (n, 5, 5), J r (n, 5), the loss r.r (n,)) of the residuals r = _residuals at q and their analytic
    Jacobian J along the 5 numbers (_bases_system of _number_bases)."""
    return _bases_system(prob, _number_bases(prob, q))


def _bases_system(prob: _Problem, bases) -> tuple:
    """(J J^T (n, 5, 5), J r (n, 5), the loss r.r (n,)) of the residuals and their analytic Jacobian J along the 5
    directions of `bases` (_linearisation). The lumitexels' share, 3 L rows of 5 a texel, is summed in one Warp
    launch that never stores them (reconstruction.stages.fitting.sums.lumitexel_terms); the photos' few rows in
    torch."""
    val, dD0, dS0, rd, rs, da, db, photo_r, photo_J = _linearisation(prob, bases)
    loss, A, g = fit_sums.lumitexel_terms(val, prob.target, prob.ratio, rd, rs, prob.config.loss, prob.scale_m,
                                          dD0, dS0, da, db)
    for r, J in zip(photo_r, photo_J):
        A = A + J @ J.transpose(1, 2)
        g = g + (J @ r[..., None])[..., 0]
        loss = loss + r.square().sum(1)
    return A, g, loss


def _linearisation(prob: _Problem, bases):
    """What the analytic Jacobian of _residuals is made of, for `bases` (_number_bases at the numbers q, or
    _isotropic_bases): the bases' derivatives from basis_jvp per camera, the closed-form albedos' derivatives
    (_albedo_derivatives), the chain rule through the projections onto the photos' weights and the loss's
    transform. Costs about one evaluation of the forward model per camera where the forward difference takes five
    (FitConfig.jacobian). Returns config.camera's grey bases val (2, n, L) and their derivatives dD0, dS0 (n, 5,
    L), the shared albedos rd, rs (n, 3) and their derivatives da, db (n, 5, 3), and each photo group's residuals
    (n, 3 K) and Jacobian rows (n, 5, 3 K), along the 5 directions of `bases`."""
    from twin.optics.torch_ops import tf32_products

    c = prob.config
    photos = prob.photos if prob.has_lines else ()
    pb, dpb = [None] * len(photos), [None] * len(photos)

    def project(cam, bases):
        """Each photo group of camera cam: (W D, W S) and their derivatives (dWD, dWS), (3, n, 5, K) each."""
        for i, g in enumerate(photos):
            if g.camera == cam:
                pb[i] = _photo_pair(prob, g, bases[0])
                with tf32_products(c.precision == "tf32"):  # FitConfig.precision: the system's direction only
                    dpb[i] = (_project_normal_rows(g, bases[1], prob.ratio[0]), _project(g, bases[2], prob.ratio[1]))

    # another camera's bases are projected and freed before config.camera's are computed: a view's bases and their
    # derivatives are 12 floats a texel-LED pair (9.7 GB for a chunk of 16,384 paper texels), and both views' at once
    # would be most of a chunk's memory (ours; docs/performance.md)
    for cam in dict.fromkeys(g.camera for g in photos if g.camera != c.camera):
        project(cam, bases(cam))
    val, dD0, dS0 = bases(c.camera)
    project(c.camera, (val, dD0, dS0))
    sums, dsums = _albedo_sums(prob, val, pb, (dD0, dS0, dpb))
    rd, rs, own = _projected(prob, val, pb, sums)
    da, db = _albedo_derivatives(sums, dsums, rd, rs, c.rho_s_max)
    photo_J = []
    for g, (WD, WS), (dWD, dWS), (a, b) in zip(photos, pb, dpb, own):
        if g.camera == c.camera:
            ga, gb = da, db
        else:  # its own albedos (_projected), and their own derivatives
            ga, gb = _albedo_derivatives(_photo_terms(g, WD, WS), _photo_dterms(g, WD, WS, dWD, dWS), a, b,
                                         c.rho_s_max)
        M_hat = a.T[:, :, None] * WD + b.T[:, :, None] * WS
        dM = (ga.permute(2, 0, 1)[..., None] * WD[:, :, None] + gb.permute(2, 0, 1)[..., None] * WS[:, :, None]
              + a.T[:, :, None, None] * dWD + b.T[:, :, None, None] * dWS)  # (3, n, J, K)
        fpm = _df(M_hat, c.loss, g.scale) * math.sqrt(g.lam / M_hat[:, 0].numel())
        photo_J.append((fpm[:, :, None] * dM).permute(1, 2, 0, 3).reshape(prob.n, GEOMETRY_SIZE, -1))
    return val, dD0, dS0, rd, rs, da, db, _photo_residuals(prob, _predicted(pb, own)), photo_J


def _number_bases(prob: _Problem, q: torch.Tensor):
    """camera -> its grey bases val (2, n, L) and their derivatives dD0, dS0 (n, 5, L) along the direct method's
    5 numbers [u, v, theta, log alpha_x, log alpha_y] at q (_grey with _frame_derivatives): _linearisation's
    bases."""
    geom, d_frame, d_log_alpha = _frame_derivatives(prob, q)
    return lambda camera: _grey(prob, geom, camera, (d_frame, d_log_alpha))


def _isotropic_bases(prob: _Problem, x: torch.Tensor):
    """camera -> the grey bases and their derivatives along the joint prior's tensor coordinates x = [u, v, m, c,
    s] (geometry._to_tensor) at the isotropic lobe (c = s = 0; x's own c, s are not read), where the chain rule
    through the tangent angle (_tensor_system) divides by d = 0. With c + i s = d e^(2 i theta), the lobe's
    derivative along c is that of log alpha_x - log alpha_y at theta = 0, along s the same at theta = pi / 4, and
    along m that of both log alphas; an isotropic lobe is the same at any theta, so the bases are those at theta = 0.
    Exact at c = s = 0, for two launches of basis_jvp per camera (the second for the one direction s), where forward
    differences take six evaluations of the residuals (ours)."""
    zero = torch.zeros_like(x[:, 0])
    q = torch.stack([x[:, 0], x[:, 1], zero, x[:, 2], x[:, 2]], 1)
    geom, d_frame, _ = _frame_derivatives(prob, q)
    turned = _log_geometry(q + q.new_tensor([0.0, 0.0, math.pi / 4, 0.0, 0.0]), prob.frame)
    d_frame = torch.cat([d_frame[:, :2], torch.zeros_like(d_frame[:, :2])], 1)  # u, v; m and c turn no frame row
    d_log_alpha = q.new_tensor([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0], [1.0, -1.0]]).expand(q.shape[0], 4, 2)
    along_s = (q.new_zeros(q.shape[0], 1, 3, 3), q.new_tensor([[[1.0, -1.0]]]).expand(q.shape[0], 1, 2))

    def bases(camera):
        val, dD, dS = _grey(prob, geom, camera, (d_frame, d_log_alpha))
        _, dD_s, dS_s = _grey(prob, turned, camera, along_s)
        return val, torch.cat([dD, dD_s], 1), torch.cat([dS, dS_s], 1)

    return bases


def _albedo_derivatives(sums: list, dsums: list, a: torch.Tensor, b: torch.Tensor, rho_s_max: float):
    """(da, db) (n, J, 3) of the closed-form albedos (model._solve_box) along J directions, from the quadratic's sums
    (dd, dm, ds, ss, sm) (n, 3) and their derivatives (n, J, 3): the minimiser's own derivative (variable
    projection, Golub & Pereyra 1973), by the implicit function theorem on the free coordinates, 0 for one that
    sits on its box edge."""
    dtype = a.dtype
    dd, dm, ds, ss, sm = (x[:, None].double() for x in sums)
    ddd, ddm, dds, dss, dsm = (x.double() for x in dsums)
    a, b = a[:, None].double(), b[:, None].double()
    r1 = ddm - a * ddd - b * dds  # d(dm) - d(dd) a - d(ds) b
    r2 = dsm - a * dds - b * dss
    a_free = (a > 0) & (a < 1)
    b_free = (b > 0) & (b < rho_s_max)
    det = (dd * ss - ds * ds).clamp_min(1e-30)
    both = a_free & b_free
    da = torch.where(both, (ss * r1 - ds * r2) / det, torch.where(a_free, r1 / dd.clamp_min(1e-30), 0.0))
    db = torch.where(both, (dd * r2 - ds * r1) / det, torch.where(b_free, r2 / ss.clamp_min(1e-30), 0.0))
    return da.to(dtype), db.to(dtype)


def _analytic_jacobian(prob: _Problem, q: torch.Tensor) -> torch.Tensor:
    """(n, 5, residuals) Jacobian of _residuals at q, exact (_linearisation), every row stored: what
    `hemicube bench fit-jacobian` and the tests check against central differences; the fit itself takes the
    Gauss-Newton system without the rows (_normal_equations)."""
    val, dD0, dS0, rd, rs, da, db, _, photo_J = _linearisation(prob, _number_bases(prob, q))
    c, ratio = prob.config, prob.ratio
    D, S = _split(prob, val)
    m_hat = rd[:, None] * D + rs[:, None] * S
    fp = _df(m_hat, c.loss, prob.scale_m) / math.sqrt(m_hat[0].numel())
    # (n, J, L, 3): f'(m_hat) d m_hat = f'(m_hat) (da D + rd dD + db S + rs dS), in place (the largest tensor here)
    dm = torch.mul(dD0[..., None], (rd[:, None] * ratio[0])[:, None])
    dm.addcmul_(dS0[..., None], (rs[:, None] * ratio[1])[:, None])
    dm.addcmul_(da[:, :, None], D[:, None]).addcmul_(db[:, :, None], S[:, None]).mul_(fp[:, None])
    return torch.cat([dm.reshape(prob.n, GEOMETRY_SIZE, -1), *photo_J], dim=2)


def _forward_difference(prob: _Problem, q: torch.Tensor, r: torch.Tensor, to_numbers=None) -> torch.Tensor:
    """(n, 5, residuals) forward-difference Jacobian (FitConfig.fd_step) of _residuals at q, whose value is r, row j
    the derivative along number j; with `to_numbers`, of _residuals(to_numbers(q)) (another parameterisation of
    the same 5 numbers)."""
    h = prob.config.fd_step
    eye = torch.eye(GEOMETRY_SIZE, dtype=q.dtype, device=q.device) * h
    f = to_numbers or (lambda x: x)
    return torch.stack([(_residuals(prob, f(q + eye[j])) - r) / h for j in range(GEOMETRY_SIZE)], 1)


def _difference_system(prob: _Problem, q: torch.Tensor, to_numbers=None) -> tuple:
    """(J J^T, J r, r.r) of _residuals at q (at to_numbers(q), with `to_numbers`) by forward differences
    (_forward_difference)."""
    r = _residuals(prob, to_numbers(q) if to_numbers else q)
    J = _forward_difference(prob, q, r, to_numbers)
    return J @ J.transpose(1, 2), (J @ r[..., None])[..., 0], r.square().sum(1)


def _tensor_system(prob: _Problem, x: torch.Tensor) -> tuple:
    """(J J^T, J r, r.r) of the residuals r = _residuals(_from_tensor(x)) in the tensor coordinates x, J their
    Jacobian there. The analytic one (FitConfig.jacobian) by the chain rule through _from_tensor (J = dq/dx^T J_q,
    so J J^T = dq/dx^T (J_q J_q^T) dq/dx), whose angle is undefined where the lobe is isotropic (d = 0): there, for
    d < 1e-4, the system of the isotropic lobe at [u, v, m, 0, 0] (_isotropic_bases; its error at such d is O(d),
    the chain rule's float32's epsilon / d relative, from the tangent angle's 1 / d); the loss is x's own."""
    if prob.config.jacobian != "analytic":
        return _difference_system(prob, x, _from_tensor)
    q = _from_tensor(x)
    d = torch.hypot(x[:, 3], x[:, 4])
    ds = d.clamp_min(1e-30)
    cos, sin = x[:, 3] / ds, x[:, 4] / ds
    dq = torch.zeros(x.shape[0], GEOMETRY_SIZE, GEOMETRY_SIZE, dtype=x.dtype, device=x.device)  # dq_j / dx_k
    dq[:, 0, 0] = dq[:, 1, 1] = dq[:, 3, 2] = dq[:, 4, 2] = 1.0
    dq[:, 2, 3], dq[:, 2, 4] = -sin / (2 * ds), cos / (2 * ds)  # theta = atan2(s, c) / 2
    dq[:, 3, 3], dq[:, 3, 4], dq[:, 4, 3], dq[:, 4, 4] = cos, sin, -cos, -sin  # m +- hypot(c, s)
    A, g, loss = _normal_equations(prob, q)
    A = dq.transpose(1, 2) @ A @ dq
    g = (dq.transpose(1, 2) @ g[..., None])[..., 0]
    near = torch.nonzero(d < 1e-4).flatten()
    if near.numel():
        part = prob.part(near)
        A[near], g[near], _ = _bases_system(part, _isotropic_bases(part, x[near]))
    return A, g, loss
