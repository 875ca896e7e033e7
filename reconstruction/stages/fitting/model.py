"""The GGX fit's forward model, closed-form albedos and loss (paper §7.2, reference §5).

Physics. The prediction of a texel is the twin's own forward model, not a re-implementation of GGX:
    m_hat[p, l, c] = twin.lumitexels(rig, pos, n, t, rho_d, rho_s, alpha_x, alpha_y, convention="physical",
                                     camera, transparency=0, visibility=True)[p, upper[l], c] * LUMITEXEL_SCALE
i.e. the "network units" of reconstruction.network.data (what reconstruction.network.data.synthesize renders in grey);
with torch tensors in, twin.lumitexels is differentiable through its Warp tape. The line term predicts
M_hat[p, k, c] = sum_l W[k, l, c] m_hat[p, l, c] (reference §2.4) for the upper-LED line weights W.

Loss per texel (reference §5 adds lambda_m times the line term to the lumitexel term):
    "log1p"  mean_{l,c} (log(1 + m_hat) - log(1 + m))^2 + lambda_lines mean_{k,c} (log(1 + M_hat) - log(1 + M))^2
             (the network's Eq. 3 form: network units are scaled so that log(1 + m) compresses the range)
    "mse"    mean_{l,c} ((m_hat - m) / s_m)^2 + lambda_lines mean_{k,c} ((M_hat - M) / s_M)^2, s = the mean
             target over all texels. The reference's MSE compares m_hat with s m for a frozen "albedo
             scalar" s and divides the exported rho by s again; m_hat is linear in rho, so that scalar only
             rescales the loss. Dividing by the target's mean does the same and keeps lambda dimensionless.

Albedos in closed form. Eq. 1 is linear in the albedos: m_hat[l, c] = rho_d[c] D[l, c] + rho_s[c] S[l, c]
with D = I_c Psi V (wi.n) / (pi r^2) and S = I_c Psi V fs (wi.n) / r^2 (twin.optics.lumitexel's docstring; Schlick's
F0 is grey, so fs is one number per LED). ONE launch of the forward model with rho_d = (1, 0, 0) and
rho_s = (0, 1, 0) gives D in channel 0 and S in channel 1 (twin.optics.jvp.basis_jvp, which also gives their
derivatives for the Jacobian); the other channels follow from the LEDs' RGB intensities (D[l, c] = D[l, 0] I[l, c]
/ I[l, 0]), and so do the photos' predictions, one matrix product of the grey bases with the weights times those
ratios. For given geometry, rho_d and rho_s then minimise the loss's Gauss-Newton quadratic at the target
(weights f'(m)^2; exact for "mse") on the box [0, 1] x [0, rho_s_max], per texel and channel, lumitexel and line
terms together (`_projected`).

Sums over the LEDs in Warp. Every per-texel sum over the lumitexels' LEDs and channels, the albedo quadratic's, the
loss's and the Gauss-Newton system's J J^T and J r, is one Warp launch over the grey bases
(reconstruction.stages.fitting.sums), which never stores a (texels x LEDs x 3) tensor beyond the target itself; torch
keeps the photos' few residuals (docs/performance.md has what this saves). The stored residuals (_residuals) and
Jacobian (reconstruction.stages.fitting.jacobian._analytic_jacobian) stay as the checked reference.
"""
from __future__ import annotations

import math

import torch

import twin

from reconstruction.network.data import LUMITEXEL_SCALE
from reconstruction.stages.fitting import sums as fit_sums
from reconstruction.stages.fitting.geometry import _log_geometry
from reconstruction.stages.fitting.problem import _f, _Photos, _Problem


def _lumitexels(prob: _Problem, geom: dict, rho_d: torch.Tensor, rho_s: torch.Tensor,
                camera: str | None = None) -> torch.Tensor:
    """(n, L_upper, 3) network units seen from `camera` (None: config.camera): the twin's Warp forward model
    (differentiable)."""
    c = prob.config
    m = twin.lumitexels(prob.upper_rig, prob.pos, geom["normal"], geom["tangent"], rho_d, rho_s, geom["alpha_x"],
                        geom["alpha_y"], convention="physical", device=c.device, camera=camera or c.camera,
                        transparency=torch.zeros(prob.n, device=prob.pos.device), visibility=True)
    return m * LUMITEXEL_SCALE


