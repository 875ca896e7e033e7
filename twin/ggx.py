"""Anisotropic GGX + Lambert BRDF of the OpenSVBRDF light stage, as NVIDIA Warp functions.

Model (Ma et al. 2023, "OpenSVBRDF", §5; Walter et al. 2007; Heitz 2014, JCGT 3(2)):

    f(ωi, ωo) = ρd/π + ρs · D(h) F(ωi·h) G(ωi, ωo) / (4 cosθi cosθo),   h = normalize(ωi + ωo)

and f = 0 when cosθi ≤ 0 or cosθo ≤ 0. Every direction is expressed in the local frame
(t, b, n): t is the tangent (the αx axis), b = n × t, n the normal, v_loc = (v·t, v·b, v·n).

Options, chosen by integer flags so that one compiled kernel serves all of them:
  * G: separable Smith G1(ωi)·G1(ωo) (OpenSVBRDF, default) or height-correlated
    1 / (1 + Λ(ωi) + Λ(ωo)) (Heitz 2014 §6, eq. 99).
  * F: Schlick with F0 = ((η−1)/(η+1))² (η = 1.5 → 0.04, OpenSVBRDF's constant, default) or the
    exact unpolarised dielectric Fresnel (Walter et al. 2007 eq. 22), with total internal reflection.
  * eps: 0 gives the exact maths; 1e-6 reproduces the regularisers of the authors' renderer
    (α + eps in D, + eps in the G1 denominator, + eps in 4 cosθi cosθo).

All functions are float32 and stay finite for α ∈ [0.006, 1] and every direction, including exactly
grazing ones (v_z = 0) and the degenerate half vector ωi = −ωo.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

# warp-lang 1.19 has no `config.quiet` any more (setting it is a silent no-op); the greeting and the
# per-module "load took" lines are INFO messages, so raise the threshold to WARNING.
wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)

G_SEPARABLE = 0
G_HEIGHT_CORRELATED = 1
F_SCHLICK = 0
F_DIELECTRIC = 1

_G_MODES = {"separable": G_SEPARABLE, "height-correlated": G_HEIGHT_CORRELATED}
_F_MODES = {"schlick": F_SCHLICK, "dielectric": F_DIELECTRIC}

INV_PI = wp.constant(1.0 / math.pi)
# Smallest denominators we allow. They are far below any value that unit vectors with
# α ≥ 0.006 can produce away from the horizon (cosθ > ~1e-15), so they change nothing there, and
# they are normal float32 numbers, so flush-to-zero of denormals on the GPU cannot undo them.
_TINY = wp.constant(1.0e-30)
_TINY_COS = wp.constant(1.0e-15)


@wp.func
def half_vector(wi: wp.vec3, wo: wp.vec3):
    """normalize(ωi + ωo); returns n = (0,0,1) when ωi = −ωo (then f = 0 anyway: one of the two
    is below or on the horizon, so any unit vector would do)."""
    s = wi + wo
    l2 = wp.dot(s, s)
    if l2 <= 1.0e-24:
        return wp.vec3(0.0, 0.0, 1.0)
    return s / wp.sqrt(l2)


@wp.func
def ggx_d(h_loc: wp.vec3, ax: float, ay: float, eps: float):
    """Anisotropic GGX normal distribution (Walter et al. 2007 eq. 33; Heitz 2014 eq. 85):
    D(h) = χ⁺(h_z) / (π αx αy (hx²/αx² + hy²/αy² + hz²)²).
    eps > 0: the authors' regulariser, h ⊘ (αx+eps, αy+eps, 1+eps) inside the sum, π αx αy unchanged."""
    if h_loc[2] <= 0.0:
        return 0.0
    x = h_loc[0] / (ax + eps)
    y = h_loc[1] / (ay + eps)
    z = h_loc[2] / (1.0 + eps)
    s = wp.max(x * x + y * y + z * z, 1.0e-12)  # ≥ 1 for a unit h and α ≤ 1; guards h = 0
    return 1.0 / (wp.pi * ax * ay * s * s)


