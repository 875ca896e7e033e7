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

All functions are generic over the float type (float32 or float64, see below), differentiable by Warp's
autodiff away from their guards, and stay finite for α ∈ [0.006, 1] and every direction, including
exactly grazing ones (v_z = 0) and the degenerate half vector ωi = −ωo. The numpy API (`brdf`,
`specular_terms`, `to_local`) evaluates in float32 by default, float64 with dtype="float64".
"""

from __future__ import annotations

import math
from typing import Any

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

# Smallest denominators we allow (written inline as `type(x)(1.0e-30)` and `type(x)(1.0e-15)` in the
# generic functions below: a `wp.constant` is float32 and would not mix with float64 arguments). They are
# far below any value that unit vectors with α ≥ 0.006 can produce away from the horizon
# (cosθ > ~1e-15), so they change nothing there, and they are normal float32 numbers (and a fortiori
# normal float64 ones), so flush-to-zero of denormals on the GPU cannot undo them.
TINY = 1.0e-30
TINY_COS = 1.0e-15
INV_PI = 1.0 / math.pi  # written inline as the literal 0.3183098861837907 (full float64 precision)

# Every @wp.func below is generic over the float type (typing.Any parameters, flags stay int): it works
# from kernels instantiated with float32 (wp.float32, wp.vec3f, wp.mat33f) and with float64 (wp.float64,
# wp.vec3d, wp.mat33d), as long as the vectors and scalars of one call share one precision. Python float
# literals are float32 inside Warp kernels and Warp refuses to mix precisions, so every literal is
# wrapped as `type(x)(literal)` with x an argument of the right scalar type (for a vector v,
# `type(v[0])`). The literal keeps its full float64 value in a float64 instantiation.


@wp.func
def half_vector(wi: Any, wo: Any):
    """normalize(ωi + ωo); returns n = (0,0,1) when ωi = −ωo (then f = 0 anyway: one of the two
    is below or on the horizon, so any unit vector would do)."""
    s = wi + wo
    l2 = wp.dot(s, s)
    if l2 <= type(wi[0])(1.0e-24):
        return type(wi)(type(wi[0])(0.0), type(wi[0])(0.0), type(wi[0])(1.0))
    return s / wp.sqrt(l2)


@wp.func
def ggx_d(h_loc: Any, ax: Any, ay: Any, eps: Any):
    """Anisotropic GGX normal distribution (Walter et al. 2007 eq. 33; Heitz 2014 eq. 85):
    D(h) = χ⁺(h_z) / (π αx αy (hx²/αx² + hy²/αy² + hz²)²).
    eps > 0: the authors' regulariser, h ⊘ (αx+eps, αy+eps, 1+eps) inside the sum, π αx αy unchanged."""
    if h_loc[2] <= type(ax)(0.0):
        return type(ax)(0.0)
    x = h_loc[0] / (ax + eps)
    y = h_loc[1] / (ay + eps)
    z = h_loc[2] / (type(ax)(1.0) + eps)
    s = wp.max(x * x + y * y + z * z, type(ax)(1.0e-12))  # ≥ 1 for a unit h and α ≤ 1; guards h = 0
    return type(ax)(1.0) / (type(ax)(wp.pi) * ax * ay * s * s)


@wp.func
def smith_g1(v_loc: Any, ax: Any, ay: Any, eps: Any):
    """Smith masking for GGX (Walter et al. 2007 eq. 34, anisotropic form of Heitz 2014 eq. 86):
    G1(v) = 2 v_z / (v_z + sqrt(αx² vx² + αy² vy² + vz²)) = 1 / (1 + Λ(v)), 0 for v_z ≤ 0.
    This form has no 1/v_z, so it is finite (→ 0) at grazing. eps: authors' + eps in the denominator."""
    vz = v_loc[2]
    if vz <= type(ax)(0.0):
        return type(ax)(0.0)
    r = wp.sqrt(ax * ax * v_loc[0] * v_loc[0] + ay * ay * v_loc[1] * v_loc[1] + vz * vz)
    return type(ax)(2.0) * vz / wp.max(vz + r + eps, type(ax)(1.0e-30))  # TINY


