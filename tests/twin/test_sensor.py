"""twin.camera.sensor: the raw-frame simulator against its noise model (means, photon-transfer variances,
fixed patterns, clipping, CFA), determinism, and the numpy optics helpers.

Noise model of one pixel in DN (g electrons per DN, mu mean electrons incl. dark signal):
    temporal variance  = (mu + read_noise^2) / g^2 + 1/12        (shot, read, quantisation)
    fixed patterns     = (PRNU mu)^2 / g^2 + dsnu^2 / g^2        (spatial only, cancel in frame differences)
"""
from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from twin.camera.bayer import cfa_index
from twin.rig.camera import Camera, SensorParams
from twin.camera.sensor import (POISSON_INVERSION_MAX, apply_crosstalk, apply_optics, apply_vignetting, effective_gain,
                         expected_dn, fixed_pattern, fixed_pattern_arrays, raw_frame, saturation_radiance,
                         sensor_consts, simulate_raw, vignetting_factor)

S = SensorParams()  # IMX540-like defaults: 12 bit, RG, 2.4 e/DN, FW 9800 e, read 2.3 e, black 16 DN
H = W = 128
T = 0.01


def flat(level_e, sensor=S, t=T, h=H, w=W):
    """A flat grey radiance whose mean signal is `level_e` photo-electrons (before dark current)."""
    return np.full((h, w, 3), level_e / (sensor.electrons_per_radiance_s * t), np.float32)


def sim(rad, sensor=S, t=T, seed=1, frame=0, key="cam0", gain_db=0.0):
    return simulate_raw(rad, sensor=sensor, exposure_s=t, gain_db=gain_db, seed=seed, frame=frame, camera_key=key)


def model(sensor, mu_e, t=T, gain_db=0.0):
    """(temporal variance, fixed-pattern variance) in DN^2 of a pixel with mean mu_e photo-electrons."""
    g = effective_gain(sensor, gain_db)
    mu = mu_e + sensor.dark_current_e_per_s * t
    temporal = (mu + sensor.read_noise_e ** 2) / g ** 2 + 1 / 12
    fpn = ((sensor.prnu * mu_e) ** 2 + sensor.dsnu_e ** 2) / g ** 2
    return temporal, fpn


# --- statistics -------------------------------------------------------------------------------------
@pytest.mark.parametrize("sensor, level_e", [
    (S, 0.0),  # dark frame: black level + dark signal
    (S, 3.0),  # Poisson by exact inversion
    (S, 0.95 * POISSON_INVERSION_MAX),  # both sides of the switch to the Cornish-Fisher quantile
    (S, 1.05 * POISSON_INVERSION_MAX),
    (S, 800.0),
    (S, 6000.0),
    # a deep-well 16-bit sensor for large counts
    (SensorParams(bit_depth=16, gain_e_per_dn=8.0, full_well_e=3e5, black_level_dn=200.0), 5e4),
])
def test_flat_field_mean_and_photon_transfer_variance(sensor, level_e):
    rad = flat(level_e, sensor)
    a = sim(rad, sensor, frame=0).astype(np.float64)
    b = sim(rad, sensor, frame=1).astype(np.float64)
    exp = expected_dn(rad, sensor, T)
    assert np.ptp(exp) == 0
    temporal, fpn = model(sensor, level_e)
    N = a.size
    # spatial mean of one frame: within 3 sigma / sqrt(N) of the noise-free mean
    assert abs(a.mean() - exp.mean()) < 3 * np.sqrt((temporal + fpn) / N), (a.mean(), exp.mean())
    # given the camera's own fixed pattern, the mean is tighter still: 3 temporal sigma / sqrt(N)
    gain, off = fixed_pattern(sensor, "cam0", H, W)
    e = np.clip(level_e * gain + sensor.dark_current_e_per_s * T + off, None, sensor.full_well_e)
    cond = np.mean(e / sensor.gain_e_per_dn + sensor.black_level_dn)
    assert abs(a.mean() - cond) < 3 * np.sqrt(temporal / N), (a.mean(), cond)
    # temporal variance from the frame difference (fixed patterns cancel): within 10% of the model
    var_t = np.var(a - b) / 2
    assert var_t == pytest.approx(temporal, rel=0.10), (var_t, temporal)
    # spatial variance of one frame includes the fixed patterns
    assert a.var() == pytest.approx(temporal + fpn, rel=0.10)