@wp.func
def smith_g1(v_loc: wp.vec3, ax: float, ay: float, eps: float):
    """Smith masking for GGX (Walter et al. 2007 eq. 34, anisotropic form of Heitz 2014 eq. 86):
    G1(v) = 2 v_z / (v_z + sqrt(αx² vx² + αy² vy² + vz²)) = 1 / (1 + Λ(v)), 0 for v_z ≤ 0.
    This form has no 1/v_z, so it is finite (→ 0) at grazing. eps: authors' + eps in the denominator."""
    vz = v_loc[2]
    if vz <= 0.0:
        return 0.0
    r = wp.sqrt(ax * ax * v_loc[0] * v_loc[0] + ay * ay * v_loc[1] * v_loc[1] + vz * vz)
    return 2.0 * vz / wp.max(vz + r + eps, _TINY)


@wp.func
def smith_lambda(v_loc: wp.vec3, ax: float, ay: float):
    """Smith Λ for anisotropic GGX (Heitz 2014 eq. 86): Λ = (−1 + sqrt(1 + (αx²vx² + αy²vy²)/vz²)) / 2.
    Written as a² / (2 vz (vz + r)), r = sqrt(a² + vz²), which equals (r − vz)/(2 vz) without its
    cancellation near normal incidence. Λ diverges like 1/v_z at grazing; v_z is clamped to 1e-15 so
    the value stays finite (≤ ~5e29). Only meaningful for v_z > 0 (G is zero below the horizon)."""
    vz = wp.max(v_loc[2], _TINY_COS)
    a2 = ax * ax * v_loc[0] * v_loc[0] + ay * ay * v_loc[1] * v_loc[1]
    r = wp.sqrt(a2 + vz * vz)
    return a2 / wp.max(2.0 * vz * (vz + r), _TINY)


@wp.func
def masking_shadowing(wi_loc: wp.vec3, wo_loc: wp.vec3, ax: float, ay: float, g_mode: int, eps: float):
    """G(ωi, ωo). Separable: G1(ωi) G1(ωo) (OpenSVBRDF, Walter et al. 2007 eq. 23).
    Height-correlated (Heitz 2014 eq. 99): 1/(1 + Λi + Λo). With 1 + Λ = (v_z + r)/(2 v_z) this is
    2 vi vo / (ri vo + ro vi), finite at grazing; eps enters as r → r + eps, exactly as in G1, which
    keeps G_hc ≥ G1 G1 true for every eps (it is (ri − vi)(ro − vo) ≥ 0 after clearing denominators)."""
    vi = wi_loc[2]
    vo = wo_loc[2]
    if vi <= 0.0 or vo <= 0.0:
        return 0.0
    if g_mode == G_HEIGHT_CORRELATED:
        ri = wp.sqrt(ax * ax * wi_loc[0] * wi_loc[0] + ay * ay * wi_loc[1] * wi_loc[1] + vi * vi) + eps
        ro = wp.sqrt(ax * ax * wo_loc[0] * wo_loc[0] + ay * ay * wo_loc[1] * wo_loc[1] + vo * vo) + eps
        return 2.0 * vi * vo / wp.max(ri * vo + ro * vi, _TINY)
    return smith_g1(wi_loc, ax, ay, eps) * smith_g1(wo_loc, ax, ay, eps)


@wp.func
def fresnel_schlick(c: float, f0: float):
    """Schlick's approximation F0 + (1 − F0)(1 − c)^5 (OpenSVBRDF uses F0 = 0.04)."""
    m = 1.0 - wp.clamp(c, 0.0, 1.0)
    m2 = m * m
    return f0 + (1.0 - f0) * m2 * m2 * m


@wp.func
def fresnel_dielectric(c: float, eta: float):
    """Exact unpolarised Fresnel reflectance (Walter et al. 2007 eq. 22, in its rs/rp form) for light
    arriving from outside at cosθ = c ≥ 0 onto a dielectric of relative IOR η = n_inside / n_outside.
    Total internal reflection (possible for η < 1) gives 1; η = 1 (index matched) gives 0."""
    ci = wp.clamp(c, 0.0, 1.0)
    if eta == 1.0:
        return 0.0
    sin2_t = (1.0 - ci * ci) / (eta * eta)  # Snell
    if sin2_t >= 1.0:
        return 1.0
    ct = wp.sqrt(1.0 - sin2_t)
    rs = (ci - eta * ct) / wp.max(ci + eta * ct, _TINY)
    rp = (eta * ci - ct) / wp.max(eta * ci + ct, _TINY)
    return 0.5 * (rs * rs + rp * rp)


