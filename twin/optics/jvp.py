"""Forward-mode derivatives of the unit-albedo lumitexel bases (paper Eq. 1) along per-point directions: what a
Gauss-Newton fit of the GGX geometry needs, in one launch, instead of one launch per finite difference.

    val, dD, dS = twin.optics.jvp.basis_jvp(rig, position, normal, tangent, alpha_x, alpha_y, d_frame, d_log_alpha,
                                            camera="primary")

For each point p and LED l, `val[0, p, l]` is channel 0 and `val[1, p, l]` channel 1 of Eq. 1 with rho_d =
(1, 0, 0) and rho_s = (0, 1, 0): the diffuse basis D and the specular basis S of reconstruction.stages.fitting, the very
numbers twin.lumitexels gives for those albedos, computed by the same `led_response`, so to the bit. `dD[p, j, l]`,
`dS[p, j, l]` are their derivatives along direction j of point p, which moves the point's local frame (rows
t', b, n; twin.optics.ggx.local_frame) by d_frame[p, j] (3 x 3) and its log roughness by d_log_alpha[p, j] (2).
Position, LED, camera, emission profile and visibility do not move, so every factor of Eq. 1 but the BRDF and
the cosine is a constant of the derivative, and each derivative is the value times a logarithmic derivative
that needs the local directions only:

    D = c_D (wi . n)                                  d ln D = d(wi_z) / wi_z
    S = c_S fs wi_z,  fs = D_ggx F G1(wi) G1(wo) / (4 wi_z wo_z + eps)     (Walter et al. 2007 eq. 20)
    d ln S = d ln D_ggx + d ln F + d ln G1(wi) + d ln G1(wo) + d wi_z / wi_z - d(4 wi_z wo_z) / (4 wi_z wo_z + eps)
    d ln D_ggx = -d ln ax - d ln ay - 2 dQ / Q,  Q = hx^2 / (ax + eps)^2 + hy^2 / (ay + eps)^2 + hz^2 / (1 + eps)^2
    d ln G1(v) = dvz / vz - (dvz + dr) / (vz + r + eps),  r = sqrt(ax^2 vx^2 + ay^2 vy^2 + vz^2)
    d ln F = -5 (1 - F0) (1 - c)^4 dc / F,  c = wi . h   (Schlick)
    dh = (ds - h (h . ds)) / |s|,  s = wi + wo,  d wi_local = d_frame wi_world,  d wo_local = d_frame wo_world

Implemented for the reference's GGX convention, separable Smith G1 and Schlick Fresnel (what the fit uses); the
wrapper refuses the others. Where a basis is 0 (below a horizon, an occluded or a dark LED, a bottom LED) its
derivative is 0: one-sided at those edges, as the kernel's branches are. Every kernel is generic over float32 /
float64; tests/test_jvp.py checks the float64 derivatives against central differences of twin.lumitexels.
"""
from __future__ import annotations

import contextlib
from typing import Any

import warp as wp

from twin.optics.lumitexel import Options, led_response, point_inputs


@wp.func
def _grad_log_g1(v: Any, ax: Any, ay: Any, eps: Any):
    """The gradient of ln G1(v), G1 = 2 vz / (vz + r + eps) (twin.optics.ggx.smith_g1), r = sqrt(ax^2 vx^2 + ay^2 vy^2
    + vz^2): (d/dv (3), d/d ln ax, d/d ln ay), with d(ax^2) = 2 ax^2 d ln ax."""
    tx = ax * ax * v[0]
    ty = ay * ay * v[1]
    r = wp.sqrt(tx * v[0] + ty * v[1] + v[2] * v[2])
    k = type(ax)(1.0) / (v[2] + r + eps)
    kr = k / r
    g = type(v)(-kr * tx, -kr * ty, type(ax)(1.0) / v[2] - k - kr * v[2])
    return g, -kr * tx * v[0], -kr * ty * v[1]


