"""Training-data generator of the acquisition network (reconstruction/network/data.py, paper §6).

Oracles: the analytic moments of the sampling distributions (log-uniform alpha, uniform albedos, the
cosine / uniform tilt laws), binomial bounds on the augmentation fractions, direct `twin.lumitexels`
calls on the same parameters (bit-exact), the white Lambertian normalisation, and byte equality of
regenerated batches. All on the "mini" rig (396 upper LEDs) on the CPU.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

import twin
from reconstruction.network.data import (LUMITEXEL_SCALE, PARAM_KEYS, PERTURBED, RANDOM, SAME, LumitexelStream,
                                 SamplingConfig, heldout_set, pair_targets, perturb_for_secondary,
                                 sample_parameters, swap_albedos, synthesize, white_reference)

N = 2000
B = 16


@pytest.fixture(scope="module")
def rig():
    return twin.load_rig("mini")


def _gen(seed):
    g = torch.Generator()
    g.manual_seed(seed)
    return g


@pytest.fixture(scope="module")
def params(rig):
    return sample_parameters(N, SamplingConfig(), rig, _gen(1))


def _within(x, mean, std, n, k=4.0):
    return abs(float(x) - mean) <= k * std / math.sqrt(n)


def _tilt(p, rig):
    c = (p["normal"].double() @ torch.tensor(rig.sample.normal, dtype=torch.float64)).clamp(-1, 1)
    return torch.rad2deg(torch.acos(c))


# --- configuration ------------------------------------------------------------------------------------
def test_config_defaults_and_validation():
    c = SamplingConfig()
    assert c.alpha_range == (0.006, 0.5) and c.rho_d_range == (0.0, 1.0) and c.rho_s_range == (0.0, 10.0)
    assert (c.area_mm, c.tilt, c.max_tilt_deg, c.perturbed, c.random) == (120.0, "cosine", 60.0, 0.30, 0.10)
    with pytest.raises(ValueError, match="tilt"):
        SamplingConfig(tilt="gaussian")
    with pytest.raises(ValueError, match="alpha_range"):
        SamplingConfig(alpha_range=(0.0, 0.5))
    with pytest.raises(ValueError, match="perturbed"):
        SamplingConfig(perturbed=0.8, random=0.3)
    with pytest.raises(ValueError, match="max_tilt_deg"):
        SamplingConfig(max_tilt_deg=90)
    with pytest.raises(AttributeError):
        c.area_mm = 10.0  # frozen


# --- parameter distributions ----------------------------------------------------------------------------
def test_parameter_shapes_and_dtypes(params):
    for k in PARAM_KEYS:
        assert params[k].dtype == torch.float32, k
    for k in ("position", "normal", "tangent", "rho_d", "rho_s"):
        assert params[k].shape == (N, 3), k
    assert params["alpha_x"].shape == params["alpha_y"].shape == (N,)
    # grey: one albedo on the three channels
    for k in ("rho_d", "rho_s"):
        assert torch.equal(params[k][:, 0], params[k][:, 1]) and torch.equal(params[k][:, 0], params[k][:, 2])


def test_positions_uniform_on_sample_square(params, rig):
    s = rig.sample
    rel = params["position"].double() - torch.tensor(s.origin, dtype=torch.float64)
    assert float((rel @ torch.tensor(s.normal, dtype=torch.float64)).abs().max()) < 1e-4  # on the plane
    for axis in (s.x_axis, s.y_axis):
        c = rel @ torch.tensor(np.asarray(axis), dtype=torch.float64)
        assert float(c.abs().max()) <= 60.0 + 1e-4 and float(c.abs().max()) > 59.0
        assert _within(c.mean(), 0.0, 120 / math.sqrt(12), N) and _within(c.var(), 120**2 / 12, 120**2 / 12 * 0.9, N)


def test_roughness_log_uniform(params):
    la, lb = math.log(0.006), math.log(0.5)
    mean, std = (la + lb) / 2, (lb - la) / math.sqrt(12)
    for k in ("alpha_x", "alpha_y"):
        a = params[k].double()
        assert float(a.min()) >= 0.006 * (1 - 1e-6) and float(a.max()) <= 0.5 * (1 + 1e-6)
        assert _within(torch.log(a).mean(), mean, std, N), (k, float(torch.log(a).mean()), mean)
        # log-uniform, not uniform: the median of alpha is the geometric mean of the range
        assert abs(float(torch.log(a).median()) - mean) < 4 * std * 1.8 / math.sqrt(N)
    corr = np.corrcoef(np.log(params["alpha_x"].numpy()), np.log(params["alpha_y"].numpy()))[0, 1]
    assert abs(corr) < 4 / math.sqrt(N)  # independent


def test_albedos_uniform(params):
    rd, rs = params["rho_d"][:, 0].double(), params["rho_s"][:, 0].double()
    assert 0 <= float(rd.min()) and float(rd.max()) <= 1 and 0 <= float(rs.min()) and float(rs.max()) <= 10
    assert _within(rd.mean(), 0.5, 1 / math.sqrt(12), N) and _within(rs.mean(), 5.0, 10 / math.sqrt(12), N)


@pytest.mark.parametrize("tilt", ["cosine", "uniform"])
def test_frames(rig, tilt):
    cfg = SamplingConfig(tilt=tilt)
    p = sample_parameters(N, cfg, rig, _gen(2))
    n, t = p["normal"].double(), p["tangent"].double()
    assert float((torch.linalg.vector_norm(n, dim=1) - 1).abs().max()) < 1e-6
    assert float((torch.linalg.vector_norm(t, dim=1) - 1).abs().max()) < 1e-6
    assert float((n * t).sum(1).abs().max()) < 1e-6
    th = _tilt(p, rig)
    assert float(th.max()) <= 60.0 + 1e-3
    sin2max = math.sin(math.radians(60)) ** 2
    if tilt == "cosine":  # density cos sin  <=>  sin^2(theta) ~ U[0, sin^2 max]
        s2 = torch.sin(torch.deg2rad(th)) ** 2
        assert _within(s2.mean(), sin2max / 2, sin2max / math.sqrt(12), N)
    else:
        assert _within(th.mean(), 30.0, 60 / math.sqrt(12), N)
    # azimuth and tangent angle uniform: no preferred in-plane direction
    for v in (n, t):
        assert _within(v[:, 0].mean(), 0.0, 1.0, N) and _within(v[:, 1].mean(), 0.0, 1.0, N)


def test_area_larger_than_plane_rejected(rig):
    with pytest.raises(ValueError, match="area_mm"):
        sample_parameters(4, SamplingConfig(area_mm=rig.sample.max_size + 1), rig, _gen(0))


# --- secondary-view augmentation ------------------------------------------------------------------------
def test_secondary_fractions_and_perturbations(params, rig):
    cfg = SamplingConfig()
    s = perturb_for_secondary(params, cfg, _gen(3), rig)
    mode = s["augmentation"]
    for m, f in ((PERTURBED, 0.30), (RANDOM, 0.10), (SAME, 0.60)):
        count = int((mode == m).sum())
        assert abs(count - N * f) <= 4 * math.sqrt(N * f * (1 - f)), (m, count)
    same, per, rnd = mode == SAME, mode == PERTURBED, mode == RANDOM
    for k in PARAM_KEYS:
        assert s[k].dtype == torch.float32 and s[k].shape == params[k].shape
        assert torch.equal(s[k][same], params[k][same]), k  # untouched: bit-identical
        assert torch.equal(s["position"], params["position"])  # the texel stays where it is
    # perturbed: material x N(1, 5%), clipped; grey kept
    for k, hi in (("rho_d", 1.0), ("rho_s", 10.0)):
        r = (s[k][per, 0] / params[k][per, 0]).double()
        assert abs(float(r.std()) - 0.05) < 0.01 and abs(float(r.mean()) - 1) < 0.01
        assert float(s[k][per].max()) <= hi and torch.equal(s[k][:, 0], s[k][:, 2])
    for k in ("alpha_x", "alpha_y"):
        a = s[k][per]
        assert float(a.min()) >= 0.006 * (1 - 1e-6) and float(a.max()) <= 0.5 * (1 + 1e-6)
        assert abs(float((a / params[k][per]).double().std()) - 0.05) < 0.015
    # perturbed normal: tan(angle) = |N(0, 15%)|, so E[tan] = 0.15 sqrt(2/pi); frames stay orthonormal
    n0, n1, t1 = params["normal"].double(), s["normal"].double(), s["tangent"].double()
    ang = torch.acos((n0 * n1).sum(1).clamp(-1, 1))
    assert abs(float(torch.tan(ang[per]).mean()) - 0.15 * math.sqrt(2 / math.pi)) < 0.015
    assert float((torch.linalg.vector_norm(n1, dim=1) - 1).abs().max()) < 1e-6
    assert float((torch.linalg.vector_norm(t1, dim=1) - 1).abs().max()) < 1e-6
    assert float((n1 * t1).sum(1).abs().max()) < 1e-6
    # fully random: a fresh draw, unrelated to the primary, within the ranges
    assert float((s["rho_d"][rnd, 0] - params["rho_d"][rnd, 0]).abs().min()) > 0
    assert abs(np.corrcoef(s["alpha_x"][rnd].log().numpy(), params["alpha_x"][rnd].log().numpy())[0, 1]) < 0.3
    assert float(_tilt({"normal": s["normal"][rnd]}, rig).max()) <= 60.0 + 1e-3
    with pytest.raises(ValueError, match="rig"):
        perturb_for_secondary(params, cfg, _gen(3))


# --- rendering --------------------------------------------------------------------------------------------
def _direct(rig, p, camera):
    """The oracle: twin.lumitexels on the same parameters, upper LEDs, grey, scaled (numpy, float32)."""
    m = twin.lumitexels(rig, *[p[k].numpy() for k in PARAM_KEYS], camera=camera, convention="physical",
                        transparency=np.zeros(len(p["position"])))
    m = m[:, ~rig.is_bottom]
    return (m[..., 0] + m[..., 1] + m[..., 2]) * np.float32(LUMITEXEL_SCALE / 3)


@pytest.mark.parametrize("camera", ["primary", "secondary"])
def test_synthesize_matches_twin_lumitexels(rig, camera):
    p = sample_parameters(B, SamplingConfig(), rig, _gen(4))
    m = synthesize(rig, p, camera, "cpu")
    assert m.dtype == torch.float32 and m.shape == (B, 396) and m.device.type == "cpu"
    np.testing.assert_array_equal(m.numpy(), _direct(rig, p, camera))
    assert float(m.max()) > 0


def test_scale_normalisation(rig):
    # the centre white Lambertian texel reads ~1 at its brightest (the nearest top LED), mini and paper
    o = torch.tensor([rig.sample.origin], dtype=torch.float32)
    white = {"position": o, "normal": torch.tensor([rig.sample.normal]), "tangent": torch.tensor([rig.sample.x_axis]),
             "rho_d": torch.ones(1, 3), "rho_s": torch.zeros(1, 3), "alpha_x": torch.tensor([0.1]),
             "alpha_y": torch.tensor([0.1])}
    m = synthesize(rig, white, "primary", "cpu")
    assert abs(float(m.max()) - 1) < 0.1
    assert abs(white_reference(rig) * LUMITEXEL_SCALE - 1) < 0.01
    paper = twin.load_rig("paper")
    assert abs(white_reference(paper) * LUMITEXEL_SCALE - 1) < 1e-5  # the constant is the paper rig's


# --- streams ------------------------------------------------------------------------------------------------
def _bytes(d):
    out = []
    for k in sorted(d):
        v = d[k]
        if isinstance(v, dict):
            out.append(_bytes(v))
        elif isinstance(v, list):
            out.extend(_bytes(x) for x in v)
        else:
            out.append(v.cpu().numpy().tobytes())
    return b"".join(out)


def test_batch_shapes_values(rig):
    b = LumitexelStream(rig, SamplingConfig(), B, seed=0).batch(0)
    assert b["views"].shape == (B, 2, 396) and b["views"].dtype == torch.float32
    assert b["target"].shape == (B, 396) and torch.equal(b["target"], b["views"][:, 0])
    assert torch.isfinite(b["views"]).all() and float(b["views"].min()) >= 0
    # the views are the primary parameters in the primary camera, the augmented ones in the secondary
    assert torch.equal(b["views"][:, 0], synthesize(rig, b["params"], "primary"))
    assert torch.equal(b["views"][:, 1], synthesize(rig, b["secondary"][0], "secondary"))


def test_seeded_determinism(rig):
    cfg = SamplingConfig()
    s = LumitexelStream(rig, cfg, B, seed=11)
    a1 = _bytes(s.batch(7))
    assert a1 == _bytes(s.batch(7))
    t = LumitexelStream(rig, cfg, B, seed=11)
    t.batch(3)
    assert _bytes(t.batch(7)) == a1  # regenerated alone or after another batch: the same bytes
    assert _bytes(s.batch(8)) != a1
    other = LumitexelStream(rig, cfg, B, seed=12).batch(7)
    assert not torch.equal(other["views"], s.batch(7)["views"])
    assert _bytes(s.pair_batch(2)) == _bytes(LumitexelStream(rig, cfg, B, seed=11).pair_batch(2))


def test_pair_batch(rig):
    s = LumitexelStream(rig, SamplingConfig(), B, seed=5)
    p = s.pair_batch(0)
    pa, pb, tg = p["params_a"], p["params_b"], p["targets"]
    assert tg.shape == (B, 4, 396) and p["views_a"].shape == p["views_b"].shape == (B, 2, 396)
    assert torch.isfinite(tg).all() and float(tg.min()) >= 0
    assert not torch.equal(pa["rho_d"], pb["rho_d"]) and not torch.equal(pa["position"], pb["position"])
    np.testing.assert_array_equal(tg[:, 0].numpy(), p["views_a"][:, 0].numpy())
    np.testing.assert_array_equal(tg[:, 1].numpy(), p["views_b"][:, 0].numpy())
    ab = dict(pa, rho_d=pb["rho_d"], rho_s=pb["rho_s"])  # a's geometry and roughness, b's albedos
    ba = dict(pb, rho_d=pa["rho_d"], rho_s=pa["rho_s"])
    np.testing.assert_array_equal(tg[:, 2].numpy(), _direct(rig, ab, "primary"))
    np.testing.assert_array_equal(tg[:, 3].numpy(), _direct(rig, ba, "primary"))
    assert all(torch.equal(swap_albedos(pa, pb)[k], ab[k]) for k in PARAM_KEYS)
    assert not torch.equal(tg[:, 2], tg[:, 0])
    # with equal albedos the swap changes nothing
    pb_same = dict(pb, rho_d=pa["rho_d"], rho_s=pa["rho_s"])
    t2 = pair_targets(rig, pa, pb_same)
    assert torch.equal(t2[:, 2], t2[:, 0]) and torch.equal(t2[:, 3], t2[:, 1])


def test_heldout_fixed_and_disjoint(rig):
    cfg = SamplingConfig()
    h1, h2 = heldout_set(rig, cfg, B, seed=0, device="cpu"), heldout_set(rig, cfg, B, seed=0, device="cpu")
    assert h1["views"].shape == (B, 2, 396) and h1["target"].shape == (B, 396)
    assert _bytes(h1) == _bytes(h2)
    train = LumitexelStream(rig, cfg, B, seed=0).batch(0)
    assert not torch.equal(h1["views"], train["views"])
    assert not torch.equal(h1["params"]["position"], train["params"]["position"])
    assert torch.isfinite(h1["views"]).all() and float(h1["views"].min()) >= 0


def test_missing_camera(rig):
    one = replace(rig, cameras={"primary": rig.cameras["primary"]})
    with pytest.raises(ValueError, match="secondary"):
        LumitexelStream(one, SamplingConfig(), B, seed=0)
    p = sample_parameters(2, SamplingConfig(), one, _gen(0))
    with pytest.raises(ValueError, match="secondary"):
        synthesize(one, p, "secondary")
    b = LumitexelStream(one, SamplingConfig(), 4, seed=0, cameras=("primary",)).batch(0)
    assert b["views"].shape == (4, 1, 396)
