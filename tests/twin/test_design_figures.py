"""Pattern families (twin.capture.pattern_sets: hadamard, gradients, olat) and the noise figures of a pattern
designer (twin.design.noise), against closed forms and a Monte Carlo simulation of the sensor."""
from __future__ import annotations

import numpy as np
import pytest

import twin
from twin.camera.hdr import merge_hdr_numpy
from twin.camera.sensor import dn_max, effective_gain
from twin.capture import pattern_sets
from twin.capture.plan import DEFAULT_FRAMES, bracket_exposures, bracket_frames
from twin.design.noise import (demultiplexing_gain, hadamard_gain_closed_form, measurement_noise,
                               olat_functional_gain)
from twin.rig.camera import SensorParams


@pytest.fixture(scope="module")
def rig():
    return twin.load_rig("mini")


def _signed(ps):
    """(K, L, 3) signed weights of a (+, -) paired PatternSet."""
    lv = ps.levels.astype(np.int64)
    return (lv[0::2] - lv[1::2]) / 255.0


def _check_pairs(ps, family, count, rig):
    assert ps.names == tuple(f"{family}_{k:02d}{s}" for k in range(count) for s in "+-")
    assert ps.num_leds == rig.num_leds
    assert not ps.levels[:, rig.is_bottom].any()
    assert (ps.levels == ps.levels[..., :1]).all()  # grey: the channels are equal
    assert not (ps.levels[0::2] & ps.levels[1::2]).any()  # an LED is lit in at most one frame of a pair


def _sylvester(order):
    """Sylvester's construction H_2m = [[H, H], [H, -H]] (the oracle for scipy.linalg.hadamard)."""
    H = np.ones((1, 1), dtype=np.int64)
    while len(H) < order:
        H = np.block([[H, H], [H, -H]])
    return H


# --- pattern families -------------------------------------------------------------------------------
def test_hadamard_rows_levels_and_pairs(rig):
    up = ~rig.is_bottom
    n_up = int(up.sum())
    order = 512  # next power of two >= 396 upper LEDs of the mini rig
    assert 256 < n_up <= order
    ps = pattern_sets.hadamard(rig, order - 1)  # every row but the all-ones one
    _check_pairs(ps, "hadamard", order - 1, rig)
    assert set(np.unique(ps.levels)) == {0, 255}
    H = _sylvester(order)
    assert (H @ H.T == order * np.eye(order, dtype=np.int64)).all()  # rows mutually orthogonal (full order)
    signed = _signed(ps)[..., 0]
    assert (signed[:, up] == H[1:, :n_up]).all()  # rows 1.., upper LEDs in rig order
    assert ((ps.levels[0::2] | ps.levels[1::2])[:, up] == 255).all()  # each upper LED lit in + or -
    assert pattern_sets.hadamard(rig, 5).levels.tobytes() == ps.levels[:10].tobytes()


def test_hadamard_rows_on_the_paper_rig():
    """The paper rig's 12,288 upper LEDs need order 16,384: its rows are made without the whole matrix, and
    equal Sylvester's construction (rows 1..4 of order 16,384 from the 128 x 128 block pattern)."""
    paper = twin.load_rig("paper")
    up = ~paper.is_bottom
    signed = _signed(pattern_sets.hadamard(paper, 4))[..., 0][:, up]
    H128 = _sylvester(128)
    # H_16384 = H_128 (x) H_128 (Kronecker): row i < 128 is H_128[0] (x) H_128[i] = 128 copies of H_128[i]
    want = np.tile(H128[1:5], (1, 128))[:, :int(up.sum())]
    assert (signed == want).all()


def test_signed_weights_invert_signed_pairs(rig):
    w = np.random.default_rng(3).uniform(-1, 1, (5, rig.num_leds, 3))
    got = pattern_sets.signed_weights(pattern_sets.signed_pairs(w, [f"p{k}" for k in range(5)], rig.name))
    assert got.shape == (5, rig.num_leds) and got.dtype == np.float64
    assert np.abs(got - w.mean(axis=2)).max() <= 0.5 / 255 + 1e-12  # each frame rounded to 8-bit levels
    with pytest.raises(ValueError, match="pairs"):
        pattern_sets.signed_weights(pattern_sets.uniform(rig))


def test_lines_are_the_plans_linear_lights(rig):
    ps = pattern_sets.lines(rig, 10)
    _check_pairs(ps, "lines", 10, rig)
    assert not ps.levels[1::2].any()  # - frames dark
    ref = pattern_sets.linear_lights(rig, 10)
    assert (ps.levels[0::2] == ref.levels).all()
    with pytest.raises(ValueError, match="count"):
        pattern_sets.lines(rig, 65)