def test_black_level_at_zero_light():
    a = sim(np.zeros((H, W, 3), np.float32)).astype(np.float64)
    temporal, fpn = model(S, 0.0)
    dark_dn = S.black_level_dn + S.dark_current_e_per_s * T / S.gain_e_per_dn
    assert abs(a.mean() - dark_dn) < 3 * np.sqrt((temporal + fpn) / a.size)
    assert a.min() >= S.black_level_dn - 6 and a.max() <= S.black_level_dn + 6
    # no black level: the ADC clips at 0, the mean rises above the true 0
    z = sim(np.zeros((H, W, 3), np.float32), replace(S, black_level_dn=0.0)).astype(np.float64)
    assert z.min() == 0 and 0.2 < z.mean() < 0.6


def test_saturation_adc_and_full_well():
    # 0 dB: the ADC top (4095 DN = 9790 e above black) comes before the 9800 e full well
    L_sat = saturation_radiance(S, T)
    assert L_sat * S.electrons_per_radiance_s * T + S.dark_current_e_per_s * T == pytest.approx((4095 - 16) * 2.4)
    raw = sim(np.full((H, W, 3), 3 * L_sat, np.float32))
    assert np.all(raw == 4095)
    assert np.all(expected_dn(np.full((2, 2, 3), 3 * L_sat), S, T) == 4095)
    # -6 dB: the full well clips first, at round(9800 / g + 16) DN, noise-free (clipping follows readout)
    g = effective_gain(S, -6.0)
    assert g == pytest.approx(2.4 * 10 ** 0.3)
    fw_dn = np.floor(S.full_well_e / g + S.black_level_dn + 0.5)
    raw = sim(np.full((H, W, 3), 3 * saturation_radiance(S, T, -6.0), np.float32), gain_db=-6.0)
    assert np.all(raw == fw_dn) and fw_dn < 4095
    # just below saturation most pixels are not clipped, just above nearly all are
    below = sim(np.full((H, W, 3), 0.97 * L_sat, np.float32))
    above = sim(np.full((H, W, 3), 1.03 * L_sat, np.float32))
    assert np.mean(below == 4095) < 0.01 and np.mean(above == 4095) > 0.99


def test_gain_db_scales_dn_per_electron():
    rad = flat(500.0)
    m0 = sim(rad).astype(np.float64).mean() - S.black_level_dn
    m6 = sim(rad, gain_db=20 * np.log10(2)).astype(np.float64).mean() - S.black_level_dn
    assert m6 / m0 == pytest.approx(2.0, rel=0.01)
    assert expected_dn(rad, S, T, gain_db=20 * np.log10(2)).mean() - 16 == pytest.approx(
        2 * (expected_dn(rad, S, T).mean() - 16))


@pytest.mark.parametrize("pattern", ["RG", "GR", "GB", "BG"])
def test_cfa_colour_assignment(pattern):
    sensor = replace(S, bayer=pattern)
    idx = cfa_index(pattern, 16, 16)
    for c in range(3):
        rad = np.zeros((16, 16, 3), np.float32)
        rad[..., c] = 2000.0 / (S.electrons_per_radiance_s * T)  # 2000 e on channel c only
        raw = sim(rad, sensor).astype(np.float64)
        lit = raw > S.black_level_dn + 100
        np.testing.assert_array_equal(lit, idx == c)
        assert raw[idx == c].mean() == pytest.approx(expected_dn(rad, sensor, T)[idx == c].mean(), rel=0.02)
    if pattern == "RG":
        assert idx[:2, :2].tolist() == [[0, 1], [1, 2]]  # R at (0,0), G at (0,1) and (1,0), B at (1,1)


# --- the inverse-CDF variates against scipy (the oracle) ---------------------------------------------
import warp as wp  # noqa: E402

from twin.camera import sensor as _sensor  # noqa: E402


@wp.kernel
def _quantiles(mu: wp.array(dtype=wp.float64), u: wp.array(dtype=wp.float64), z: wp.array(dtype=wp.float64),
               n: wp.array(dtype=wp.float64)):
    i = wp.tid()
    z[i] = _sensor.normal_quantile(u[i])
    n[i] = _sensor.poisson_quantile(mu[i], u[i])


def _q(mu, u):
    mu, u = np.broadcast_arrays(np.asarray(mu, np.float64), np.asarray(u, np.float64))
    z, n = wp.zeros(u.size, dtype=wp.float64), wp.zeros(u.size, dtype=wp.float64)
    wp.launch(_quantiles, dim=u.size, inputs=[wp.array(mu.ravel(), dtype=wp.float64),
                                              wp.array(u.ravel(), dtype=wp.float64)], outputs=[z, n])
    return z.numpy(), n.numpy()


