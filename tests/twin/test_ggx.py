"""Tests of twin/ggx.py against independent oracles: Mitsuba 3's MicrofacetDistribution and fresnel(),
closed forms (Schlick, Lambert, Heitz 2014 inequalities) and numerical integrals (normalisation of D,
of the visible normals, directional albedo). Every kernel test runs on every available Warp device."""

import math
from typing import Any

import numpy as np
import pytest
import warp as wp

from twin.optics import ggx
# (αx, αy): isotropic at both ends of the supported range, anisotropic both ways, extreme anisotropy.
ALPHAS = [(0.006, 0.006), (0.1, 0.3), (0.5, 0.05), (1.0, 1.0), (0.006, 1.0), (0.25, 0.25)]


def _hemisphere(rng, n, zmin=0.0):
    """Seeded directions on the upper hemisphere (z > zmin), rounded to float32 so that the kernel and
    the oracle see bit-identical inputs."""
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    v = v[v[:, 2] > zmin]
    return v.astype(np.float32)


def _terms(wi, wo, ax, ay, device, **kw):
    n = len(wi)
    return ggx.specular_terms(wi, wo, np.full(n, ax), np.full(n, ay), device=device, **kw)


def _rel(a, b):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.abs(a - b) / np.maximum(np.abs(b), 1e-300)


# ---------------------------------------------------------------------------------------------
# 1. Mitsuba 3 oracle for D, G1 and G


@pytest.fixture(scope="module")
def mi():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    return mi


def _v(mi, x):
    return mi.Vector3f(float(x[0]), float(x[1]), float(x[2]))


@pytest.mark.parametrize("ax,ay", ALPHAS)
def test_d_g1_g_match_mitsuba(mi, device, ax, ay):
    rng = np.random.default_rng(1)
    wi, wo = _hemisphere(rng, 1000), _hemisphere(rng, 1000)
    n = min(len(wi), len(wo))
    wi, wo = wi[:n], wo[:n]
    t = _terms(wi, wo, ax, ay, device)
    md = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, ax, ay, False)
    d_mi, g1i_mi, g1o_mi, g_mi = (np.empty(n) for _ in range(4))
    for k in range(n):
        # m = the kernel's own float32 h. D is ill-conditioned in h (|∂lnD/∂h| up to 2/α ≈ 330 for
        # α = 0.006), so comparing at two independently rounded h's would measure rounding of h, not D.
        # χ⁺(v·m) in Mitsuba's smith_g1 holds: ωi·h = ωo·h = |ωi + ωo|/2 > 0.
        m, a, b = _v(mi, t["h"][k]), _v(mi, wi[k]), _v(mi, wo[k])
        d_mi[k] = md.eval(m)
        g1i_mi[k], g1o_mi[k] = md.smith_g1(a, m), md.smith_g1(b, m)
        g_mi[k] = md.G(a, b, m)
    # Both sides are float32 evaluations of the same closed forms on bit-identical inputs: ≲ 10 rounded
    # operations of ≤ 2^-24 ≈ 6e-8 each, amplified ≤ 2× by the square in D's denominator, give ≲ 2e-6;
    # 1e-5 is the requested bound and leaves a 5× margin.
    rtol = 1e-5
    on = d_mi > 0  # Mitsuba cuts D to 0 where D·cosθm ≤ 1e-20; there ours must be below that cut-off too.
    assert on.mean() > 0.99
    assert np.all(t["D"][~on] * t["h"][~on, 2] <= 1e-20 * (1 + rtol))
    assert _rel(t["D"][on], d_mi[on]).max() <= rtol
    for ours, ref in ((t["G1_i"], g1i_mi), (t["G1_o"], g1o_mi), (t["G"], g_mi)):
        assert _rel(ours, ref).max() <= rtol


def test_g1_edge_cases_match_mitsuba(mi, device):
    # Normal incidence (G1 = 1 exactly), exactly grazing (0), just above grazing, below the horizon.
    v = np.array([[0, 0, 1], [1, 0, 0], [0.6, 0.8, 0], [0.9999995, 0, 1e-3], [0.6, 0, -0.8]], np.float32)
    n = len(v)
    t = ggx.specular_terms(v, v, np.full(n, 0.1), np.full(n, 0.3), device=device)
    md = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, 0.1, 0.3, False)
    ref = np.array([md.smith_g1(_v(mi, x), mi.Vector3f(0.0, 0.0, 1.0)) for x in v])
    assert t["G1_i"][0] == 1.0 and np.all(t["G1_i"][[1, 2, 4]] == 0.0)
    # Mitsuba's G1 is two-sided (it only tests (v·m) cosθv > 0), so below the horizon it returns
    # G1(−v); OpenSVBRDF (and we) return 0 there, as asserted above. Same float32 argument as above.
    np.testing.assert_allclose(t["G1_i"][:4], ref[:4], rtol=1e-5, atol=0)


# ---------------------------------------------------------------------------------------------
# 2. Fresnel


