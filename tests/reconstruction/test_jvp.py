"""Forward-mode derivatives of the fit's lumitexel bases (twin.optics.jvp) and the analytic Jacobian of the GGX
fit built on them (reconstruction.stages.fitting.jacobian._analytic_jacobian), against independent oracles in float64:

* the kernel's derivatives against central differences of twin.lumitexels itself (the forward model, not the
  kernel), along random directions that move the normal, the tangent and both roughnesses at once;
* the fit's Jacobian (lumitexels, both views' photos, closed-form albedos on their box, both losses) against
  central differences of the fit's own residuals.

Tolerances: central differences of step h err by O(h^2) relative plus rounding eps / h, amplified where a column
is small against the residuals' size (a nearly isotropic lobe's tangent angle: 1e-4 of the others). For the bases
(h = 1e-6) 1e-6 relative is met with a margin of 80 (measured 1.2e-8); for the fit's Jacobian (h = 1e-5) 1e-5 with
a margin of 11 (measured 8.7e-7 at worst).
"""
from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest
import torch

import twin
from reconstruction.stages.fitting import FitConfig
from reconstruction.stages.fitting.config import GEOMETRY_SIZE
from reconstruction.stages.fitting.geometry import _from_tensor, _log_geometry, _to_tensor
from reconstruction.stages.fitting.jacobian import _analytic_jacobian, _normal_equations, _tensor_system
from reconstruction.stages.fitting.model import _grey, _loss, _photo_bases, _projected, _residuals
from reconstruction.stages.fitting.problem import _problem
from reconstruction.network.data import LUMITEXEL_SCALE
from twin.capture.pattern_sets import linear_lights
from twin.optics.jvp import basis_jvp


@pytest.fixture(scope="module")
def upper(mini):
    keep = np.flatnonzero(~np.asarray(mini.is_bottom))
    return replace(mini, leds=mini.leds.subset(keep)), keep


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _points(rig, P, seed):
    g = np.random.default_rng(seed)
    s = rig.sample
    pos = s.origin + (g.uniform(-1, 1, (P, 1)) * s.x_axis + g.uniform(-1, 1, (P, 1)) * s.y_axis) * 0.4 * s.max_size
    n = _unit(s.normal + 0.3 * g.normal(size=(P, 3)))
    t = _unit(np.cross(n, g.normal(size=(P, 3))))
    ax, ay = (np.exp(g.uniform(np.log(0.01), np.log(0.8), P)) for _ in range(2))
    return g, pos, n, t, ax, ay


@pytest.mark.slow
def test_basis_derivatives_match_central_differences_of_the_forward_model(upper, device):
    """64 points with narrow to rough, anisotropic lobes, each moved along its own random direction of normal,
    tangent and log roughness: the bases are twin.lumitexels' channels 0 and 1 for rho_d = (1, 0, 0), rho_s =
    (0, 1, 0) to the bit, and their derivatives equal central differences of twin.lumitexels to 1e-6 relative."""
    rig, _ = upper
    P = 64
    g, pos, n0, t0, ax0, ay0 = _points(rig, P, 0)
    a, b, k = g.normal(size=(P, 3)), g.normal(size=(P, 3)), g.normal(size=(P, 2))

    def geometry(u):
        n = _unit(n0 + u * a)
        t = t0 + u * b
        t = _unit(t - (t * n).sum(1, keepdims=True) * n)
        return n, t, ax0 * np.exp(u * k[:, 0]), ay0 * np.exp(u * k[:, 1]), np.stack([t, np.cross(n, t), n], 1)

    def bases(u):
        n, t, ax, ay, _ = geometry(u)
        e = np.eye(3)
        m = twin.lumitexels(rig, pos, n, t, np.tile(e[0], (P, 1)), np.tile(e[1], (P, 1)), ax, ay, camera="primary",
                            dtype="float64", visibility=True, device=device)
        return m[..., 0], m[..., 1]

    h = 1e-6
    (dp, sp), (dm, sm), (d0, s0) = bases(h), bases(-h), bases(0.0)
    n, t, ax, ay, _ = geometry(0.0)
    d_frame = (geometry(h)[4] - geometry(-h)[4]) / (2 * h)  # the frame's own derivative, float64 (error ~1e-10)

    def T(x):
        return torch.as_tensor(x, dtype=torch.float64, device=device)

    val, dD, dS = basis_jvp(rig, T(pos), T(n), T(t), T(ax), T(ay), T(d_frame[:, None]), T(k[:, None]),
                            camera="primary", visibility=True)
    assert val.shape == (2, P, rig.num_leds) and dD.shape == dS.shape == (P, 1, rig.num_leds)
    np.testing.assert_array_equal(val[0].cpu().numpy(), d0)
    np.testing.assert_array_equal(val[1].cpu().numpy(), s0)
    for got, (plus, minus) in ((dD, (dp, dm)), (dS, (sp, sm))):
        fd = (plus - minus) / (2 * h)
        assert np.abs(got[:, 0].cpu().numpy() - fd).max() <= 1e-6 * np.abs(fd).max()
    assert np.abs(fd).max() > 0 and (np.abs(dS[:, 0].cpu().numpy()) > 0).mean() > 0.3  # the check saw slopes