@wp.func
def fresnel(c: float, f_mode: int, eta: float):
    """Fresnel term at c = ωi·h: exact dielectric, or Schlick with F0 = ((η−1)/(η+1))²."""
    if f_mode == F_DIELECTRIC:
        return fresnel_dielectric(c, eta)
    r = (eta - 1.0) / (eta + 1.0)
    return fresnel_schlick(c, r * r)


@wp.func
def ggx_specular(wi_loc: wp.vec3, wo_loc: wp.vec3, ax: float, ay: float, g_mode: int, f_mode: int,
                 eta: float, eps: float):
    """Microfacet specular lobe D F G / (4 cosθi cosθo + eps) (Walter et al. 2007 eq. 20), without ρs.
    Zero below or on the horizon. The denominator floor only matters for cosθi cosθo < ~1e-31,
    where G ~ cosθi cosθo makes the numerator vanish too."""
    ci = wi_loc[2]
    co = wo_loc[2]
    if ci <= 0.0 or co <= 0.0:
        return 0.0
    h = half_vector(wi_loc, wo_loc)
    d = ggx_d(h, ax, ay, eps)
    g = masking_shadowing(wi_loc, wo_loc, ax, ay, g_mode, eps)
    f = fresnel(wp.clamp(wp.dot(wi_loc, h), 0.0, 1.0), f_mode, eta)
    return d * f * g / wp.max(4.0 * ci * co + eps, _TINY)


@wp.func
def ggx_brdf(wi_loc: wp.vec3, wo_loc: wp.vec3, rho_d: wp.vec3, rho_s: wp.vec3, ax: float, ay: float,
             g_mode: int, f_mode: int, eta: float, eps: float):
    """Full RGB BRDF ρd/π + ρs fs (Ma et al. 2023 §5), zero when either direction is below the horizon."""
    if wi_loc[2] <= 0.0 or wo_loc[2] <= 0.0:
        return wp.vec3(0.0)
    fs = ggx_specular(wi_loc, wo_loc, ax, ay, g_mode, f_mode, eta, eps)
    return rho_d * INV_PI + rho_s * fs


@wp.func
def local_frame(n: wp.vec3, t: wp.vec3):
    """World → local rotation whose rows are (t', b, n), so `frame * v` = (v·t', v·b, v·n).
    t' = normalize(t − (t·n) n) (Gram–Schmidt), b = n × t'. If t is (nearly) parallel to n, any
    perpendicular is used (Duff et al. 2017 branchless basis) so the result is always a rotation."""
    nl = wp.length(n)
    nn = wp.vec3(0.0, 0.0, 1.0)
    if nl > 1.0e-20:
        nn = n / nl
    tp = t - wp.dot(t, nn) * nn
    tl = wp.length(tp)
    if tl > 1.0e-6:
        tp = tp / tl
    else:
        sgn = wp.where(nn[2] >= 0.0, 1.0, -1.0)
        a = -1.0 / (sgn + nn[2])
        bb = nn[0] * nn[1] * a
        tp = wp.vec3(1.0 + sgn * nn[0] * nn[0] * a, sgn * bb, -sgn * nn[0])
    b = wp.cross(nn, tp)
    return wp.mat33(tp[0], tp[1], tp[2], b[0], b[1], b[2], nn[0], nn[1], nn[2])


# --------------------------------------------------------------------------------------------
# Kernels (defined at import time: adding one later would change the module hash and recompile).