@pytest.mark.parametrize("eta", [1.5, 1.33, 2.4, 1 / 1.5, 1 / 1.33, 1.0])
def test_fresnel_dielectric_matches_mitsuba(mi, device, eta):
    rng = np.random.default_rng(2)
    cos = np.concatenate([[0.0, 1e-4, 1.0], rng.uniform(0, 1, 500)])
    sin = np.sqrt(1 - cos**2)
    # Mirror pair about n: h = (0, 0, 1) and ωi·h = cos. We compare at the kernel's own c.
    wi = np.stack([sin, np.zeros_like(cos), cos], 1).astype(np.float32)
    wo = wi * np.array([-1, 1, 1], np.float32)
    t = _terms(wi, wo, 0.2, 0.2, device, fresnel="dielectric", eta=eta)
    c = t["c"].astype(np.float64)
    ref = np.array([mi.fresnel(float(x), float(eta))[0] for x in c])
    # Away from the critical angle both are float32 evaluations of the same closed form (a handful of
    # rounded operations; measured ≤ 6.5e-7 relative for η > 1, ≤ 2.8e-6 for η < 1 outside the band
    # below, where 1/cos²θt ≤ 100 still amplifies); 1e-5 is ≥ 3.5× that. Near the critical angle (η < 1), cosθt = sqrt(1 − sin²θt) turns a
    # 1-ulp difference δ in sin²θt into δ/(2 cos²θt) relative, up to sqrt(δ) ≈ 2.5e-4 absolute at
    # cosθt → 0; within cos²θt < 1e-2 we therefore only ask for 2e-3 absolute (measured 2e-6).
    near_crit = np.abs(1 - (1 - c**2) / eta**2) < 1e-2
    assert _rel(t["F"][~near_crit], ref[~near_crit]).max() <= 1e-5
    assert np.all(np.abs(t["F"][near_crit] - ref[near_crit]) <= 2e-3)
    assert np.all((t["F"] >= 0) & (t["F"] <= 1))
    if eta < 1:  # total internal reflection beyond the critical angle
        assert np.all(t["F"][(1 - c**2) / eta**2 >= 1 + 1e-6] == 1.0)
    # Normal incidence closed form ((η−1)/(η+1))², float32 rounding only.
    assert t["F"][c == 1.0] == pytest.approx(((eta - 1) / (eta + 1)) ** 2, rel=1e-6, abs=1e-7)


def test_fresnel_schlick_closed_form(device):
    rng = np.random.default_rng(3)
    cos = np.concatenate([[0.0, 1.0], rng.uniform(0, 1, 300)])
    sin = np.sqrt(1 - cos**2)
    wi = np.stack([sin, np.zeros_like(cos), cos], 1).astype(np.float32)
    wo = wi * np.array([-1, 1, 1], np.float32)
    t = _terms(wi, wo, 0.2, 0.2, device, fresnel="schlick", eta=1.5)
    c = t["c"].astype(np.float64)
    f0 = ((1.5 - 1) / (1.5 + 1)) ** 2
    assert f0 == pytest.approx(0.04, abs=1e-15)  # OpenSVBRDF's constant follows from η = 1.5
    # float32 evaluation of a 5th power and one FMA-like sum: ≲ 5e-7 relative; 2e-6 is 4× that.
    np.testing.assert_allclose(t["F"], f0 + (1 - f0) * (1 - c) ** 5, rtol=2e-6)
    assert t["F"][c == 1.0] == pytest.approx(0.04, rel=1e-6)  # normal incidence: F = F0
    assert t["F"][c == 0.0] == 1.0  # grazing: F = 1 exactly (0.04 + 0.96 rounds to 1 in float32)


# ---------------------------------------------------------------------------------------------
# 3. Closed forms and integrals


def _random_frames(rng, n):
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    tan = rng.normal(size=(n, 3))
    tan -= np.sum(tan * nrm, 1, keepdims=True) * nrm * rng.uniform(0, 1, (n, 1))  # not orthogonal on purpose
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    return nrm, tan