def _grey(prob: _Problem, geom: dict, camera: str | None = None, derivatives: tuple | None = None):
    """The grey bases val (2, n, L) = D0, S0 in network units: the lumitexels of unit diffuse and unit specular
    albedo in the LEDs' first and second channel, seen from `camera` (None: config.camera), one Warp launch of
    twin.optics.jvp.basis_jvp (the same led_response as the forward model); the channels follow by the LEDs'
    intensity ratios (_split, module docstring). With derivatives = (d_frame, d_log_alpha)
    (geometry._frame_derivatives), (val, dD0, dS0), the bases' derivatives (n, 5, L) along the 5 numbers."""
    from twin.optics.jvp import basis_jvp

    d_frame, d_log_alpha = derivatives or (prob.pos.new_zeros(prob.n, 0, 3, 3), prob.pos.new_zeros(prob.n, 0, 2))
    val, dD0, dS0 = basis_jvp(prob.upper_rig, prob.pos, geom["normal"], geom["tangent"], geom["alpha_x"],
                              geom["alpha_y"], d_frame, d_log_alpha, camera=camera or prob.config.camera,
                              visibility=True)
    val.mul_(LUMITEXEL_SCALE)  # in place: basis_jvp's outputs are fresh, and at 12,288 LEDs large
    return (val, dD0.mul_(LUMITEXEL_SCALE), dS0.mul_(LUMITEXEL_SCALE)) if derivatives else val