@wp.func
def _grad_log_specular(wi: Any, wo: Any, ax: Any, ay: Any, f0: Any, eps: Any):
    """The gradient of ln (fs wi_z) (module docstring) at local wi, wo above the horizon: (d/dwi, d/dwo, d/d ln ax,
    d/d ln ay). The half vector's share goes through dh = (I - h h^T) ds / |s|, s = wi + wo, to both."""
    one = type(ax)(1.0)
    four = type(ax)(4.0)
    s = wi + wo
    ls = wp.length(s)
    h = s / ls
    ex2 = (ax + eps) * (ax + eps)
    ey2 = (ay + eps) * (ay + eps)
    ez2 = (one + eps) * (one + eps)
    q = h[0] * h[0] / ex2 + h[1] * h[1] / ey2 + h[2] * h[2] / ez2
    gh = type(wi)(h[0] / ex2, h[1] / ey2, h[2] / ez2) * (-four / q)  # d(-2 ln Q)/dh
    ga_x = -one + four * h[0] * h[0] * ax / (ex2 * (ax + eps) * q)  # d ln D_ggx / d ln ax
    ga_y = -one + four * h[1] * h[1] * ay / (ey2 * (ay + eps) * q)
    g_wi = type(wi)(type(ax)(0.0), type(ax)(0.0), type(ax)(0.0))
    c = wp.dot(wi, h)
    if c > type(ax)(0.0) and c < one:  # Schlick: d ln F = kappa (dwi . h + wi . dh)
        m = one - c
        m4 = m * m * m * m
        kappa = -type(ax)(5.0) * (one - f0) * m4 / (f0 + (one - f0) * m4 * m)
        g_wi = h * kappa
        gh = gh + wi * kappa
    gs = (gh - h * wp.dot(h, gh)) / ls
    gi, gi_x, gi_y = _grad_log_g1(wi, ax, ay, eps)
    go, go_x, go_y = _grad_log_g1(wo, ax, ay, eps)
    den = four * wi[2] * wo[2] + eps  # ln wi_z - ln(4 wi_z wo_z + eps)
    g_wi = g_wi + gs + gi + type(wi)(type(ax)(0.0), type(ax)(0.0), one / wi[2] - four * wo[2] / den)
    g_wo = gs + go + type(wi)(type(ax)(0.0), type(ax)(0.0), -four * wi[2] / den)
    return g_wi, g_wo, ga_x + gi_x + go_x, ga_y + gi_y + go_y


@wp.kernel(enable_backward=False)  # forward mode by hand: no adjoint code to compile
def basis_jvp_kernel(pos: wp.array(dtype=Any), frames: wp.array(dtype=Any), wo_l: wp.array(dtype=Any),
                     ax: wp.array(dtype=Any), ay: wp.array(dtype=Any), beta: wp.array(dtype=Any),
                     d_frame: wp.array2d(dtype=Any), d_log_alpha: wp.array2d(dtype=Any),
                     lpos: wp.array(dtype=Any), lnrm: wp.array(dtype=Any), lu: wp.array(dtype=Any),
                     lint: wp.array(dtype=Any), prof: wp.array2d(dtype=Any), lbot: wp.array(dtype=wp.int32),
                     o: Options, val: wp.array3d(dtype=Any), d_diffuse: wp.array3d(dtype=Any),
                     d_specular: wp.array3d(dtype=Any)):
    """(P, L) threads: the two bases by led_response (module docstring), then their derivatives along the
    point's d_frame.shape[1] directions (the outputs come zeroed)."""
    p, l = wp.tid()
    zero = ax[p] * type(ax[p])(0.0)
    one = zero + type(zero)(1.0)
    x = pos[p]
    e0 = type(x)(one, zero, zero)
    e1 = type(x)(zero, one, zero)
    # rho_d = (1, 0, 0) and rho_s = (0, 1, 0) at once: channel 0 is the diffuse basis, channel 1 the specular one
    m = led_response(x, frames[p], wo_l[p], e0, e1, ax[p], ay[p], beta[p], lpos[l], lnrm[l], lu[l], lint[l], prof, l,
                     lbot[l], o)
    vd = m[0]
    vs = m[1]
    val[0, p, l] = vd
    val[1, p, l] = vs
    if lbot[l] != 0 or (vd == zero and vs == zero) or d_frame.shape[1] == 0:  # no derivatives asked: the bases alone
        return
    f = frames[p]
    wi_w = wp.normalize(lpos[l] - x)
    wi = f * wi_w
    wo = wo_l[p]
    wo_w = wp.transpose(f) * wo
    eta = type(zero)(o.eta)
    r0 = (eta - one) / (eta + one)
    g_wi = type(wi)(zero, zero, zero)
    g_wo = type(wi)(zero, zero, zero)
    g_ax = zero
    g_ay = zero
    if vs != zero:
        g_wi, g_wo, g_ax, g_ay = _grad_log_specular(wi, wo, ax[p], ay[p], r0 * r0, type(zero)(o.eps))
    for j in range(d_frame.shape[1]):
        df = d_frame[p, j]
        dwi = df * wi_w
        if vd != zero:
            d_diffuse[p, j, l] = vd * dwi[2] / wi[2]
        if vs != zero:
            da = d_log_alpha[p, j]
            d_specular[p, j, l] = vs * (wp.dot(g_wi, dwi) + wp.dot(g_wo, df * wo_w) + g_ax * da[0] + g_ay * da[1])