def test_normal_quantile_is_as241():
    from scipy.special import ndtri

    u = np.concatenate([np.linspace(1e-9, 1 - 1e-9, 20001), 10.0 ** -np.arange(1, 17), 1 - 10.0 ** -np.arange(1, 16)])
    z, _ = _q(1.0, u)
    ref = ndtri(u)
    assert np.max(np.abs(z - ref) / np.maximum(np.abs(ref), 1e-3)) < 1e-14


@pytest.mark.parametrize("mu", [0.3, 5.0, 30.0, 63.9, 64.0, 200.0, 1e4, 1e7])
def test_poisson_quantile_against_scipy(mu):
    """The shot-noise quantile: the exact Poisson quantile below the switch, the skew-corrected Gaussian one
    above it (at most 1 count away, in < 1e-3 of draws); moments and a chi-square against
    scipy.stats.poisson on 2e5 seeded uniforms."""
    from scipy import stats

    rng = np.random.default_rng(int(mu * 10))
    N = 200_000
    u = (np.floor(rng.uniform(0, 2**52, N)) + 0.5) / 2**52  # the kernel's uniform grid
    _, n = _q(mu, u)
    ks = np.arange(stats.poisson.ppf(1e-12, mu), stats.poisson.ppf(1 - 1e-12, mu) + 1)
    cdf_k = stats.poisson.cdf(ks, mu)
    exact = ks[np.minimum(np.searchsorted(cdf_k, u), ks.size - 1)]  # the smallest k with cdf(k) >= u
    miss = np.mean(n != exact)
    assert np.max(np.abs(n - exact)) <= 1
    assert miss == 0 if mu < POISSON_INVERSION_MAX else miss < 1e-3
    # moments: within 4 standard errors (Var of the sample variance: (mu + 2 mu^2) / N for a Poisson)
    assert abs(n.mean() - mu) < 4 * np.sqrt(mu / N)
    assert abs(n.var() - mu) < 4 * np.sqrt((mu + 2 * mu * mu) / N)
    assert abs(stats.skew(n) - 1 / np.sqrt(mu)) < 4 * np.sqrt(6 / N)
    # chi-square over bins of >= 5 expected draws
    edges, last = [], 0.0  # bin starts: each bin holds >= 5 expected draws
    for k, c in zip(ks[1:], cdf_k[:-1]):
        if c - last >= 5 / N:
            edges.append(k)
            last = c
    cdf = stats.poisson.cdf(np.array(edges) - 1, mu)
    expected = np.diff(np.concatenate([[0.0], cdf, [1.0]])) * N
    observed = np.bincount(np.searchsorted(edges, n, side="right"), minlength=len(expected))
    chi2 = np.sum((observed - expected) ** 2 / expected)
    assert stats.chi2.sf(chi2, len(expected) - 1) > 1e-3


def test_poisson_quantile_is_monotone_in_the_mean():
    """For fixed draws the count never decreases as the mean grows, across the switch too."""
    mu = np.linspace(40.0, 90.0, 5001)
    for u in (1e-6, 0.02, 0.3, 0.5, 0.77, 0.999, 1 - 1e-9):
        _, n = _q(mu, u)
        assert np.all(np.diff(n) >= 0), u


def test_a_few_ulps_of_the_mean_move_a_pixel_by_at_most_1_dn():
    """The CPU vs CUDA contract: a radiance that differs in its last bits (another device's rounding)
    changes no raw value by more than 1 DN, and few of them at all."""
    rng = np.random.default_rng(11)
    rad = (rng.uniform(0, 1.2, (256, 256, 3)) ** 3 * 3 * saturation_radiance(S, T)).astype(np.float32)
    base = sim(rad, seed=5, frame=9).astype(np.int32)
    for ulps in (1, 2, 4):
        moved = rad.copy()
        for _ in range(ulps):
            moved = np.nextafter(moved, np.where(rng.uniform(size=rad.shape) < 0.5, 0, np.inf).astype(np.float32))
        d = np.abs(sim(moved, seed=5, frame=9).astype(np.int32) - base)
        assert d.max() <= 1, ulps
        assert np.mean(d > 0) < 1e-3, (ulps, np.mean(d > 0))