@wp.kernel
def _brdf_kernel(wi: wp.array(dtype=wp.vec3), wo: wp.array(dtype=wp.vec3),
                 normal: wp.array(dtype=wp.vec3), tangent: wp.array(dtype=wp.vec3),
                 rho_d: wp.array(dtype=wp.vec3), rho_s: wp.array(dtype=wp.vec3),
                 alpha_x: wp.array(dtype=float), alpha_y: wp.array(dtype=float),
                 g_mode: int, f_mode: int, eta: float, eps: float, out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    frame = local_frame(normal[i], tangent[i])
    out[i] = ggx_brdf(frame * wi[i], frame * wo[i], rho_d[i], rho_s[i], alpha_x[i], alpha_y[i],
                      g_mode, f_mode, eta, eps)


@wp.kernel
def _terms_kernel(wi: wp.array(dtype=wp.vec3), wo: wp.array(dtype=wp.vec3),
                  alpha_x: wp.array(dtype=float), alpha_y: wp.array(dtype=float),
                  g_mode: int, f_mode: int, eta: float, eps: float,
                  h_out: wp.array(dtype=wp.vec3), c_out: wp.array(dtype=float),
                  d_out: wp.array(dtype=float), g1i_out: wp.array(dtype=float),
                  g1o_out: wp.array(dtype=float), g_out: wp.array(dtype=float),
                  li_out: wp.array(dtype=float), lo_out: wp.array(dtype=float),
                  f_out: wp.array(dtype=float), fs_out: wp.array(dtype=float)):
    i = wp.tid()
    a = wi[i]
    b = wo[i]
    ax = alpha_x[i]
    ay = alpha_y[i]
    h = half_vector(a, b)
    c = wp.clamp(wp.dot(a, h), 0.0, 1.0)
    h_out[i] = h
    c_out[i] = c
    d_out[i] = ggx_d(h, ax, ay, eps)
    g1i_out[i] = smith_g1(a, ax, ay, eps)
    g1o_out[i] = smith_g1(b, ax, ay, eps)
    g_out[i] = masking_shadowing(a, b, ax, ay, g_mode, eps)
    li_out[i] = smith_lambda(a, ax, ay)
    lo_out[i] = smith_lambda(b, ax, ay)
    f_out[i] = fresnel(c, f_mode, eta)
    fs_out[i] = ggx_specular(a, b, ax, ay, g_mode, f_mode, eta, eps)


@wp.kernel
def _to_local_kernel(v: wp.array(dtype=wp.vec3), normal: wp.array(dtype=wp.vec3),
                     tangent: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = local_frame(normal[i], tangent[i]) * v[i]


# --------------------------------------------------------------------------------------------
# numpy-facing API


def _vectors(name: str, x, n: int | None) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and a.shape[0] != n):
        want = "(N, 3)" if n is None else f"({n}, 3)"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or Inf")
    return a


def _scalars(name: str, x, n: int) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or Inf")
    if np.any(a <= 0.0):
        raise ValueError(f"{name} must be > 0 (GGX roughness), got min {a.min()}")
    return a


def _unit(name: str, a: np.ndarray) -> None:
    # The contract is unit vectors; 1e-3 accepts float32 round-off and catches un-normalised input.
    bad = np.abs(np.linalg.norm(a, axis=1) - 1.0) > 1e-3
    if np.any(bad):
        raise ValueError(f"{name} must be unit vectors (|v| = 1 ± 1e-3); row {int(np.argmax(bad))} is not")


def _modes(g: str, fresnel: str, eta: float, eps: float) -> tuple[int, int, float, float]:
    if g not in _G_MODES:
        raise ValueError(f"unknown g={g!r}; expected one of {sorted(_G_MODES)}")
    if fresnel not in _F_MODES:
        raise ValueError(f"unknown fresnel={fresnel!r}; expected one of {sorted(_F_MODES)}")
    if not (np.isfinite(eta) and eta > 0.0):
        raise ValueError(f"eta must be a finite relative IOR > 0, got {eta}")
    if not (np.isfinite(eps) and eps >= 0.0):
        raise ValueError(f"eps must be finite and >= 0, got {eps}")
    return _G_MODES[g], _F_MODES[fresnel], float(eta), float(eps)


def _wp(a: np.ndarray, dtype, device) -> wp.array:
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=device)