def basis_jvp(rig, position, normal, tangent, alpha_x, alpha_y, d_frame, d_log_alpha, *, camera=None,
              convention="physical", visibility=None, g="separable", fresnel="schlick", eta=1.5):
    """The bases and their directional derivatives (module docstring) for torch tensors on one device, float32
    or float64: position, normal, tangent (P, 3), alpha_x, alpha_y (P,), d_frame (P, J, 3, 3), d_log_alpha
    (P, J, 2). Returns torch tensors val (2, P, L), dD (P, J, L), dS (P, J, L) on that device (no autograd)."""
    import torch

    from twin.optics.inputs import CONVENTIONS, _init, _led_inputs
    from twin.optics.torch_ops import _wp_device, rig_setup

    if g != "separable" or fresnel != "schlick":
        raise ValueError(f"basis_jvp implements the separable Smith G1 and Schlick's Fresnel (the reference's GGX "
                         f"convention), got g={g!r}, fresnel={fresnel!r}")
    P = position.shape[0]
    J = d_frame.shape[1]
    if tuple(d_frame.shape) != (P, J, 3, 3) or tuple(d_log_alpha.shape) != (P, J, 2):
        raise ValueError(f"d_frame must have shape (P, J, 3, 3) and d_log_alpha (P, J, 2) for P = {P}, got "
                         f"{tuple(d_frame.shape)} and {tuple(d_log_alpha.shape)}")
    double = position.dtype == torch.float64
    vec, scal, mat, vec2 = ((wp.vec3d, wp.float64, wp.mat33d, wp.vec2d) if double
                            else (wp.vec3f, wp.float32, wp.mat33f, wp.vec2f))
    dtype = position.dtype
    device = _wp_device(position)
    _init()
    arrays, o, cam = rig_setup((rig, convention, camera, g, fresnel, eta, visibility), device, double)

    def w(x, t):
        return wp.from_torch(x.detach().to(dtype).contiguous(), dtype=t)

    L = rig.num_leds
    val = torch.zeros(2, P, L, dtype=dtype, device=position.device)
    dD = torch.zeros(P, J, L, dtype=dtype, device=position.device)
    dS = torch.zeros(P, J, L, dtype=dtype, device=position.device)
    beta = torch.zeros(P, dtype=dtype, device=position.device)
    stream = (wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(position.device)))
              if position.device.type == "cuda" else None)
    with stream or contextlib.nullcontext():
        pts = point_inputs(w(position, vec), w(normal, vec), w(tangent, vec), None, None, w(alpha_x, scal),
                           w(alpha_y, scal), w(beta, scal), cam, device)
        wp.launch(basis_jvp_kernel, dim=(P, L),
                  inputs=[pts[0], pts[1], pts[2], pts[5], pts[6], pts[7], w(d_frame, mat), w(d_log_alpha, vec2),
                          *_led_inputs(arrays, CONVENTIONS[convention]), o],
                  outputs=[w(val, scal), w(dD, scal), w(dS, scal)], device=device)
    return val, dD, dS