@wp.func
def smith_lambda(v_loc: Any, ax: Any, ay: Any):
    """Smith Λ for anisotropic GGX (Heitz 2014 eq. 86): Λ = (−1 + sqrt(1 + (αx²vx² + αy²vy²)/vz²)) / 2.
    Written as a² / (2 vz (vz + r)), r = sqrt(a² + vz²), which equals (r − vz)/(2 vz) without its
    cancellation near normal incidence. Λ diverges like 1/v_z at grazing; v_z is clamped to 1e-15 so
    the value stays finite (≤ ~5e29). Only meaningful for v_z > 0 (G is zero below the horizon)."""
    vz = wp.max(v_loc[2], type(ax)(1.0e-15))  # TINY_COS
    a2 = ax * ax * v_loc[0] * v_loc[0] + ay * ay * v_loc[1] * v_loc[1]
    r = wp.sqrt(a2 + vz * vz)
    return a2 / wp.max(type(ax)(2.0) * vz * (vz + r), type(ax)(1.0e-30))  # TINY


@wp.func
def masking_shadowing(wi_loc: Any, wo_loc: Any, ax: Any, ay: Any, g_mode: int, eps: Any):
    """G(ωi, ωo). Separable: G1(ωi) G1(ωo) (OpenSVBRDF, Walter et al. 2007 eq. 23).
    Height-correlated (Heitz 2014 eq. 99): 1/(1 + Λi + Λo). With 1 + Λ = (v_z + r)/(2 v_z) this is
    2 vi vo / (ri vo + ro vi), finite at grazing; eps enters as r → r + eps, exactly as in G1, which
    keeps G_hc ≥ G1 G1 true for every eps (it is (ri − vi)(ro − vo) ≥ 0 after clearing denominators)."""
    vi = wi_loc[2]
    vo = wo_loc[2]
    if vi <= type(ax)(0.0) or vo <= type(ax)(0.0):
        return type(ax)(0.0)
    if g_mode == G_HEIGHT_CORRELATED:
        ri = wp.sqrt(ax * ax * wi_loc[0] * wi_loc[0] + ay * ay * wi_loc[1] * wi_loc[1] + vi * vi) + eps
        ro = wp.sqrt(ax * ax * wo_loc[0] * wo_loc[0] + ay * ay * wo_loc[1] * wo_loc[1] + vo * vo) + eps
        return type(ax)(2.0) * vi * vo / wp.max(ri * vo + ro * vi, type(ax)(1.0e-30))  # TINY
    return smith_g1(wi_loc, ax, ay, eps) * smith_g1(wo_loc, ax, ay, eps)


@wp.func
def fresnel_schlick(c: Any, f0: Any):
    """Schlick's approximation F0 + (1 − F0)(1 − c)^5 (OpenSVBRDF uses F0 = 0.04)."""
    m = type(c)(1.0) - wp.clamp(c, type(c)(0.0), type(c)(1.0))
    m2 = m * m
    return f0 + (type(c)(1.0) - f0) * m2 * m2 * m


@wp.func
def fresnel_dielectric(c: Any, eta: Any):
    """Exact unpolarised Fresnel reflectance (Walter et al. 2007 eq. 22, in its rs/rp form) for light
    arriving from outside at cosθ = c ≥ 0 onto a dielectric of relative IOR η = n_inside / n_outside.
    Total internal reflection (possible for η < 1) gives 1; η = 1 (index matched) gives 0."""
    ci = wp.clamp(c, type(c)(0.0), type(c)(1.0))
    if eta == type(c)(1.0):
        return type(c)(0.0)
    sin2_t = (type(c)(1.0) - ci * ci) / (eta * eta)  # Snell
    if sin2_t >= type(c)(1.0):
        return type(c)(1.0)
    ct = wp.sqrt(type(c)(1.0) - sin2_t)
    rs = (ci - eta * ct) / wp.max(ci + eta * ct, type(c)(1.0e-30))  # TINY
    rp = (eta * ci - ct) / wp.max(eta * ci + ct, type(c)(1.0e-30))
    return type(c)(0.5) * (rs * rs + rp * rp)