def _split(prob: _Problem, val: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """D, S (n, L, 3) of the grey bases val (2, n, L) (_grey)."""
    return val[0][..., None] * prob.ratio[0], val[1][..., None] * prob.ratio[1]


def _project(g: "_Photos", x: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """A photo group's predictions (3, n, ..., K) of grey bases x (n, ..., L) whose channels follow by `ratio` (L, 3):
    one matrix product with the weights W[c] ratio[:, c], all channels side by side."""
    W = (g.W * ratio.T[:, :, None]).permute(1, 0, 2).reshape(g.W.shape[1], -1)  # (L, 3 K)
    out = (x.reshape(-1, x.shape[-1]) @ W).reshape(*x.shape[:-1], 3, g.W.shape[2])
    return out.movedim(-2, 0)


def _project_normal_rows(g: "_Photos", dD: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """_project of the diffuse basis's derivatives dD (n, 5, L): only the normal's two rows are projected, the
    others are zeros (the diffuse lobe does not depend on the tangent or the roughness, so basis_jvp's rows along
    theta and the log alphas are exact zeros; projecting them was 3/10 of the Jacobian's projections)."""
    out = _project(g, dD[:, :2], ratio)
    return torch.cat([out, out.new_zeros(*out.shape[:2], dD.shape[1] - 2, out.shape[3])], 2)


def _photo_bases(prob: _Problem, geom: dict, val: torch.Tensor) -> list:
    """For each photo group (prob.photos): (W D, W S), each (3, n, K), the bases of its camera (val for
    config.camera, one more launch for another) under its weights; [] without photos."""
    if not prob.has_lines:
        return []
    bases = {prob.config.camera: val}
    out = []
    for g in prob.photos:
        if g.camera not in bases:
            bases[g.camera] = _grey(prob, geom, g.camera)
        out.append(_photo_pair(prob, g, bases[g.camera]))
    return out


def _photo_pair(prob: _Problem, g: "_Photos", val: torch.Tensor) -> tuple:
    """(W D, W S), each (3, n, K): a photo group's predictions of the grey bases val (2, n, L) of its camera."""
    return _project(g, val[0], prob.ratio[0]), _project(g, val[1], prob.ratio[1])


def _solve_box(dd, dm, ds, ss, sm, rho_s_max: float):
    """argmin over a in [0, 1], b in [0, rho_s_max] of a^2 dd + 2ab ds + b^2 ss - 2a dm - 2b sm (elementwise).
    A convex quadratic on a box: its minimum is the unconstrained one when that is feasible, else on an
    edge, where it is the 1-D minimum clipped to the edge; all five are evaluated, the best feasible kept (the
    first of equals; (0, 0) where none is feasible). The five side by side, in one set of operations: on a GPU
    this runs once per evaluation of the loss, and one operation per candidate was launch-bound there."""
    tiny = 1e-30
    det = (dd * ss - ds * ds).clamp_min(tiny)
    s_, d_ = ss.clamp_min(tiny), dd.clamp_min(tiny)
    zero, one, top = torch.zeros_like(dd), torch.ones_like(dd), torch.full_like(dd, rho_s_max)
    a = torch.stack([(dm * ss - sm * ds) / det, zero, one, (dm / d_).clamp(0, 1),
                     ((dm - rho_s_max * ds) / d_).clamp(0, 1)])
    b = torch.stack([(sm * dd - dm * ds) / det, (sm / s_).clamp(0, rho_s_max), ((sm - ds) / s_).clamp(0, rho_s_max),
                     zero, top])
    e = a * a * dd + b * b * ss + 2 * a * b * ds - 2 * a * dm - 2 * b * sm
    ok = (a >= 0) & (a <= 1) & (b >= 0) & (b <= rho_s_max) & torch.isfinite(e)
    best = torch.where(ok, e, torch.full_like(e, math.inf)).argmin(0, keepdim=True)
    found = ok.any(0)
    return (torch.where(found, a.gather(0, best)[0], zero), torch.where(found, b.gather(0, best)[0], zero))


def _projected(prob: _Problem, val: torch.Tensor, photo_bases: list, sums: list | None = None):
    """(n, 3) rho_d, rho_s in closed form (module docstring) for the grey bases val (_grey) and each photo group's
    predictions (W D, W S) (_photo_bases), and the albedos each photo group is predicted with: config.camera's
    share the lumitexels' (the result), another camera's photos get their own pair, fitted to them alone (ours:
    the 45-degree view's texel footprint is ~1.4x longer, so where the colour varies it averages another
    mixture, and with shared albedos the fit explained that brightness difference between the views by a
    false specular lobe, a far too rough one on fabric; with its own albedos that view informs the geometry, the
    normal, tangent and roughness, only). Constants for autograd: at the minimiser the loss's gradient w.r.t.
    them vanishes (exactly for "mse", to first order for "log1p"), so the geometry's gradient needs none.
    `sums`: _albedo_sums of these bases, when the caller has them. Returns (rho_d, rho_s, [(rho_d, rho_s) of
    each photo group])."""
    with torch.no_grad():
        sums = sums if sums is not None else _albedo_sums(prob, val, photo_bases)
        a, b = _solve_box(*(s.double() for s in sums), prob.config.rho_s_max)
        albedos = (a.to(val.dtype), b.to(val.dtype))
        own = [albedos if g.camera == prob.config.camera else _own_albedos(prob, g, WD, WS)
               for g, (WD, WS) in zip(prob.photos, photo_bases)]
    return albedos[0], albedos[1], own


def _albedo_sums(prob: _Problem, val: torch.Tensor, photo_bases: list, derivatives: tuple | None = None):
    """The albedo quadratic's sums (dd, dm, ds, ss, sm), each (n, 3), of the lumitexels and config.camera's
    photos (_solve_box's a^2 dd + 2ab ds + b^2 ss - 2a dm - 2b sm: the loss to second order in the albedos), the
    lumitexels' in one Warp launch (reconstruction.stages.fitting.sums). With derivatives = (dD0, dS0, photo_dbases),
    the bases' derivatives (n, 5, L) and each photo group's (dWD, dWS) (3, n, 5, K): (sums, their derivatives, each
    (n, 5, 3))."""
    with torch.no_grad():
        dD0, dS0, dpb = derivatives or (None, None, None)
        sums, dsums = fit_sums.albedo_sums(val, prob.target, prob.ratio, prob.config.loss, prob.scale_m, dD0, dS0)
        for i, (g, (WD, WS)) in enumerate(zip(prob.photos, photo_bases)):
            if g.camera == prob.config.camera:
                sums = [s + e for s, e in zip(sums, _photo_terms(g, WD, WS))]
                if derivatives:
                    dsums = [s + e for s, e in zip(dsums, _photo_dterms(g, WD, WS, *dpb[i]))]
    return (sums, dsums) if derivatives else sums


def _photo_terms(g: _Photos, WD: torch.Tensor, WS: torch.Tensor) -> list:
    """A photo group's share of the albedo quadratic's sums (dd, dm, ds, ss, sm), each (n, 3)."""
    return [(g.M_w * e).sum(2).T for e in (WD * WD, WD * g.M, WD * WS, WS * WS, WS * g.M)]


def _photo_dterms(g: _Photos, WD, WS, dWD, dWS) -> list:
    """The derivatives (n, J, 3) of a photo group's share of the albedo sums (_photo_terms) along J directions,
    for photo bases (3, n, K) and their derivatives (3, n, J, K)."""
    Mw, M = g.M_w[:, :, None], g.M[:, :, None]
    WD, WS = WD[:, :, None], WS[:, :, None]
    return [(x * Mw).sum(3).permute(1, 2, 0) for x in (2 * WD * dWD, dWD * M, dWD * WS + WD * dWS, 2 * WS * dWS,
                                                         dWS * M)]


def _own_albedos(prob: _Problem, g: _Photos, WD: torch.Tensor, WS: torch.Tensor) -> tuple:
    """The closed-form albedos of one photo group alone (_projected)."""
    with torch.no_grad():
        return tuple(x.to(WD.dtype) for x in _solve_box(*(e.double() for e in _photo_terms(g, WD, WS)),
                                                   prob.config.rho_s_max))


def _predicted(photo_bases: list, albedos: list) -> list:
    """Each photo group's predictions (3, n, K) for its bases (W D, W S) and albedos (rho_d, rho_s) (n, 3)."""
    return [a.T[:, :, None] * WD + b.T[:, :, None] * WS for (WD, WS), (a, b) in zip(photo_bases, albedos)]


def _photo_residuals(prob: _Problem, photos_hat: list) -> list:
    """Each photo group's residuals (n, 3 K), sqrt(lambda / (3 K)) (f(M_hat) - f(M)), for its predictions
    (3, n, K): the sum of their squares is its share of the per-texel loss (module docstring)."""
    out = []
    for g, M_hat in zip(prob.photos, photos_hat):
        r = (_f(M_hat, prob.config.loss, g.scale) - g.M_f).permute(1, 0, 2).reshape(M_hat.shape[1], -1)
        out.append(r * math.sqrt(g.lam / M_hat[:, 0].numel()))
    return out


def _loss_of(prob: _Problem, m_hat: torch.Tensor, photos_hat: list) -> torch.Tensor:
    """(n,) per-texel loss (module docstring) of predicted lumitexels (n, L, 3) and photos (each (3, n, K))."""
    out = (_f(m_hat, prob.config.loss, prob.scale_m) - prob.target_f).square().mean(dim=(1, 2))
    return out + sum(r.square().sum(1) for r in _photo_residuals(prob, photos_hat))


def _projected_loss(prob: _Problem, geom: dict, sums: list | None = None):
    """The loss of `geom` with its closed-form albedos: (loss (n,), rho_d, rho_s); with a list `sums`, the
    albedo quadratic's sums (_albedo_sums) are appended to it. The lumitexels' share in one Warp launch
    (reconstruction.stages.fitting.sums), the photos' in torch."""
    val = _grey(prob, geom)
    pb = _photo_bases(prob, geom, val)
    own_sums = _albedo_sums(prob, val, pb)
    if sums is not None:
        sums.append(own_sums)
    rd, rs, own = _projected(prob, val, pb, own_sums)
    loss = fit_sums.lumitexel_terms(val, prob.target, prob.ratio, rd, rs, prob.config.loss, prob.scale_m)[0]
    return loss + sum(r.square().sum(1) for r in _photo_residuals(prob, _predicted(pb, own))), rd, rs


def _loss(prob: _Problem, q: torch.Tensor) -> torch.Tensor:
    """(n,) per-texel loss of the direct method's numbers q with their closed-form albedos (_projected_loss): the
    sum of the squares of _residuals."""
    return _projected_loss(prob, _log_geometry(q, prob.frame))[0]


def _residuals(prob: _Problem, q: torch.Tensor) -> torch.Tensor:
    """(n, 3 L + 3 K) residuals of the direct method's numbers q with their closed-form albedos, scaled so that
    the sum of their squares is the per-texel loss (_loss_of): (f(m_hat) - f(m)) / sqrt(3 L), then
    sqrt(lambda / (3 K)) (f(M_hat) - f(M))."""
    c = prob.config
    geom = _log_geometry(q, prob.frame)
    val = _grey(prob, geom)
    pb = _photo_bases(prob, geom, val)
    rd, rs, own = _projected(prob, val, pb)
    D, S = _split(prob, val)
    m_hat = rd[:, None] * D + rs[:, None] * S
    lumi = (_f(m_hat, c.loss, prob.scale_m) - prob.target_f).reshape(prob.n, -1) / math.sqrt(m_hat[0].numel())
    return torch.cat([lumi, *_photo_residuals(prob, _predicted(pb, own))], dim=1)


def _rendered_loss(prob: _Problem, geom: dict, rho_d: torch.Tensor, rho_s: torch.Tensor) -> torch.Tensor:
    """The loss of explicit parameters (the neural method's)."""
    m_hat = _lumitexels(prob, geom, rho_d, rho_s)
    photos_hat = []
    for g in prob.photos if prob.has_lines else ():
        if g.camera == prob.config.camera:
            photos_hat.append(torch.matmul(m_hat.permute(2, 0, 1), g.W))
        else:  # another view: its own closed-form albedos (_projected)
            WD, WS = _photo_pair(prob, g, _grey(prob, geom, g.camera))
            photos_hat += _predicted([(WD, WS)], [_own_albedos(prob, g, WD, WS)])
    return _loss_of(prob, m_hat, photos_hat)