# --- fixed patterns -----------------------------------------------------------------------------------
def test_fixed_patterns_per_camera():
    big = replace(S, prnu=0.05, dsnu_e=0.0, read_noise_e=0.0, dark_current_e_per_s=0.0)
    gain, off = fixed_pattern(big, "cam0", H, W)
    gain2, _ = fixed_pattern(big, "cam0", H, W)
    np.testing.assert_array_equal(gain, gain2)
    assert gain.std() == pytest.approx(0.05, rel=0.05) and abs(gain.mean() - 1) < 0.002
    np.testing.assert_array_equal(off, 0.0)
    _, off_d = fixed_pattern(S, "cam0", H, W)
    assert off_d.std() == pytest.approx(S.dsnu_e, rel=0.05)
    other, _ = fixed_pattern(big, "cam1", H, W)
    assert abs(np.corrcoef(gain.ravel(), other.ravel())[0, 1]) < 0.03

    # the simulated frames carry the pattern: 5% PRNU at 5000 e is 250 e against 71 e of shot noise,
    # so frames correlate at ~250^2 / (250^2 + 71^2) = 0.93 whatever the seed and frame
    rad = flat(5000.0, big)
    a = sim(rad, big, seed=1, frame=0).astype(np.float64).ravel()
    b = sim(rad, big, seed=99, frame=7).astype(np.float64).ravel()
    c = sim(rad, big, seed=1, frame=0, key="cam1").astype(np.float64).ravel()
    assert np.corrcoef(a, b)[0, 1] > 0.88
    assert np.corrcoef(a, gain.ravel())[0, 1] > 0.93
    assert abs(np.corrcoef(a, c)[0, 1]) < 0.03
    assert np.corrcoef(c, other.ravel())[0, 1] > 0.93


def test_frames_differ_and_noise_is_independent():
    rad = flat(1000.0)
    a, b = sim(rad, frame=0).astype(np.float64), sim(rad, frame=1).astype(np.float64)
    assert np.mean(a != b) > 0.8
    ta, tb = a - expected_dn(rad, S, T), b - expected_dn(rad, S, T)
    # with the fixed pattern in common, residual correlation is fpn / (temporal + fpn) ~ 0.1
    temporal, fpn = model(S, 1000.0)
    assert np.corrcoef(ta.ravel(), tb.ravel())[0, 1] == pytest.approx(fpn / (temporal + fpn), abs=0.03)
    # neighbouring pixels are uncorrelated
    assert abs(np.corrcoef(ta[:, :-1].ravel(), ta[:, 1:].ravel())[0, 1]) < 0.03


# --- determinism ----------------------------------------------------------------------------------
def _sha(a):
    return hashlib.sha256(a.tobytes()).hexdigest()


def test_determinism_bytes():
    rng = np.random.default_rng(3)
    rad = rng.uniform(0, 3 * saturation_radiance(S, T), size=(64, 96, 3)).astype(np.float32)
    h = _sha(sim(rad, seed=42, frame=3))
    assert h == _sha(sim(rad, seed=42, frame=3))
    assert h == _sha(sim(rad.astype(np.float64), seed=42, frame=3))
    others = {_sha(sim(rad, seed=43, frame=3)), _sha(sim(rad, seed=42, frame=4)),
              _sha(sim(rad, seed=42, frame=3, key="cam1")), _sha(sim(rad, seed=2**40 + 42, frame=3))}
    assert h not in others and len(others) == 4


def test_fixed_patterns_drawn_once_give_the_same_bytes():
    """A capture draws a camera's fixed patterns once (fixed_pattern_arrays) and hands them to every raw_frame:
    the same bytes as simulate_raw, which draws them per call; and the same bytes as when the raw kernel drew
    them per pixel in every frame (the digest pinned from that version, main at 2975137)."""
    import warp as wp

    rng = np.random.default_rng(3)
    rad = rng.uniform(0, 3 * saturation_radiance(S, T), size=(64, 96, 3)).astype(np.float32)
    assert _sha(sim(rad, seed=42, frame=3)) == "68502fe4183f341d1cbe78b70bf7fbde7e39edcdcdc129787f7b3bff8723590f"
    rad_wp = wp.array(rad, dtype=wp.vec3f, device="cpu")
    fixed = fixed_pattern_arrays(sensor_consts(S, exposure_s=T, seed=0, frame=0, camera_key="cam0"), 64, 96, "cpu")
    np.testing.assert_array_equal(fixed[0].numpy(), fixed_pattern(S, "cam0", 64, 96)[0])
    for seed, frame, t in ((42, 3, T), (7, 0, T / 3), (7, 1, 2 * T)):
        k = sensor_consts(S, exposure_s=t, seed=seed, frame=frame, camera_key="cam0")
        assert np.array_equal(raw_frame(rad_wp, k, fixed=fixed).numpy(), sim(rad, t=t, seed=seed, frame=frame))
    small = fixed_pattern_arrays(sensor_consts(S, exposure_s=T, seed=0, frame=0, camera_key="cam0"), 32, 96, "cpu")
    with pytest.raises(ValueError, match=r"fixed patterns must be two \(64, 96\) arrays"):
        raw_frame(rad_wp, k, fixed=small)