def _above(rng, nrm, zmin):
    """Unit vectors with v·n ≥ zmin for each row's normal."""
    out = np.empty_like(nrm)
    todo = np.ones(len(nrm), bool)
    while todo.any():
        v = rng.normal(size=(todo.sum(), 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        ok = np.sum(v * nrm[todo], 1) >= zmin
        idx = np.flatnonzero(todo)[ok]
        out[idx] = v[ok]
        todo[idx] = False
    return out


@pytest.mark.parametrize("g", ["separable", "height-correlated"])
@pytest.mark.parametrize("fres", ["schlick", "dielectric"])
def test_reciprocity(device, g, fres):
    rng = np.random.default_rng(4)
    n = 2000
    nrm, tan = _random_frames(rng, n)
    wi, wo = _above(rng, nrm, 1e-3), _above(rng, nrm, 1e-3)
    ax, ay = np.exp(rng.uniform(np.log(0.006), 0, (2, n)))
    zero, rs = np.zeros((n, 3)), rng.uniform(0, 10, (n, 3))  # ρd = 0: test the specular lobe alone
    f1 = ggx.brdf(wi, wo, nrm, tan, zero, rs, ax, ay, g=g, fresnel=fres, device=device)
    f2 = ggx.brdf(wo, wi, nrm, tan, zero, rs, ax, ay, g=g, fresnel=fres, device=device)
    assert np.all(f1 > 0)
    # Everything is evaluated symmetrically except c = ωi·h versus ωo·h (equal in exact arithmetic,
    # each rounded to ~2·2^-24). |dF/dc| ≤ 5(1 − F0) ≈ 4.8 (Schlick; the exact form for η = 1.5 is
    # flatter) and F ≥ F0 = 0.04, so the relative mismatch is ≤ 4.8·2.4e-7/0.04 ≈ 3e-5; 5e-5 bounds it.
    assert _rel(f1, f2).max() <= 5e-5


def _slope_grid(ax, ay, n_psi, n_phi):
    """Midpoint grid over the hemisphere of microfacet normals in GGX slope space (Heitz 2014 §2.3):
    slopes (αx r cosφ, αy r sinφ), r = tanψ, ψ ∈ [0, π/2). Returns unit h (float32) and the quadrature
    weight w with ∫ g(h) dω_h ≈ Σ g(h) w. Uses dω_h = cos³θh d(slope), d(slope) = αx αy r dr dφ and
    dr = sec²ψ dψ. The mapping concentrates nodes where a lobe of width α lives, so one grid serves
    α from 0.006 to 1 (a uniform θ grid would need ~1e5 θ nodes for α = 0.006)."""
    psi = (np.arange(n_psi) + 0.5) * (0.5 * np.pi / n_psi)
    phi = (np.arange(n_phi) + 0.5) * (2 * np.pi / n_phi)
    psi, phi = np.meshgrid(psi, phi, indexing="ij")
    r = np.tan(psi)
    sx, sy = ax * r * np.cos(phi), ay * r * np.sin(phi)
    h = np.stack([-sx, -sy, np.ones_like(sx)], -1)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    w = h[..., 2] ** 3 * ax * ay * r / np.cos(psi) ** 2 * (0.5 * np.pi / n_psi) * (2 * np.pi / n_phi)
    return h.reshape(-1, 3), w.reshape(-1)


INTEGRAL_ALPHAS = [(0.006, 0.006), (0.05, 0.3), (0.3, 0.3), (1.0, 0.2), (1.0, 1.0)]


def test_d_normalisation(device):
    # ∫ D(h) cosθh dω_h = 1 (projected microfacet area = macro area; Walter et al. 2007 eq. 4).
    for ax, ay in INTEGRAL_ALPHAS:
        h, w = _slope_grid(ax, ay, 256, 64)
        hf = h.astype(np.float32)
        t = _terms(hf, hf, ax, ay, device)  # ωi = ωo = h → the kernel's half vector is h
        integral = np.sum(t["D"] * h[:, 2] * w)
        # In ψ the integrand is smooth (sinψ cosψ / π per unit φ), so the midpoint rule with 256 nodes
        # errs by ~(π/512)²/6 ≈ 6e-6 (measured ≤ 6.3e-6); float32 D adds ≲ 1e-6. 1e-4 is a 15× margin.
        assert integral == pytest.approx(1.0, abs=1e-4), (ax, ay)


VIEWS = [0.0, 60.0, 85.0]  # θo in degrees (φo = 30°, off both anisotropy axes)


def _view(theta_deg):
    th, ph = np.radians(theta_deg), np.radians(30.0)
    return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


@pytest.mark.parametrize("g", ["separable", "height-correlated"])
def test_visible_normals_and_albedo(device, g):
    """Heitz 2014 eq. 2: ∫ G1(ωo) ⟨ωo,h⟩⁺ D(h) dω_h = cosθo (this ties the Smith G1 to D), and the
    single-scattering directional albedo ∫ fs cosθi dωi with F ≡ 1 is ≤ 1 (it is that integral with an
    extra G1(ωi) ≤ 1, or G2 ≤ G1(ωo))."""
    for ax, ay in INTEGRAL_ALPHAS:
        h, w = _slope_grid(ax, ay, 256, 128)
        for th in VIEWS:
            wo = _view(th)
            hw = h @ wo  # ⟨ωo, h⟩
            wi = 2 * hw[:, None] * h - wo  # mirror ωo about h
            n = len(h)
            t = _terms(wi.astype(np.float32), np.tile(wo, (n, 1)).astype(np.float32), ax, ay, device, g=g)
            vis = np.sum(t["G1_o"] * np.maximum(hw, 0) * t["D"] * w) / wo[2]
            # Measured |error| ≤ 6.3e-6 on this 256×128 grid (1.6e-6 on 512×256: the midpoint rule's
            # O(Δ²), the kink of ⟨ωo,h⟩⁺ included); 1e-4 is a 15× margin that a wrong constant, a
            # swapped α or a G1 inconsistent with D (all ≥ 1e-2 effects) cannot pass.
            assert vis == pytest.approx(1.0, abs=1e-4), (ax, ay, th)
            # dω_i = 4 ⟨ωo,h⟩ dω_h (Walter et al. 2007 eq. 14); F divided out.
            ok = hw > 0
            albedo = np.sum((t["fs"] / t["F"] * wi[:, 2] * 4 * hw * w)[ok])
            assert albedo <= 1.0 + 1e-4, (ax, ay, th)  # same quadrature tolerance as above
            # Sanity that the integral measures something: a near-mirror keeps almost all energy
            # (measured 0.9973–0.99997); the roughest, α = 1 head-on, keeps ≈ 0.31 (half of its
            # visible normals are tilted > 45°, sending ωi below the horizon).
            assert albedo > (0.99 if max(ax, ay) <= 0.006 else 0.25), (ax, ay, th)


def test_lambert_exact(device):
    rng = np.random.default_rng(5)
    n = 500
    nrm, tan = _random_frames(rng, n)
    wi, wo = _above(rng, nrm, 0.05), _above(rng, nrm, 0.05)
    ax, ay = np.exp(rng.uniform(np.log(0.006), 0, (2, n)))
    f = ggx.brdf(wi, wo, nrm, tan, np.ones((n, 3)), np.zeros((n, 3)), ax, ay, device=device)
    assert np.all(f == np.float32(1 / np.pi))  # exact: 1·(1/π) + 0·fs with finite fs


def test_height_correlated_vs_separable_and_lambda(device):
    rng = np.random.default_rng(6)
    wi, wo = _hemisphere(rng, 3000, 1e-3), _hemisphere(rng, 3000, 1e-3)
    n = min(len(wi), len(wo))
    wi, wo = wi[:n], wo[:n]
    wi[:50] = [0, 0, 1]  # normal incidence for ωi
    for ax, ay in ALPHAS:
        sep = _terms(wi, wo, ax, ay, device, g="separable")
        hc = _terms(wi, wo, ax, ay, device, g="height-correlated")
        # G2 ≥ G1 G1 ⇔ (ri − vi)(ro − vo) ≥ 0 (Heitz 2014 §6): holds exactly; 1e-6 relative is float32
        # rounding of the two different expressions (a few ulp each).
        assert np.all(hc["G"] >= sep["G"] * (1 - 1e-6))
        # Equal when one direction is at normal incidence (Λ = 0 there).
        np.testing.assert_allclose(hc["G"][:50], sep["G"][:50], rtol=1e-6)
        # Λ against Heitz 2014 eq. 86 in float64, and G1 = 1/(1 + Λ), G2 = 1/(1 + Λi + Λo).
        v = wi.astype(np.float64)
        lam = (-1 + np.sqrt(1 + (ax**2 * v[:, 0] ** 2 + ay**2 * v[:, 1] ** 2) / v[:, 2] ** 2)) / 2
        # Λ is well conditioned for v_z ≥ 1e-3 (relative sensitivity ≤ 1 to each input) and is computed
        # without cancellation: float32 gives ≲ 1e-6; the float64 reference from the same float32
        # inputs (cancellation in −1 + sqrt(1 + x) costs it ≤ 1e-16/x, harmless) — 1e-5 relative,
        # with 1e-9 absolute for Λ ≈ 0 near normal incidence.
        np.testing.assert_allclose(sep["Lambda_i"], lam, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(sep["G1_i"], 1 / (1 + sep["Lambda_i"].astype(np.float64)), rtol=1e-5)
        g2 = 1 / (1 + hc["Lambda_i"].astype(np.float64) + hc["Lambda_o"])
        np.testing.assert_allclose(hc["G"], g2, rtol=1e-5)


@pytest.mark.parametrize("g", ["separable", "height-correlated"])
def test_eps_regulariser(device, g):
    """eps = 1e-6 (the authors' regularisers) against eps = 0 (exact maths), away from grazing."""
    rng = np.random.default_rng(7)
    wi, wo = _hemisphere(rng, 2000, 0.1), _hemisphere(rng, 2000, 0.1)
    n = min(len(wi), len(wo))
    wi, wo = wi[:n], wo[:n]
    eps = 1e-6
    rel_max = {}
    for ax, ay in ALPHAS:
        e0 = _terms(wi, wo, ax, ay, device, g=g)
        e1 = _terms(wi, wo, ax, ay, device, g=g, eps=eps)
        rel = _rel(e1["fs"], e0["fs"])
        ci, co = wi[:, 2].astype(np.float64), wo[:, 2].astype(np.float64)
        # First-order bound: D ∝ s⁻² with s's terms scaled by (1 + eps/α)⁻² → ≤ 4 eps / min(α, 1);
        # G1 = 2v/(v + r + eps) → ≤ eps/(2v) each (r ≥ v; the same for G2 with r → r + eps);
        # 1/(4 ci co + eps) → ≤ eps/(4 ci co). 1.2× covers second order; 2e-6 is two float32 evaluations.
        bound = 4 * eps / min(ax, ay, 1.0) + eps / (2 * ci) + eps / (2 * co) + eps / (4 * ci * co)
        assert np.all(rel <= 1.2 * bound + 2e-6), (ax, ay)
        rel_max[(ax, ay)] = rel.max()
        if min(ax, ay) >= 0.9:
            sel = (ci >= 0.5) & (co >= 0.5)
            assert rel[sel].max() < 1e-5  # the "< 1e-5" rule of thumb holds only for rough lobes
    # The regulariser is really applied: for α = 0.006, eps/α ≈ 1.7e-4 shifts D by up to ~7e-4.
    assert rel_max[(0.006, 0.006)] > 1e-4


# ---------------------------------------------------------------------------------------------
# 4. Robustness


def _edge_directions():
    rng = np.random.default_rng(8)
    dirs = [[0, 0, 1], [0, 0, -1]]
    for phi in np.radians([0, 30, 90, 135, 180, 270]):
        c, s = np.cos(phi), np.sin(phi)
        dirs += [[c, s, 0.0]]  # exactly grazing
        for z in (1e-30, 1e-20, 1e-7, 1e-3, -1e-7, -0.5, 0.5):
            dirs += [[c * np.sqrt(1 - z * z), s * np.sqrt(1 - z * z), z]]
    r = rng.normal(size=(6, 3))
    dirs += list(r / np.linalg.norm(r, axis=1, keepdims=True))
    d = np.array(dirs, np.float64)
    return np.concatenate([d, -d])  # so that ωi = −ωo occurs for every direction


def test_finite_everywhere_and_zero_below_horizon(device):
    _check_finite_everywhere(device, "float32")


def _check_finite_everywhere(device, dtype):
    d = _edge_directions()
    m = len(d)
    i, o = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    wi, wo = d[i.ravel()], d[o.ravel()]  # all ordered pairs: includes ωi = ωo and ωi = −ωo
    n = len(wi)
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    nrm, tan = np.tile([0.0, 0, 1], (n, 1)), np.tile([1.0, 0, 0], (n, 1))  # identity frame: exact local z
    ones = np.ones((n, 3))
    for ax in np.geomspace(0.006, 1, 5):
        for ay in np.geomspace(0.006, 1, 5):
            for g in ("separable", "height-correlated"):
                for fres in ("schlick", "dielectric"):
                    for eps in (0.0, 1e-6):
                        kw = dict(g=g, fresnel=fres, eps=eps, device=device, dtype=dtype)
                        f = ggx.brdf(wi, wo, nrm, tan, ones, 10 * ones, np.full(n, ax), np.full(n, ay), **kw)
                        assert f.dtype == np.dtype(dtype)
                        assert np.all(np.isfinite(f)) and np.all(f >= 0)
                        assert np.all(f[below] == 0)
                        t = _terms(wi, wo, ax, ay, **kw)
                        for k, v in t.items():
                            assert np.all(np.isfinite(v)), k
                        assert np.all(t["fs"][below] == 0) and np.all(t["G"][below] == 0)
                        assert np.all(t["fs"] >= 0) and np.all((t["F"] >= 0) & (t["F"] <= 1))


def test_local_frame(device):
    rng = np.random.default_rng(9)
    n = 400
    nrm, tan = _random_frames(rng, n)
    tan[:20] = nrm[:20]  # parallel tangent: the fallback must still give a rotation
    tan[20:40] = -nrm[20:40]
    v = rng.normal(size=(n, 3))
    loc = ggx.to_local(v, nrm, tan, device=device).astype(np.float64)
    # Gram–Schmidt reference in float64 (rows 40: have a usable tangent).
    nn, tt, vv = nrm[40:], tan[40:], v[40:]
    tp = tt - np.sum(tt * nn, 1, keepdims=True) * nn
    tp /= np.linalg.norm(tp, axis=1, keepdims=True)
    ref = np.stack([np.sum(vv * tp, 1), np.sum(vv * np.cross(nn, tp), 1), np.sum(vv * nn, 1)], 1)
    # float32 normalisation, cross and dot products: a few ulp of |v| ≲ 4 → ~1e-6 absolute; 1e-5 margin.
    np.testing.assert_allclose(loc[40:], ref, atol=1e-5)
    np.testing.assert_allclose(loc[:40, 2], np.sum(v[:40] * nrm[:40], 1), atol=1e-5)  # always v·n
    np.testing.assert_allclose(np.linalg.norm(loc, axis=1), np.linalg.norm(v, axis=1), rtol=1e-5)


# ---------------------------------------------------------------------------------------------
# 5. Input validation


def _good(n=4):
    rng = np.random.default_rng(10)
    v = _hemisphere(rng, 64, 0.1)[: 2 * n].astype(np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return dict(wi=v[:n], wo=v[n:], normal=np.tile([0.0, 0, 1], (n, 1)), tangent=np.tile([1.0, 0, 0], (n, 1)),
                rho_d=np.full((n, 3), 0.5), rho_s=np.full((n, 3), 2.0), alpha_x=np.full(n, 0.1),
                alpha_y=np.full(n, 0.2))


def _with(key, fn):
    def make():
        a = _good()
        a[key] = fn(np.array(a[key]))
        return a
    return make


def _set(i, val):
    def fn(a):
        a.flat[i] = val
        return a
    return fn


BAD_INPUTS = [
    ("wi shape", _with("wi", lambda a: a[:, :2]), {}, r"wi must have shape \(N, 3\)"),
    ("wo rows", _with("wo", lambda a: a[:3]), {}, r"wo must have shape \(4, 3\)"),
    ("rho_s shape", _with("rho_s", lambda a: a[:, 0]), {}, r"rho_s must have shape \(4, 3\)"),
    ("alpha shape", _with("alpha_y", lambda a: a[:, None]), {}, r"alpha_y must have shape \(4,\)"),
    ("nan normal", _with("normal", _set(2, np.nan)), {}, "normal contains NaN or Inf"),
    ("inf rho_s", _with("rho_s", _set(0, np.inf)), {}, "rho_s contains NaN or Inf"),
    ("nan alpha", _with("alpha_x", _set(0, np.nan)), {}, "alpha_x contains NaN or Inf"),
    ("zero alpha", _with("alpha_x", _set(1, 0.0)), {}, "alpha_x must be > 0"),
    ("neg alpha", _with("alpha_y", _set(1, -0.1)), {}, "alpha_y must be > 0"),
    ("neg rho_d", _with("rho_d", _set(4, -0.01)), {}, "rho_d must be >= 0"),
    ("neg rho_s", _with("rho_s", _set(4, -1.0)), {}, "rho_s must be >= 0"),
    ("non-unit wo", _with("wo", lambda a: 2 * a), {}, "wo must be unit vectors"),
    ("parallel tangent", _with("tangent", lambda a: np.tile([0.0, 0, 1], (4, 1))), {}, "tangent must not be parallel"),
    ("unknown g", _good, {"g": "correlated"}, "unknown g='correlated'"),
    ("unknown fresnel", _good, {"fresnel": "conductor"}, "unknown fresnel='conductor'"),
    ("bad eta", _good, {"eta": 0.0}, "eta must be a finite relative IOR > 0"),
    ("bad eps", _good, {"eps": -1e-6}, "eps must be finite and >= 0"),
]


@pytest.mark.parametrize("name,make,kw,msg", BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_brdf_rejects_bad_input(device, name, make, kw, msg):
    with pytest.raises(ValueError, match=msg):
        ggx.brdf(**make(), **kw, device=device)


def test_brdf_good_input_and_empty(device):
    f = ggx.brdf(**_good(), device=device)
    assert f.shape == (4, 3) and f.dtype == np.float32 and np.all(f > 0.5 / math.pi)
    e = {k: v[:0] for k, v in _good().items()}
    assert ggx.brdf(**e, device=device).shape == (0, 3)


# ---------------------------------------------------------------------------------------------
# 6. float64: the same generic @wp.func's instantiated with wp.float64 / wp.vec3d / wp.mat33d


def _np_d(h, ax, ay):
    """Anisotropic GGX D in float64, textbook form (Walter et al. 2007 eq. 33; Heitz 2014 eq. 85)."""
    s = h[:, 0] ** 2 / ax**2 + h[:, 1] ** 2 / ay**2 + h[:, 2] ** 2
    return np.where(h[:, 2] > 0, 1 / (np.pi * ax * ay * s**2), 0.0)


def _np_lambda(v, ax, ay):
    """Smith Λ in float64, textbook form (Heitz 2014 eq. 86): (−1 + sqrt(1 + (αx²vx² + αy²vy²)/vz²)) / 2."""
    return (-1 + np.sqrt(1 + (ax**2 * v[:, 0] ** 2 + ay**2 * v[:, 1] ** 2) / v[:, 2] ** 2)) / 2


def _np_fresnel_dielectric(c, eta):
    """Walter et al. 2007 eq. 22 in its own (g, c) form, not the rs/rp form the kernel uses:
    F = ½ (g−c)²/(g+c)² (1 + ((c(g+c) − 1)/(c(g−c) + 1))²), g² = η² − 1 + c²; g² < 0 is total
    internal reflection (F = 1)."""
    g2 = eta**2 - 1 + c**2
    g = np.sqrt(np.maximum(g2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        f = 0.5 * (g - c) ** 2 / (g + c) ** 2 * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)
    return np.where(g2 < 0, 1.0, f)


def _pairs(rng, n, zmin, dtype=np.float64):
    wi, wo = _hemisphere(rng, n, zmin), _hemisphere(rng, n, zmin)
    m = min(len(wi), len(wo))
    return wi[:m].astype(dtype), wo[:m].astype(dtype)


@pytest.mark.parametrize("g", ["separable", "height-correlated"])
@pytest.mark.parametrize("fres,eta", [("schlick", 1.5), ("dielectric", 1.5), ("dielectric", 1 / 1.33),
                                      ("dielectric", 1.0)])
def test_float64_matches_float64_closed_forms(device, g, fres, eta):
    """Mitsuba's scalar variants are float32, so they bound our float32 D/G1/G only to ~1e-6 (section 1).
    In float64 we compare against textbook float64 closed forms, written differently from the kernel's
    cancellation-free forms, at 1e-12: a wrong constant, a float32 literal or a float32 round trip
    anywhere in the float64 path (≥ 6e-8 relative) cannot pass."""
    rng = np.random.default_rng(12)
    # float32-rounded directions (as in the other sections) but no longer unit in float64: the closed
    # forms below do not assume |v| = 1 except D (h is normalised here as in the kernel).
    wi, wo = _pairs(rng, 1000, 0.0)
    wi = np.concatenate([wi, [[0, 0, 1], [1e-3, 0, 1]]])  # normal incidence (Λ = 0), near normal
    wo = np.concatenate([wo, [[0.6, 0, 0.8], [0, 0.6, 0.8]]])
    n = len(wi)
    for ax, ay in ALPHAS:
        t = _terms(wi, wo, ax, ay, device, g=g, fresnel=fres, eta=eta, dtype="float64")
        assert all(v.dtype == np.float64 for v in t.values())
        s = wi + wo
        h = s / np.linalg.norm(s, axis=1, keepdims=True)
        # h: one normalisation, a few ulp. D is computed from our own numpy h, not the kernel's: D's
        # relative sensitivity to h is ≤ ~4/α ≈ 700, so 1e-16 in h gives ≤ 1e-13 in D.
        np.testing.assert_allclose(t["h"], h, rtol=0, atol=1e-15)
        np.testing.assert_allclose(t["D"], _np_d(h, ax, ay), rtol=1e-12, atol=0)
        lam_i, lam_o = _np_lambda(wi, ax, ay), _np_lambda(wo, ax, ay)
        # Λ's textbook form loses ~1e-16 absolute to the cancellation in −1 + sqrt(1 + x) (x → 0 at
        # normal incidence), hence atol; G1 = 1/(1 + Λ) is then good to ~1e-16 relative.
        np.testing.assert_allclose(t["Lambda_i"], lam_i, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(t["Lambda_o"], lam_o, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(t["G1_i"], 1 / (1 + lam_i), rtol=1e-12, atol=0)
        np.testing.assert_allclose(t["G1_o"], 1 / (1 + lam_o), rtol=1e-12, atol=0)
        g_ref = 1 / (1 + lam_i + lam_o) if g == "height-correlated" else 1 / ((1 + lam_i) * (1 + lam_o))
        np.testing.assert_allclose(t["G"], g_ref, rtol=1e-12, atol=0)
        c = np.clip(np.sum(wi * h, 1), 0, 1)
        np.testing.assert_allclose(t["c"], c, rtol=1e-14, atol=1e-15)
        c = t["c"]  # F at the kernel's own c (as in section 2)
        if fres == "schlick":
            f0 = ((eta - 1) / (eta + 1)) ** 2
            f_ref = f0 + (1 - f0) * (1 - c) ** 5
            ok = np.ones(n, bool)
        else:
            f_ref = _np_fresnel_dielectric(c, eta)
            # Within cos²θt < 1e-6 of the critical angle, cosθt = sqrt(1 − sin²θt) amplifies a 1e-16
            # difference by up to 1/(2 cos²θt); outside that band the two forms agree to ≲ 1e-13.
            ok = np.abs(1 - (1 - c**2) / eta**2) >= 1e-6
        np.testing.assert_allclose(t["F"][ok], f_ref[ok], rtol=1e-12, atol=1e-15)
        fs_ref = _np_d(h, ax, ay) * t["F"] * g_ref / (4 * wi[:, 2] * wo[:, 2])
        np.testing.assert_allclose(t["fs"], fs_ref, rtol=1e-12, atol=0)


def test_float64_closed_forms_match_mitsuba(mi):
    """Ties section 6's numpy closed forms to Mitsuba (float32-limited, same 1e-5 as section 1)."""
    rng = np.random.default_rng(13)
    wi, wo = _pairs(rng, 200, 0.0)
    s = wi + wo
    h = s / np.linalg.norm(s, axis=1, keepdims=True)
    for ax, ay in ALPHAS:
        md = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, ax, ay, False)
        hf = h.astype(np.float32)
        d_mi = np.array([md.eval(_v(mi, x)) for x in hf])
        g1_mi = np.array([md.smith_g1(_v(mi, a), _v(mi, m)) for a, m in zip(wi, hf)])
        on = d_mi > 0
        assert on.mean() > 0.99
        assert _rel(_np_d(hf.astype(np.float64), ax, ay)[on], d_mi[on]).max() <= 1e-5
        assert _rel(1 / (1 + _np_lambda(wi, ax, ay)), g1_mi).max() <= 1e-5
    for eta in (1.5, 1 / 1.33):
        c = rng.uniform(0, 1, 200)
        ref = np.array([mi.fresnel(float(x), float(eta))[0] for x in c])
        ok = np.abs(1 - (1 - c**2) / eta**2) >= 1e-2
        assert _rel(_np_fresnel_dielectric(c, eta)[ok], ref[ok]).max() <= 1e-5


def test_float64_agrees_with_float32(device):
    rng = np.random.default_rng(14)
    wi, wo = _pairs(rng, 2000, 0.05, np.float32)  # bit-identical inputs for both precisions
    for ax, ay in ALPHAS:
        for g in ("separable", "height-correlated"):
            for fres, eta in (("schlick", 1.5), ("dielectric", 1.5), ("dielectric", 1 / 1.33)):
                kw = dict(g=g, fresnel=fres, eta=eta)
                t32 = _terms(wi, wo, ax, ay, device, **kw)
                t64 = _terms(wi, wo, ax, ay, device, dtype="float64", **kw)
                # float32 rounding only (measured ≤ 1.1e-6 for every term); near the critical angle
                # (η < 1) F is ill-conditioned in c (see section 2: measured 7.9e-6 within
                # cos²θt < 1e-2), so F and fs are compared outside that band.
                ok = np.abs(1 - (1 - t64["c"] ** 2) / eta**2) >= 1e-2
                for k in t32:
                    sel = ok if k in ("F", "fs") else slice(None)
                    assert t32[k].dtype == np.float32 and t64[k].dtype == np.float64
                    assert _rel(t32[k][sel], t64[k][sel]).max() <= 1e-5, (ax, ay, g, fres, eta, k)
    # Full BRDF through the float64 local frame, random non-orthogonal tangents.
    nrm, tan = _random_frames(rng, 2000)
    wi, wo = _above(rng, nrm, 0.1), _above(rng, nrm, 0.1)
    ax, ay = np.exp(rng.uniform(np.log(0.05), 0, (2, 2000)))
    args = (wi, wo, nrm, tan, rng.uniform(0, 1, (2000, 3)), rng.uniform(0, 10, (2000, 3)), ax, ay)
    f32, f64 = ggx.brdf(*args, device=device), ggx.brdf(*args, device=device, dtype="float64")
    assert f32.dtype == np.float32 and f64.dtype == np.float64
    # α ≥ 0.05 keeps D's sensitivity to the float32-rotated h moderate (≤ ~4/α = 80 per unit of h,
    # ~1e-7 rotation error): measured ≤ 2e-6.
    assert _rel(f32, f64).max() <= 1e-5
    # ρd/π in float64 carries 1/π to full precision (a float32 constant would be off by ~3e-8).
    lam = ggx.brdf(wi, wo, nrm, tan, np.ones((2000, 3)), np.zeros((2000, 3)), ax, ay, device=device, dtype="float64")
    np.testing.assert_allclose(lam, 1 / np.pi, rtol=1e-15, atol=0)
    # The float64 frame: Gram–Schmidt reference at float64 precision.
    v = rng.normal(size=(2000, 3))
    loc = ggx.to_local(v, nrm, tan, device=device, dtype="float64")
    tp = tan - np.sum(tan * nrm, 1, keepdims=True) * nrm
    tp /= np.linalg.norm(tp, axis=1, keepdims=True)
    ref = np.stack([np.sum(v * tp, 1), np.sum(v * np.cross(nrm, tp), 1), np.sum(v * nrm, 1)], 1)
    assert loc.dtype == np.float64
    np.testing.assert_allclose(loc, ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(ggx.to_local(v, nrm, tan, device=device), loc, rtol=0, atol=1e-5)


def test_float64_finite_everywhere_and_zero_below_horizon(device):
    _check_finite_everywhere(device, "float64")


# Autodiff through the generic functions (float64, so that central differences are accurate to ~1e-10).
# Kernels are defined (and instantiated) at import time so that the test module compiles once.


@wp.kernel
def _spec_kernel(wi: wp.array(dtype=wp.vec3d), wo: wp.array(dtype=wp.vec3d), ax: wp.array(dtype=wp.float64),
                 ay: wp.array(dtype=wp.float64), rho_s: wp.float64, g_mode: int, f_mode: int, eta: wp.float64,
                 eps: wp.float64, out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = rho_s * ggx.ggx_specular(wi[i], wo[i], ax[i], ay[i], g_mode, f_mode, eta, eps)


@wp.kernel
def _world_brdf_kernel(wi: wp.array(dtype=Any), wo: wp.array(dtype=Any), nrm: wp.array(dtype=Any),
                       tan: wp.array(dtype=Any), rho_d: wp.array(dtype=Any), rho_s: wp.array(dtype=Any),
                       ax: wp.array(dtype=Any), ay: wp.array(dtype=Any), g_mode: int, f_mode: int, eta: float,
                       eps: float, out: wp.array(dtype=Any)):
    """The call pattern of twin/lumitexel.py: a generic kernel, float32 options cast to the kernel's
    float type, local_frame + ggx_brdf; out = f_r + f_g + f_b."""
    i = wp.tid()
    a = ax[i]
    frame = ggx.local_frame(nrm[i], tan[i])
    f = ggx.ggx_brdf(frame * wi[i], frame * wo[i], rho_d[i], rho_s[i], a, ay[i], g_mode, f_mode, type(a)(eta),
                     type(a)(eps))
    out[i] = f[0] + f[1] + f[2]


_WORLD_KERNELS = {}
for _s, _v3 in ((wp.float32, wp.vec3f), (wp.float64, wp.vec3d)):
    _av, _as = wp.array(dtype=_v3), wp.array(dtype=_s)
    _WORLD_KERNELS[_s] = wp.overload(_world_brdf_kernel, [_av] * 6 + [_as, _as, int, int, float, float, _as])


def _fd_check(launch, params, h=1e-6, rtol=1e-5):
    """params: dict name → float64 array (P, ...) with requires_grad; launch(arrays) → wp output (P,).
    Compares the Tape gradient of sum(out) with central differences in each scalar input."""
    arrs = {k: wp.array(v, dtype=d, requires_grad=True) for k, (v, d) in params.items()}
    tape = wp.Tape()
    with tape:
        out = launch(arrs)
    tape.backward(grads={out: wp.ones(out.shape, dtype=wp.float64)})
    f = np.abs(out.numpy())[:, None]
    base = {k: v.copy() for k, (v, _) in params.items()}
    for k, (v, _) in params.items():
        ad = arrs[k].grad.numpy().reshape(len(v), -1)
        fd = np.zeros_like(ad)
        for j in range(ad.shape[1]):
            vals = []
            for sgn in (1, -1):
                x = base[k].reshape(len(v), -1).copy()
                x[:, j] += sgn * h
                moved = {kk: wp.array(x.reshape(v.shape) if kk == k else base[kk], dtype=dd)
                         for kk, (_, dd) in params.items()}
                vals.append(launch(moved).numpy())
            fd[:, j] = (vals[0] - vals[1]) / (2 * h)
        assert np.all(np.isfinite(ad)), k
        # Central differences in float64: truncation h²f'''/6 ≲ 1e-12/α³ relative and round-off
        # ~1e-16·f/h ≈ 1e-10·f absolute. rtol 1e-5, plus 1e-8·f absolute for components that vanish
        # (e.g. w.r.t. the tangent of an isotropic lobe), leaves a wide margin yet catches any wrong
        # adjoint (those are O(1) relative errors).
        err = np.abs(ad - fd) / (rtol * np.abs(fd) + 1e-8 * f)
        assert err.max() <= 1, (k, ad, fd)


# Well-conditioned points: 30°–60° off the normal, off the anisotropy axes, α ≥ 0.1, no branch within h.
_GRAD_POINTS = [  # (θi, φi, θo, φo) in degrees, αx, αy
    ((35, 20, 50, 200), 0.3, 0.15),
    ((30, 70, 45, 160), 0.5, 0.5),
    ((55, 110, 40, 330), 0.12, 0.4),
    ((20, 45, 60, 250), 1.0, 0.7),
]


def _sph(th, ph):
    th, ph = np.radians(th), np.radians(ph)
    return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


@pytest.mark.parametrize("g_mode", [ggx.G_SEPARABLE, ggx.G_HEIGHT_CORRELATED])
@pytest.mark.parametrize("f_mode,eta,eps", [(ggx.F_SCHLICK, 1.5, 0.0), (ggx.F_DIELECTRIC, 1.5, 1e-6),
                                            (ggx.F_DIELECTRIC, 1 / 1.33, 0.0)])
def test_float64_autodiff_specular_matches_finite_differences(g_mode, f_mode, eta, eps):
    wi = np.array([_sph(*p[0][:2]) for p in _GRAD_POINTS])
    wo = np.array([_sph(*p[0][2:]) for p in _GRAD_POINTS])
    ax = np.array([p[1] for p in _GRAD_POINTS])
    ay = np.array([p[2] for p in _GRAD_POINTS])
    if eta < 1:  # keep the test points clear of total internal reflection (F ≡ 1, zero gradient)
        c = np.sum(wi * (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True), 1)
        assert np.all((1 - c**2) / eta**2 < 0.9)  # sin²θt ≤ 0.86: cos²θt ≥ 0.14, well conditioned

    def launch(a):
        out = wp.zeros(len(ax), dtype=wp.float64, requires_grad=True)
        wp.launch(_spec_kernel, dim=len(ax), device="cpu",
                  inputs=[a["wi"], a["wo"], a["ax"], a["ay"], wp.float64(2.5), g_mode, f_mode, wp.float64(eta),
                          wp.float64(eps), out])
        return out

    params = {"wi": (wi, wp.vec3d), "wo": (wo, wp.vec3d), "ax": (ax, wp.float64), "ay": (ay, wp.float64)}
    _fd_check(launch, params)


@pytest.mark.parametrize("g_mode", [ggx.G_SEPARABLE, ggx.G_HEIGHT_CORRELATED])
def test_float64_autodiff_world_brdf_matches_finite_differences(g_mode):
    """Through local_frame (Gram–Schmidt, cross product, matrix from rows) and ggx_brdf, w.r.t. the
    world directions, the normal, the (non-orthogonal) tangent and α; and the float32 instantiation of
    the same generic kernel agrees with the float64 one."""
    rng = np.random.default_rng(15)
    m = len(_GRAD_POINTS)
    nrm, tan = _random_frames(rng, m)
    frames = []
    for k in range(m):  # world = local expressed in the row's frame (rows t', b, n)
        tp = tan[k] - tan[k] @ nrm[k] * nrm[k]
        tp /= np.linalg.norm(tp)
        frames.append(np.stack([tp, np.cross(nrm[k], tp), nrm[k]]))
    wi = np.array([f.T @ _sph(*p[0][:2]) for f, p in zip(frames, _GRAD_POINTS)])
    wo = np.array([f.T @ _sph(*p[0][2:]) for f, p in zip(frames, _GRAD_POINTS)])
    ax = np.array([p[1] for p in _GRAD_POINTS])
    ay = np.array([p[2] for p in _GRAD_POINTS])
    rho_d, rho_s = rng.uniform(0, 1, (m, 3)), rng.uniform(0.5, 5, (m, 3))

    def launch(a, s=wp.float64):
        out = wp.zeros(m, dtype=s, requires_grad=True)
        wp.launch(_WORLD_KERNELS[s], dim=m, device="cpu",
                  inputs=[a["wi"], a["wo"], a["nrm"], a["tan"], a["rho_d"], a["rho_s"], a["ax"], a["ay"], g_mode,
                          ggx.F_DIELECTRIC, 1.5, 0.0, out])
        return out

    params = {"wi": (wi, wp.vec3d), "wo": (wo, wp.vec3d), "nrm": (nrm, wp.vec3d), "tan": (tan, wp.vec3d),
              "rho_d": (rho_d, wp.vec3d), "rho_s": (rho_s, wp.vec3d), "ax": (ax, wp.float64),
              "ay": (ay, wp.float64)}
    _fd_check(launch, params)
    # float32 instantiation of the same generic kernel: float32 rounding only.
    a32 = {k: wp.array(v, dtype=wp.vec3f if d is wp.vec3d else wp.float32) for k, (v, d) in params.items()}
    a64 = {k: wp.array(v, dtype=d) for k, (v, d) in params.items()}
    f32, f64 = launch(a32, wp.float32).numpy(), launch(a64).numpy()
    assert f32.dtype == np.float32
    np.testing.assert_allclose(f32, f64, rtol=1e-5)