@wp.func
def fresnel(c: Any, f_mode: int, eta: Any):
    """Fresnel term at c = ωi·h: exact dielectric, or Schlick with F0 = ((η−1)/(η+1))²."""
    if f_mode == F_DIELECTRIC:
        return fresnel_dielectric(c, eta)
    r = (eta - type(c)(1.0)) / (eta + type(c)(1.0))
    return fresnel_schlick(c, r * r)


@wp.func
def ggx_specular(wi_loc: Any, wo_loc: Any, ax: Any, ay: Any, g_mode: int, f_mode: int, eta: Any, eps: Any):
    """Microfacet specular lobe D F G / (4 cosθi cosθo + eps) (Walter et al. 2007 eq. 20), without ρs.
    Zero below or on the horizon. The denominator floor only matters for cosθi cosθo < ~1e-31,
    where G ~ cosθi cosθo makes the numerator vanish too."""
    ci = wi_loc[2]
    co = wo_loc[2]
    if ci <= type(ax)(0.0) or co <= type(ax)(0.0):
        return type(ax)(0.0)
    h = half_vector(wi_loc, wo_loc)
    d = ggx_d(h, ax, ay, eps)
    g = masking_shadowing(wi_loc, wo_loc, ax, ay, g_mode, eps)
    f = fresnel(wp.clamp(wp.dot(wi_loc, h), type(ax)(0.0), type(ax)(1.0)), f_mode, eta)
    return d * f * g / wp.max(type(ax)(4.0) * ci * co + eps, type(ax)(1.0e-30))  # TINY


@wp.func
def ggx_brdf(wi_loc: Any, wo_loc: Any, rho_d: Any, rho_s: Any, ax: Any, ay: Any, g_mode: int, f_mode: int,
             eta: Any, eps: Any):
    """Full RGB BRDF ρd/π + ρs fs (Ma et al. 2023 §5), zero when either direction is below the horizon."""
    if wi_loc[2] <= type(ax)(0.0) or wo_loc[2] <= type(ax)(0.0):
        return type(rho_d)(type(ax)(0.0), type(ax)(0.0), type(ax)(0.0))
    fs = ggx_specular(wi_loc, wo_loc, ax, ay, g_mode, f_mode, eta, eps)
    return rho_d * type(ax)(0.3183098861837907) + rho_s * fs  # INV_PI = 1/π


@wp.func
def local_frame(n: Any, t: Any):
    """World → local rotation whose rows are (t', b, n), so `frame * v` = (v·t', v·b, v·n).
    t' = normalize(t − (t·n) n) (Gram–Schmidt), b = n × t'. If t is (nearly) parallel to n, any
    perpendicular is used (Duff et al. 2017 branchless basis) so the result is always a rotation.
    Returns a mat33 of n's precision (built from rows, which is generic, unlike wp.mat33(9 floats))."""
    nl = wp.length(n)
    nn = type(n)(type(nl)(0.0), type(nl)(0.0), type(nl)(1.0))
    if nl > type(nl)(1.0e-20):
        nn = n / nl
    tp = t - wp.dot(t, nn) * nn
    tl = wp.length(tp)
    if tl > type(nl)(1.0e-6):
        tp = tp / tl
    else:
        sgn = wp.where(nn[2] >= type(nl)(0.0), type(nl)(1.0), type(nl)(-1.0))
        a = type(nl)(-1.0) / (sgn + nn[2])
        bb = nn[0] * nn[1] * a
        tp = type(n)(type(nl)(1.0) + sgn * nn[0] * nn[0] * a, sgn * bb, -sgn * nn[0])
    b = wp.cross(nn, tp)
    return wp.matrix_from_rows(tp, b, nn)