def brdf(wi, wo, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, *, g: str = "separable",
         fresnel: str = "schlick", eta: float = 1.5, eps: float = 0.0, device: str = "cpu") -> np.ndarray:
    """Evaluate f(ωi, ωo) (RGB, per unit solid angle, without the cosine) for N samples.

    wi, wo, normal, tangent: (N, 3) world-space unit vectors (the tangent need only not be parallel to
    the normal; it is orthogonalised). rho_d, rho_s: (N, 3) ≥ 0. alpha_x, alpha_y: (N,) > 0.
    Returns a float32 (N, 3) array."""
    wi = _vectors("wi", wi, None)
    n = wi.shape[0]
    wo, normal, tangent = (_vectors(k, v, n) for k, v in (("wo", wo), ("normal", normal), ("tangent", tangent)))
    rho_d, rho_s = (_vectors(k, v, n) for k, v in (("rho_d", rho_d), ("rho_s", rho_s)))
    for k, v in (("rho_d", rho_d), ("rho_s", rho_s)):
        if np.any(v < 0.0):
            raise ValueError(f"{k} must be >= 0 (albedo), got min {v.min()}")
    ax, ay = _scalars("alpha_x", alpha_x, n), _scalars("alpha_y", alpha_y, n)
    for k, v in (("wi", wi), ("wo", wo), ("normal", normal), ("tangent", tangent)):
        _unit(k, v)
    if np.any(np.linalg.norm(np.cross(normal, tangent), axis=1) < 1e-6):
        raise ValueError("tangent must not be parallel to normal")
    g_mode, f_mode, eta, eps = _modes(g, fresnel, eta, eps)
    if n == 0:
        return np.zeros((0, 3), dtype=np.float32)
    wp.init()
    out = wp.zeros(n, dtype=wp.vec3, device=device)
    wp.launch(_brdf_kernel, dim=n, device=device,
              inputs=[_wp(wi, wp.vec3, device), _wp(wo, wp.vec3, device), _wp(normal, wp.vec3, device),
                      _wp(tangent, wp.vec3, device), _wp(rho_d, wp.vec3, device), _wp(rho_s, wp.vec3, device),
                      _wp(ax, float, device), _wp(ay, float, device), g_mode, f_mode, eta, eps, out])
    return out.numpy()


def specular_terms(wi_loc, wo_loc, ax, ay, *, g: str = "separable", fresnel: str = "schlick",
                   eta: float = 1.5, eps: float = 0.0, device: str = "cpu") -> dict[str, np.ndarray]:
    """Each factor of the specular lobe, for local-frame directions (N, 3) and roughness (N,).

    Returns float32 arrays: h (N,3) half vector, c = clamp(ωi·h, 0, 1), D = D(h), G1_i, G1_o, G,
    Lambda_i, Lambda_o, F = F(c), fs = ggx_specular. D, G1, Λ and F are evaluated whatever the
    horizon (for oracle tests); fs is zero below it. Directions need not be unit (oracle tests may
    pass exact grazing vectors), but must be finite."""
    wi_loc = _vectors("wi_loc", wi_loc, None)
    n = wi_loc.shape[0]
    wo_loc = _vectors("wo_loc", wo_loc, n)
    ax, ay = _scalars("ax", ax, n), _scalars("ay", ay, n)
    g_mode, f_mode, eta, eps = _modes(g, fresnel, eta, eps)
    wp.init()
    outs = {"h": wp.zeros(n, dtype=wp.vec3, device=device)}
    for k in ("c", "D", "G1_i", "G1_o", "G", "Lambda_i", "Lambda_o", "F", "fs"):
        outs[k] = wp.zeros(n, dtype=float, device=device)
    if n > 0:
        wp.launch(_terms_kernel, dim=n, device=device,
                  inputs=[_wp(wi_loc, wp.vec3, device), _wp(wo_loc, wp.vec3, device), _wp(ax, float, device),
                          _wp(ay, float, device), g_mode, f_mode, eta, eps, *outs.values()])
    return {k: v.numpy() for k, v in outs.items()}


def to_local(v, normal, tangent, *, device: str = "cpu") -> np.ndarray:
    """(N, 3) world vectors → local (t', b, n) coordinates through `local_frame` (for tests and tools).
    Unlike `brdf`, a tangent parallel to the normal is accepted: the frame then uses a fallback tangent."""
    v = _vectors("v", v, None)
    n = v.shape[0]
    normal, tangent = _vectors("normal", normal, n), _vectors("tangent", tangent, n)
    wp.init()
    out = wp.zeros(n, dtype=wp.vec3, device=device)
    if n > 0:
        wp.launch(_to_local_kernel, dim=n, device=device,
                  inputs=[_wp(v, wp.vec3, device), _wp(normal, wp.vec3, device), _wp(tangent, wp.vec3, device), out])
    return out.numpy()