def test_basis_jvp_refuses_what_it_does_not_implement(upper):
    rig, _ = upper
    _, pos, n, t, ax, ay = _points(rig, 2, 1)
    args = [torch.as_tensor(x, dtype=torch.float32) for x in (pos, n, t, ax, ay)]
    with pytest.raises(ValueError, match="separable Smith G1 and Schlick"):
        basis_jvp(rig, *args, torch.zeros(2, 1, 3, 3), torch.zeros(2, 1, 2), fresnel="dielectric")
    with pytest.raises(ValueError, match="d_frame must have shape"):
        basis_jvp(rig, *args, torch.zeros(2, 1, 3), torch.zeros(2, 1, 2))


def _problem64(mini, keep, loss, seed=1, P=40, device="cpu"):
    """A fit problem in float64 (the fit builds float32; every tensor is cast): noisy targets of random texels,
    the lumitexels, the primary view's 64 lines and 16 secondary-view photos, so the albedos hit their box."""
    g, pos, n, t, ax, ay = _points(mini, P, seed)
    rd, rs = g.uniform(0.05, 0.8, (P, 3)), g.uniform(0.1, 3, (P, 3))
    W = linear_lights(mini).weights.astype(np.float32)
    kw = dict(visibility=True, device=device)
    m = twin.lumitexels(mini, pos, n, t, rd, rs, ax, ay, camera="primary", **kw)[:, keep] * LUMITEXEL_SCALE
    lines = twin.measurements(mini, pos, n, t, rd, rs, ax, ay, patterns=W, camera="primary", **kw) * LUMITEXEL_SCALE
    sec = twin.measurements(mini, pos, n, t, rd, rs, ax, ay, patterns=W[:16], camera="secondary",
                            **kw) * LUMITEXEL_SCALE

    def noise(x):
        return x * (1 + 0.05 * g.normal(size=x.shape)).clip(0.5)

    prob = _problem(mini, pos, noise(m), noise(lines), W[:, keep], None, FitConfig(loss=loss, device=device),
                    secondary=(noise(sec), W[:16, keep]))
    cast = {f.name: getattr(prob, f.name).double() for f in fields(prob) if torch.is_tensor(getattr(prob, f.name))}
    cast["photos"] = tuple(replace(p, **{k: getattr(p, k).double() for k in ("M", "M_f", "M_w", "W")})
                           for p in prob.photos)
    q = torch.as_tensor(np.c_[g.normal(size=(P, 2)) * 0.2, g.uniform(0, 3, P), np.log(ax * 1.3), np.log(ay * 0.8)],
                        dtype=torch.float64, device=device)
    return replace(prob, **cast), q


def _rel(J, ref):
    """Per texel and number, |J - ref| / |ref| over the residuals (a column that is 0, as along the lobe of a texel
    whose rho_s sits at 0, counts against the largest column)."""
    norm = ref.norm(dim=2)
    return (J - ref).norm(dim=2) / norm.clamp_min(1e-9 * float(norm.max()))