def test_gradients_are_led_directions(rig):
    up = ~rig.is_bottom
    ps = pattern_sets.gradients(rig)
    _check_pairs(ps, "gradients", 4, rig)
    d = rig.leds.positions[up] - np.asarray(rig.sample.origin)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    signed = _signed(ps)[..., 0]
    err = np.abs(signed[:3, up] - d.T).max()
    assert err <= 0.5 / 255 + 1e-12  # rounded to the nearest 8-bit level
    assert err > 0  # and really quantised (the directions are not multiples of 1/255)
    assert (signed[3, up] == 1).all() and not ps.levels[7].any()  # constant: + frame full, - frame dark
    assert (signed[2, up] > 0).all()  # the upper LEDs lie above the sample: d_z > 0


def test_olat_one_led_each(rig):
    up = np.flatnonzero(~rig.is_bottom)
    ps = pattern_sets.olat(rig, 10)
    _check_pairs(ps, "olat", 10, rig)
    plus = ps.levels[0::2, :, 0]
    assert not ps.levels[1::2].any()
    assert ((plus == 255).sum(axis=1) == 1).all() and set(np.unique(plus)) == {0, 255}
    lit = plus.argmax(axis=1)
    assert np.isin(lit, up).all() and (np.diff(lit) > 0).all()
    assert (np.diff(lit).max() - np.diff(lit).min()) <= 1 + np.diff(up).max()  # evenly spread
    everyone = pattern_sets.olat(rig, len(up)).levels[0::2, :, 0].argmax(axis=1)
    assert (everyone == up).all()
    on = np.zeros(rig.num_leds, bool)
    on[up[::3]] = True
    on[rig.is_bottom] = True  # bottom LEDs are never chosen
    masked = pattern_sets.olat(rig, on[up].sum(), on=on).levels[0::2, :, 0].argmax(axis=1)
    assert (masked == up[::3]).all()
    with pytest.raises(ValueError, match="count"):
        pattern_sets.olat(rig, on[up].sum() + 1, on=on)
    with pytest.raises(ValueError, match="^on "):
        pattern_sets.olat(rig, 3, on=on[:-1])


@pytest.mark.parametrize("make, most", [(pattern_sets.hadamard, 511), (pattern_sets.olat, 396)])
@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "3", "most+1"])
def test_family_count_validated(rig, make, most, bad):
    with pytest.raises(ValueError, match="count"):
        make(rig, most + 1 if bad == "most+1" else bad)


# --- multiplexing gain: closed form vs the general demultiplexing ------------------------------------
def _s_matrix(n):
    """The S-matrix of order n (n + 1 a power of two): (1 - H[1:, 1:]) / 2 of the Sylvester H of order n + 1."""
    return (1 - _sylvester(n + 1)[1:, 1:]) / 2.0


@pytest.mark.parametrize("n", [3, 7, 15, 63])
@pytest.mark.parametrize("read_over_shot", [1e6, 100.0, 1.0, 0.01, 1e-6])
def test_demultiplexing_equals_hadamard_closed_form(n, read_over_shot):
    S = _s_matrix(n)
    assert (S.sum(axis=1) == (n + 1) / 2).all()
    shot = 50.0
    gain = demultiplexing_gain(S, np.full(n, shot), read_over_shot * shot)
    closed = hadamard_gain_closed_form(n, read_over_shot * shot, shot)
    np.testing.assert_allclose(gain, closed, rtol=1e-12)


@pytest.mark.parametrize("n", [3, 7, 15, 63])
def test_hadamard_gain_limits(n):
    read_only = (n + 1) / (2 * np.sqrt(n))  # Harwit & Sloane: ~ sqrt(n) / 2
    shot_only = np.sqrt((n + 1) / (2 * n))  # Wuttig: ~ 0.71
    assert hadamard_gain_closed_form(n, 4.0, 0.0) == pytest.approx(read_only, rel=1e-14)
    assert hadamard_gain_closed_form(n, 0.0, 9.0) == pytest.approx(shot_only, rel=1e-14)
    S = _s_matrix(n)
    np.testing.assert_allclose(demultiplexing_gain(S, np.zeros(n), 4.0), read_only, rtol=1e-12)
    np.testing.assert_allclose(demultiplexing_gain(S, np.full(n, 9.0), 0.0), shot_only, rtol=1e-12)
    if n == 63:
        assert read_only > 3.9 and abs(shot_only - np.sqrt(0.5)) < 0.006
    np.testing.assert_allclose(demultiplexing_gain(np.eye(n), np.arange(1.0, n + 1), 3.0), 1.0, rtol=1e-14)