def test_noise_is_a_function_of_the_pixel_not_the_launch():
    """The random state of a pixel depends on (seed, frame, camera, row, col) only: a crop of the
    radiance gives exactly the same raw values at the same sensor positions."""
    rng = np.random.default_rng(4)
    rad = rng.uniform(0, saturation_radiance(S, T), size=(48, 64, 3)).astype(np.float32)
    full = sim(rad, seed=7, frame=2)
    np.testing.assert_array_equal(sim(rad[:20, :30], seed=7, frame=2), full[:20, :30])


# --- errors ---------------------------------------------------------------------------------------
def test_input_errors():
    rad = flat(100.0, h=4, w=4)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        sim(rad[..., :2])
    bad = rad.copy()
    bad[0, 0, 0] = -1
    with pytest.raises(ValueError, match=">= 0"):
        sim(bad)
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        sim(bad)
    with pytest.raises(ValueError, match="exposure"):
        sim(rad, t=0.0)
    with pytest.raises(TypeError, match="seed"):
        sim(rad, seed=True)
    with pytest.raises(TypeError, match="frame"):
        sim(rad, frame=1.5)
    with pytest.raises(TypeError, match="camera_key"):
        sim(rad, key="")


# --- optics helpers ---------------------------------------------------------------------------------
def test_vignetting_hand_worked():
    K = np.array([[100.0, 0, 1.5], [0, 100.0, 0.5], [0, 0, 1]])  # principal point at the centre of 4x2
    f = vignetting_factor(K, 4, 2, (-0.2, 0.1, -0.05))
    # corner (0, 0): r^2 = (1.5^2 + 0.5^2) / (0.25 * (4^2 + 2^2)) = 2.5 / 5 = 0.5
    assert f[0, 0] == pytest.approx(1 - 0.2 * 0.5 + 0.1 * 0.25 - 0.05 * 0.125)
    # (row 0, col 1): r^2 = (0.25 + 0.25) / 5 = 0.1
    assert f[0, 1] == pytest.approx(1 - 0.02 + 0.001 - 0.00005)
    np.testing.assert_allclose(f, f[::-1, ::-1])
    rgb = np.ones((2, 4, 3), np.float32) * np.array([1, 2, 3], np.float32)
    ff = np.full((2, 4), 0.5)
    out = apply_vignetting(rgb, K, 4, 2, (-0.2, 0.1, -0.05), flat_field=ff)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, rgb * (f * 0.5)[..., None], rtol=1e-6)
    np.testing.assert_array_equal(apply_vignetting(rgb, K, 4, 2, (0, 0, 0)), rgb)
    with pytest.raises(ValueError):
        apply_vignetting(rgb, K, 2, 4, (0, 0, 0))
    with pytest.raises(ValueError, match=">= 0"):
        apply_vignetting(rgb, K, 4, 2, (-5.0, 0, 0))


def test_crosstalk_and_optics_from_camera():
    M = ((0.9, 0.1, 0.0), (0.05, 0.9, 0.05), (0.0, 0.2, 0.8))
    rgb = np.zeros((2, 2, 3))
    rgb[0, 0] = (1, 0, 0)
    rgb[1, 1] = (1, 2, 3)
    out = apply_crosstalk(rgb, M)
    np.testing.assert_allclose(out[0, 0], (0.9, 0.05, 0.0))
    np.testing.assert_allclose(out[1, 1], (0.9 + 0.2, 0.05 + 1.8 + 0.15, 0.4 + 2.4))
    np.testing.assert_array_equal(out[0, 1], 0)
    cam = Camera("c", 4, 2, [[100.0, 0, 1.5], [0, 100.0, 0.5], [0, 0, 1]], np.zeros(5), np.eye(3), np.zeros(3),
                 sensor=replace(S, crosstalk=M, vignetting=(-0.2, 0.0, 0.0)))
    rgb = np.random.default_rng(0).uniform(size=(2, 4, 3))
    np.testing.assert_allclose(apply_optics(rgb, cam),
                               apply_crosstalk(rgb, M) * vignetting_factor(cam.K, 4, 2, (-0.2, 0, 0))[..., None])