# --------------------------------------------------------------------------------------------
# Kernels (defined at import time: adding one later would change the module hash and recompile).
# They are generic and instantiated right here (wp.overload, `_KERNELS`) for float32 and float64, so the
# module is built once with all six instantiations and no launch adds one (a generic kernel launched with
# new argument types would add an overload, change the module hash and recompile the whole module).
# They are forward-only (enable_backward=False: the numpy API never differentiates; this halves the
# compile time of this module). The @wp.func's keep their adjoints: they are generated in the module of
# whichever kernel calls them (twin/lumitexel.py, the autodiff tests).


@wp.kernel(enable_backward=False)
def _brdf_kernel(wi: wp.array(dtype=Any), wo: wp.array(dtype=Any), normal: wp.array(dtype=Any),
                 tangent: wp.array(dtype=Any), rho_d: wp.array(dtype=Any), rho_s: wp.array(dtype=Any),
                 alpha_x: wp.array(dtype=Any), alpha_y: wp.array(dtype=Any),
                 g_mode: int, f_mode: int, eta: Any, eps: Any, out: wp.array(dtype=Any)):
    i = wp.tid()
    frame = local_frame(normal[i], tangent[i])
    out[i] = ggx_brdf(frame * wi[i], frame * wo[i], rho_d[i], rho_s[i], alpha_x[i], alpha_y[i],
                      g_mode, f_mode, eta, eps)


@wp.kernel(enable_backward=False)
def _terms_kernel(wi: wp.array(dtype=Any), wo: wp.array(dtype=Any),
                  alpha_x: wp.array(dtype=Any), alpha_y: wp.array(dtype=Any),
                  g_mode: int, f_mode: int, eta: Any, eps: Any,
                  h_out: wp.array(dtype=Any), c_out: wp.array(dtype=Any),
                  d_out: wp.array(dtype=Any), g1i_out: wp.array(dtype=Any),
                  g1o_out: wp.array(dtype=Any), g_out: wp.array(dtype=Any),
                  li_out: wp.array(dtype=Any), lo_out: wp.array(dtype=Any),
                  f_out: wp.array(dtype=Any), fs_out: wp.array(dtype=Any)):
    i = wp.tid()
    a = wi[i]
    b = wo[i]
    ax = alpha_x[i]
    ay = alpha_y[i]
    h = half_vector(a, b)
    c = wp.clamp(wp.dot(a, h), type(ax)(0.0), type(ax)(1.0))
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