def test_gain_inputs_validated():
    with pytest.raises(ValueError, match="^n "):
        hadamard_gain_closed_form(0, 1.0, 1.0)
    with pytest.raises(ValueError, match="read_var_e2"):
        hadamard_gain_closed_form(3, -1.0, 1.0)
    with pytest.raises(ValueError, match="shot_var_e2"):
        hadamard_gain_closed_form(3, 1.0, np.nan)
    with pytest.raises(ValueError, match="^W "):
        demultiplexing_gain(np.ones((2, 3)), np.ones(3), 1.0)
    with pytest.raises(ValueError, match="^W "):
        demultiplexing_gain(2 * np.eye(3), np.ones(3), 1.0)
    with pytest.raises(ValueError, match="rank"):
        demultiplexing_gain(np.ones((4, 2)), np.ones(2), 1.0)
    with pytest.raises(ValueError, match="source_signal_e"):
        demultiplexing_gain(np.eye(3), np.ones(2), 1.0)
    with pytest.raises(ValueError, match="read_var_e2"):
        demultiplexing_gain(np.eye(3), np.ones(3), np.inf)


# --- measurement noise --------------------------------------------------------------------------------
SENSOR = SensorParams()


def _texels(rig, m=5, seed=0):
    rng = np.random.default_rng(seed)
    T = rng.exponential(2.0, (m, rig.num_leds))
    T[:, rig.is_bottom] = 0.0
    return T


def test_single_led_pattern_gain_is_one(rig):
    T = _texels(rig)
    P = np.zeros((3, rig.num_leds))
    P[0, 7], P[1, 100], P[2, 300] = 1.0, -1.0, 1.0
    gain = olat_functional_gain(rig, P, T, SENSOR)
    assert gain.shape == (3, 5)
    np.testing.assert_array_equal(gain, 1.0)
    out = measurement_noise(rig, P, T, SENSOR)
    np.testing.assert_array_equal(out["signal"][1], -T[:, 100])
    assert (out["exposures_s"][0, 1] == 0).all() and (out["exposures_s"][1, 0] == 0).all()  # dark: not taken
    plan = bracket_frames(bracket_exposures(T[:, 7].max(), SENSOR), DEFAULT_FRAMES)
    assert out["exposures_s"][0, 0].tolist() == plan
    assert not out["saturated"].any() and (out["snr"] > 10).all()


@pytest.mark.parametrize("n", [4, 16, 64])
def test_fixed_exposure_equal_leds_gain(rig, n):
    """n LEDs of equal radiance r at a fixed exposure t, per photo c = read^2 + g^2/12 + dark t electrons^2
    of signal-independent variance and s = r k t of shot variance per LED: all on (one photo) vs n OLAT photos
    gives gain^2 = n (c + s) / (c + n s); half of them negative (two photos) n (c + s) / (2 c + n s).
    Read-noise limited (s -> 0): sqrt(n) and sqrt(n / 2)."""
    t = 1e-3
    g = effective_gain(SENSOR)
    c = SENSOR.read_noise_e ** 2 + g * g / 12 + SENSOR.dark_current_e_per_s * t
    leds = np.flatnonzero(~rig.is_bottom)[:n]
    P = np.zeros((2, rig.num_leds))
    P[0, leds] = 1.0
    P[1, leds] = np.where(np.arange(n) % 2, -1.0, 1.0)
    k_t = SENSOR.electrons_per_radiance_s * t
    for r in (4000 / n / k_t, c / k_t, 1e-9):  # shot noise dominating (4000 e- in all), equal to c, none
        T = np.zeros((1, rig.num_leds))
        T[0, leds] = r
        s = r * k_t
        gain = olat_functional_gain(rig, P, T, SENSOR, exposures=t)[:, 0]
        np.testing.assert_allclose(gain, [np.sqrt(n * (c + s) / (c + n * s)), np.sqrt(n * (c + s) / (2 * c + n * s))],
                                   rtol=1e-12)
    np.testing.assert_allclose(gain, [np.sqrt(n), np.sqrt(n / 2)], rtol=1e-6)


def _raw(B, t, sensor, rng, shape):
    """numpy sensor without fixed patterns: Poisson shot (signal + dark) + Gaussian read noise, full well, ADC."""
    e = rng.poisson(B * sensor.electrons_per_radiance_s * t + sensor.dark_current_e_per_s * t, shape)
    e = np.minimum(e + sensor.read_noise_e * rng.standard_normal(shape), sensor.full_well_e)
    dn = np.floor(e / effective_gain(sensor) + sensor.black_level_dn + 0.5)
    return np.clip(dn, 0, dn_max(sensor)).astype(np.uint16)