def _central(prob, q, to_numbers=lambda x: x, h=1e-5):
    e = torch.eye(GEOMETRY_SIZE, dtype=q.dtype, device=q.device) * h
    return torch.stack([(_residuals(prob, to_numbers(q + e[j])) - _residuals(prob, to_numbers(q - e[j])))
                        / (2 * h) for j in range(GEOMETRY_SIZE)], 1)


@pytest.mark.parametrize("loss", ["log1p", "mse"])
def test_fit_jacobian_matches_central_differences(mini, upper, loss, device):
    """The whole residual vector's Jacobian (variable projection: the albedos re-solved with the geometry,
    including those clipped to their box; the secondary view's own albedos; the loss's transform)."""
    prob, q = _problem64(mini, upper[1], loss, device=device)
    J = _analytic_jacobian(prob, q)
    ref = _central(prob, q)
    assert J.shape == ref.shape == (q.shape[0], GEOMETRY_SIZE, _residuals(prob, q).shape[1])
    rel = _rel(J, ref)
    assert float(rel.max()) < 1e-5, rel.max()
    geom = _log_geometry(q, prob.frame)
    val = _grey(prob, geom)
    a, b, _ = _projected(prob, val, _photo_bases(prob, geom, val))
    assert bool(((a == 0) | (a == 1) | (b == 0)).any()) and bool(((a > 0) & (a < 1)).any())  # both kinds seen


def _system_error(A, g, J, r):
    """Per texel, the relative differences of a Gauss-Newton system (A, g) from J J^T, J r."""
    A_ref, g_ref = J @ J.transpose(1, 2), (J @ r[..., None])[..., 0]
    return ((A - A_ref).flatten(1).norm(dim=1) / A_ref.flatten(1).norm(dim=1),
            (g - g_ref).norm(dim=1) / g_ref.norm(dim=1).clamp_min(1e-300))


@pytest.mark.parametrize("loss", ["log1p", "mse"])
def test_normal_equations_are_those_of_the_stored_jacobian(mini, upper, loss, device):
    """The fit's Gauss-Newton system, summed over the lumitexels' rows in one Warp launch that never stores them
    (reconstruction.stages.fitting.sums), against J J^T and J r of the stored analytic Jacobian (itself checked
    against central differences above): float64, within 1e-12 (sums in another order)."""
    prob, q = _problem64(mini, upper[1], loss, device=device)
    A, g, loss_q = _normal_equations(prob, q)
    r = _residuals(prob, q)
    eA, eg = _system_error(A, g, _analytic_jacobian(prob, q), r)
    assert float(eA.max()) < 1e-12 and float(eg.max()) < 1e-12, (eA.max(), eg.max())
    assert torch.allclose(loss_q, r.square().sum(1), rtol=1e-12, atol=0)
    assert torch.allclose(_loss(prob, q), loss_q, rtol=1e-12, atol=0)


def test_tensor_system_in_the_joint_prior_s_coordinates(mini, upper, device):
    """The joint prior's coordinates [u, v, m, d cos 2 theta, d sin 2 theta] (_to_tensor): the chain rule
    through _from_tensor, and where a lobe is isotropic (d = 0, where theta is undefined) the isotropic lobe's own
    derivatives (_isotropic_bases), both against central differences in x (the residuals are smooth in x at d = 0:
    a lobe's anisotropy enters through d^2 and d (cos 2 theta, sin 2 theta) only)."""
    prob, q = _problem64(mini, upper[1], "log1p", seed=2, P=12, device=device)
    q[:3, 4] = q[:3, 3]  # three isotropic texels
    x = _to_tensor(q)
    assert not x[:3, 3:].any()
    r = _residuals(prob, _from_tensor(x))
    A, g, loss = _tensor_system(prob, x)
    eA, eg = _system_error(A, g, _central(prob, x, _from_tensor), r)
    assert float(eA.max()) < 1e-5 and float(eg.max()) < 1e-5, (eA, eg)
    assert torch.allclose(loss, r.square().sum(1), rtol=1e-12, atol=0)