@wp.kernel(enable_backward=False)
def _to_local_kernel(v: wp.array(dtype=Any), normal: wp.array(dtype=Any),
                     tangent: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    i = wp.tid()
    out[i] = local_frame(normal[i], tangent[i]) * v[i]


# dtype name → (Warp scalar, Warp vec3, numpy dtype) for the numpy-facing API.
_PRECISIONS = {"float32": (wp.float32, wp.vec3f, np.float32), "float64": (wp.float64, wp.vec3d, np.float64)}


def _instantiate(dtype: str) -> dict:
    s, v, _ = _PRECISIONS[dtype]
    av, asc = wp.array(dtype=v), wp.array(dtype=s)
    return {
        "brdf": wp.overload(_brdf_kernel, [av, av, av, av, av, av, asc, asc, int, int, s, s, av]),
        "terms": wp.overload(_terms_kernel, [av, av, asc, asc, int, int, s, s, av] + [asc] * 9),
        "to_local": wp.overload(_to_local_kernel, [av, av, av, av]),
    }


_KERNELS = {dtype: _instantiate(dtype) for dtype in _PRECISIONS}


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
    return a


UNIT_TOLERANCE = 1e-3  # |1 - |v|| accepted: float32 round-off passes, un-normalised input does not
MIN_FRAME_SIN = 1e-3  # |n x t| below this: Gram-Schmidt of t would amplify float32 error by > 1e3


def check_unit(name: str, a: np.ndarray) -> None:
    """(N, 3) unit vectors, or a ValueError naming the first bad row."""
    norm = np.linalg.norm(a, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > UNIT_TOLERANCE)
    if bad.size:
        raise ValueError(f"{name} must be unit vectors (|v| = 1 ± {UNIT_TOLERANCE:g}): row {bad[0]} has length "
                         f"{norm[bad[0]]:.6f} ({bad.size} row(s))")


def check_material(normal, tangent, rho_d, rho_s, alpha_x, alpha_y) -> None:
    """The per-point BRDF parameters' contract (shapes already checked): unit normal and tangent, a
    tangent not parallel to the normal, albedos >= 0, roughness > 0."""
    check_unit("normal", normal)
    check_unit("tangent", tangent)
    par = np.flatnonzero(np.linalg.norm(np.cross(normal, tangent), axis=1) < MIN_FRAME_SIN)
    if par.size:
        raise ValueError(f"tangent must not be parallel to the normal (row {par[0]}): no local frame exists")
    for k, v in (("rho_d", rho_d), ("rho_s", rho_s)):
        if np.any(v < 0.0):
            raise ValueError(f"{k} must be >= 0 (albedo), got min {v.min():g}")
    for k, v in (("alpha_x", alpha_x), ("alpha_y", alpha_y)):
        if np.any(v <= 0.0):
            raise ValueError(f"{k} must be > 0 (GGX roughness), got min {v.min():g}")


def brdf_modes(g: str, fresnel: str, eta: float, eps: float = 0.0) -> tuple[int, int, float, float]:
    """Validate the BRDF options and return (g_mode, f_mode, eta, eps) for the kernels."""
    if g not in _G_MODES:
        raise ValueError(f"unknown g={g!r}; expected one of {sorted(_G_MODES)}")
    if fresnel not in _F_MODES:
        raise ValueError(f"unknown fresnel={fresnel!r}; expected one of {sorted(_F_MODES)}")
    if not (np.isfinite(eta) and eta > 0.0):
        raise ValueError(f"eta must be a finite relative IOR > 0, got {eta}")
    if not (np.isfinite(eps) and eps >= 0.0):
        raise ValueError(f"eps must be finite and >= 0, got {eps}")
    return _G_MODES[g], _F_MODES[fresnel], float(eta), float(eps)


def _precision(dtype: str):
    if dtype not in _PRECISIONS:
        raise ValueError(f"unknown dtype={dtype!r}; expected one of {sorted(_PRECISIONS)}")
    return _PRECISIONS[dtype]


def _wp(a: np.ndarray, dtype, np_dtype, device) -> wp.array:
    return wp.array(np.ascontiguousarray(a, dtype=np_dtype), dtype=dtype, device=device)


def brdf(wi, wo, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, *, g: str = "separable",
         fresnel: str = "schlick", eta: float = 1.5, eps: float = 0.0, device: str = "cpu",
         dtype: str = "float32") -> np.ndarray:
    """Evaluate f(ωi, ωo) (RGB, per unit solid angle, without the cosine) for N samples.

    wi, wo, normal, tangent: (N, 3) world-space unit vectors (the tangent need only not be parallel to
    the normal; it is orthogonalised). rho_d, rho_s: (N, 3) ≥ 0. alpha_x, alpha_y: (N,) > 0.
    dtype: "float32" (default) or "float64", the precision of the whole evaluation.
    Returns an (N, 3) array of that dtype."""
    scal, vec, npt = _precision(dtype)
    wi = _vectors("wi", wi, None)
    n = wi.shape[0]
    wo, normal, tangent = (_vectors(k, v, n) for k, v in (("wo", wo), ("normal", normal), ("tangent", tangent)))
    rho_d, rho_s = (_vectors(k, v, n) for k, v in (("rho_d", rho_d), ("rho_s", rho_s)))
    ax, ay = _scalars("alpha_x", alpha_x, n), _scalars("alpha_y", alpha_y, n)
    check_unit("wi", wi)
    check_unit("wo", wo)
    check_material(normal, tangent, rho_d, rho_s, ax, ay)
    g_mode, f_mode, eta, eps = brdf_modes(g, fresnel, eta, eps)
    if n == 0:
        return np.zeros((0, 3), dtype=npt)
    wp.init()
    out = wp.zeros(n, dtype=vec, device=device)
    vecs = [_wp(x, vec, npt, device) for x in (wi, wo, normal, tangent, rho_d, rho_s)]
    wp.launch(_KERNELS[dtype]["brdf"], dim=n, device=device,
              inputs=[*vecs, _wp(ax, scal, npt, device), _wp(ay, scal, npt, device), g_mode, f_mode,
                      scal(eta), scal(eps), out])
    return out.numpy()


def specular_terms(wi_loc, wo_loc, ax, ay, *, g: str = "separable", fresnel: str = "schlick",
                   eta: float = 1.5, eps: float = 0.0, device: str = "cpu",
                   dtype: str = "float32") -> dict[str, np.ndarray]:
    """Each factor of the specular lobe, for local-frame directions (N, 3) and roughness (N,).

    Returns arrays of `dtype` ("float32" default, or "float64"): h (N,3) half vector,
    c = clamp(ωi·h, 0, 1), D = D(h), G1_i, G1_o, G, Lambda_i, Lambda_o, F = F(c), fs = ggx_specular.
    D, G1, Λ and F are evaluated whatever the horizon (for oracle tests); fs is zero below it.
    Directions need not be unit (oracle tests may pass exact grazing vectors), but must be finite."""
    scal, vec, npt = _precision(dtype)
    wi_loc = _vectors("wi_loc", wi_loc, None)
    n = wi_loc.shape[0]
    wo_loc = _vectors("wo_loc", wo_loc, n)
    ax, ay = _scalars("ax", ax, n), _scalars("ay", ay, n)
    g_mode, f_mode, eta, eps = brdf_modes(g, fresnel, eta, eps)
    wp.init()
    outs = {"h": wp.zeros(n, dtype=vec, device=device)}
    for k in ("c", "D", "G1_i", "G1_o", "G", "Lambda_i", "Lambda_o", "F", "fs"):
        outs[k] = wp.zeros(n, dtype=scal, device=device)
    if n > 0:
        wp.launch(_KERNELS[dtype]["terms"], dim=n, device=device,
                  inputs=[_wp(wi_loc, vec, npt, device), _wp(wo_loc, vec, npt, device),
                          _wp(ax, scal, npt, device), _wp(ay, scal, npt, device), g_mode, f_mode,
                          scal(eta), scal(eps), *outs.values()])
    return {k: v.numpy() for k, v in outs.items()}


def to_local(v, normal, tangent, *, device: str = "cpu", dtype: str = "float32") -> np.ndarray:
    """(N, 3) world vectors → local (t', b, n) coordinates through `local_frame` (for tests and tools),
    evaluated and returned in `dtype` ("float32" default, or "float64").
    Unlike `brdf`, a tangent parallel to the normal is accepted: the frame then uses a fallback tangent."""
    _, vec, npt = _precision(dtype)
    v = _vectors("v", v, None)
    n = v.shape[0]
    normal, tangent = _vectors("normal", normal, n), _vectors("tangent", tangent, n)
    wp.init()
    out = wp.zeros(n, dtype=vec, device=device)
    if n > 0:
        wp.launch(_KERNELS[dtype]["to_local"], dim=n, device=device,
                  inputs=[_wp(v, vec, npt, device), _wp(normal, vec, npt, device), _wp(tangent, vec, npt, device),
                          out])
    return out.numpy()