@pytest.mark.parametrize("frames", [1, 4])
def test_sigma_matches_monte_carlo(rig, frames):
    """y = B(W+) - B(W-) drawn 20,000 times through a numpy sensor and twin's HDR merge (merge_hdr_numpy) at a
    fixed bracket taken as the plan takes one (bracket_frames: `frames` times, the shortest twice as often). The
    photos' radiances put every texel in another regime:
    read-noise dominated (<= 11 e- in the longest frame), all three exposures used with shot noise dominating the
    longest, two, the shortest only (each frame's use decided > 15 sd from the merge's threshold).
    The standard error of a standard deviation from N = 20,000 draws is ~ 1 / sqrt(2 N) = 0.5%; the tolerance
    of 3% is 6 standard errors."""
    ts = [1e-4, 8e-4, 6.4e-3]
    w = np.zeros(rig.num_leds)
    leds = np.flatnonzero(~rig.is_bottom)[[0, 50, 100, 150]]
    w[leds] = [1.0, 0.5, -1.0, -0.25]
    T = np.zeros((4, rig.num_leds))
    T[:, leds] = [[0.002, 0.002, 0.008, 0.008], [0.2, 0.2, 4.0, 4.0], [30.0, 20.0, 16.0, 16.0],
                  [150.0, 100.0, 1.6, 1.6]]  # B+: 0.003, 0.3, 40, 200; B-: 0.01, 5, 20, 2
    out = measurement_noise(rig, w[None], T, SENSOR, exposures=ts, frames=frames)
    taken = bracket_frames(ts, frames)
    assert out["exposures_s"].shape == (1, 2, len(taken)) and (out["exposures_s"] == taken).all()
    assert not out["saturated"][0]
    rng = np.random.default_rng(1234)
    shape = (100, 200)  # 20,000 independent photosites = draws
    rel = []
    for m in range(4):
        B = [T[m] @ np.clip(w, 0, None), T[m] @ np.clip(-w, 0, None)]
        raws = [[_raw(b, t, SENSOR, rng, shape) for t in taken] for b in B]
        merged = [merge_hdr_numpy(r, taken, SENSOR).mosaic.astype(np.float64) for r in raws]
        y = (merged[0] - merged[1]).ravel()
        assert abs(y.mean() - out["signal"][0, m]) < 5 * out["sigma"][0, m] / np.sqrt(y.size)
        rel.append(y.std(ddof=1) / out["sigma"][0, m] - 1)
    print("Monte Carlo sigma / model - 1:", np.round(rel, 4))
    assert np.abs(rel).max() < 0.03


def test_saturated_pattern(rig):
    P = np.zeros((2, rig.num_leds))
    P[0, ~rig.is_bottom] = 1.0
    P[1, 7] = 1.0
    T = np.zeros((2, rig.num_leds))
    T[0, ~rig.is_bottom] = 30.0  # 396 LEDs x 30 = 11,880: saturates even 20 us (3.3 e- per radiance unit)
    T[1, 7] = 1.0
    out = measurement_noise(rig, P, T, SENSOR)
    assert out["saturated"].tolist() == [True, False]
    assert out["exposures_s"][0, 0, 0] == 20e-6  # clamped to the shortest exposure of the plan
    assert np.isinf(out["sigma"][0, 0]) and out["snr"][0, 0] == 0
    assert np.isfinite(out["sigma"][0, 1]) and out["snr"][0, 1] > 0  # the dim texel is measured
    gain = olat_functional_gain(rig, P, T, SENSOR)
    assert gain[0, 0] == 0 and 0 < gain[0, 1] < np.inf and (gain[1] == 1).all()


def test_measurement_inputs_validated(rig):
    L = rig.num_leds
    P, T = np.zeros((1, L)), np.ones((2, L))
    P[0, 0] = 1
    for bad, match in [((P[:, :-1], T), "patterns_signed"), ((P * 2, T), "patterns_signed"),
                       ((P * np.nan, T), "patterns_signed"), ((np.zeros((1, L)), T), "patterns_signed"),
                       ((P, T[:, :-1]), "lumitexels"), ((P, -T), "lumitexels"), ((P, T * np.inf), "lumitexels")]:
        with pytest.raises(ValueError, match=match):
            measurement_noise(rig, *bad, SENSOR)
    with pytest.raises(ValueError, match="sensor"):
        measurement_noise(rig, P, T, None)
    for exposures in ("auto", -1.0, [1e-3, np.nan], [[1e-3]]):
        with pytest.raises(ValueError, match="exposures"):
            olat_functional_gain(rig, P, T, SENSOR, exposures)
