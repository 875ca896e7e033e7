"""twin.camera.hdr: bracket choice and the noise-optimal merge, on frames from twin.camera.sensor.simulate_raw.

Error bound used below (the noise model of twin.camera.hdr): a photosite's merged value has predicted
standard deviation sigma = 1 / sqrt(weights_sum) from shot, read and quantisation noise; the fixed
PRNU pattern (relative sigma `prnu`, the same in every frame) adds prnu * L, so the predicted relative
error is sqrt(1 / (weights_sum L^2) + prnu^2). The z-scores of the merge against the truth must have
unit spread, and the RMS relative error in every decade of radiance must match that prediction.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from twin.camera.bayer import demosaic, mosaic
from twin.rig.camera import SensorParams
from twin.camera.hdr import choose_bracket, frame_radiance, merge_hdr, merge_hdr_numpy, saturation_threshold_dn
from twin.camera.sensor import expected_dn, saturation_electrons, saturation_radiance, simulate_raw

S = SensorParams()
H, W = 192, 256
L_MIN, L_MAX = 1e-3, 1e2  # 1e5 dynamic range


def _sim(rad, ts, sensor=S, seed=11):
    return [simulate_raw(rad, sensor=sensor, exposure_s=t, seed=seed, frame=i, camera_key="cam0")
            for i, t in enumerate(ts)]


@pytest.fixture(scope="module")
def scene():
    """A log ramp from 1e-3 to 1e2 along the columns, tinted per channel, bracketed with
    choose_bracket (5 frames, x8 apart), simulated and merged."""
    logL = np.linspace(np.log10(L_MIN), np.log10(L_MAX), W)
    rad = (10 ** logL[None, :, None] * np.array([1.0, 0.8, 0.6])[None, None, :] * np.ones((H, 1, 1))).astype(np.float32)
    ts = choose_bracket(float(rad.max()), S, n=5, ratio=8.0)
    raws = _sim(rad, ts)
    res = merge_hdr(raws, ts, S)
    true = mosaic(rad.astype(np.float64), S.bayer)
    return rad, ts, raws, res, true


def test_choose_bracket():
    ts = choose_bracket(50.0, S, n=4, ratio=4.0)
    assert len(ts) == 4
    np.testing.assert_allclose(np.array(ts[1:]) / np.array(ts[:-1]), 4.0)
    # the brightest radiance fills 80% of the saturation signal (here the ADC top: 4079 DN) in the shortest
    dn = expected_dn(np.full((2, 2, 3), 50.0), S, ts[0])
    assert dn.mean() == pytest.approx(S.black_level_dn + 0.8 * saturation_electrons(S) / S.gain_e_per_dn)
    assert 50.0 < saturation_radiance(S, ts[0])
    with pytest.raises(ValueError):
        choose_bracket(0.0, S)
    with pytest.raises(ValueError):
        choose_bracket(1.0, S, ratio=1.0)


def test_hdr_recovers_radiance_over_1e5(scene):
    rad, ts, raws, res, true = scene
    assert res.radiance.shape == (H, W, 3) and res.radiance.dtype == np.float32
    assert not res.saturated_mask.any()
    assert res.frames_used.min() >= 1
    sigma2 = 1.0 / res.weights_sum.astype(np.float64) + (S.prnu * true) ** 2
    z = (res.mosaic - true) / np.sqrt(sigma2)
    # unit spread, no bias, no outliers (N = 49k photosites: |z| > 5.5 has probability ~2e-3)
    assert z.std() == pytest.approx(1.0, abs=0.04), z.std()
    assert abs(z.mean()) < 0.03
    assert np.abs(z).max() < 5.5
    rel = (res.mosaic - true) / true
    for lo in range(-3, 2):  # every decade of the 1e5 range
        m = (true >= 10.0 ** lo) & (true < 10.0 ** (lo + 1))
        predicted = np.sqrt(np.mean(sigma2[m] / true[m] ** 2))
        measured = np.sqrt(np.mean(rel[m] ** 2))
        assert measured == pytest.approx(predicted, rel=0.08), (lo, measured, predicted)
        assert predicted < 0.05  # the bound: < 5% RMS in every decade (3.4% in the darkest, ~1.8% above)
    # demosaiced output: in a smooth ramp, within a few sigma of the truth too
    rel_rgb = (res.radiance[2:-2, 2:-2] - rad[2:-2, 2:-2]) / rad[2:-2, 2:-2]
    assert np.sqrt(np.mean(rel_rgb ** 2)) < 0.03


def test_hdr_better_than_any_single_exposure(scene):
    rad, ts, raws, res, true = scene
    rms_merged = np.sqrt(np.mean(((res.mosaic - true) / true) ** 2))
    thr = saturation_threshold_dn(S)
    for lo in range(-3, 2):
        m = (true >= 10.0 ** lo) & (true < 10.0 ** (lo + 1))
        merged = np.sqrt(np.mean(((res.mosaic[m] - true[m]) / true[m]) ** 2))
        singles = []
        for r, t in zip(raws, ts):
            if np.all(r[m] < thr):  # only exposures that are unsaturated over the whole decade
                singles.append(np.sqrt(np.mean(((frame_radiance(r, t, S)[m] - true[m]) / true[m]) ** 2)))
        assert singles and merged <= min(singles) * 1.02, (lo, merged, singles)
    for r, t in zip(raws, ts):  # over the whole scene each single exposure is far worse
        single = np.sqrt(np.mean(((frame_radiance(r, t, S) - true) / true) ** 2))
        assert rms_merged < 0.1 * single


def test_saturated_everywhere_mask():
    ts = [0.001, 0.004]
    L_sat = saturation_radiance(S, ts[0])
    rad = np.full((32, 32, 3), 0.2 * L_sat, np.float32)
    rad[8:16, 10:20] = 3 * L_sat  # saturated in both frames
    rad[20:24, 4:8, 1] = 3 * L_sat  # only green saturated
    raws = _sim(rad, ts)
    res = merge_hdr(raws, ts, S)
    true = mosaic(rad.astype(np.float64), S.bayer)
    expected = true > L_sat
    np.testing.assert_array_equal(res.saturated_mask, expected)
    assert np.all(res.weights_sum[expected] == 0) and np.all(res.weights_sum[~expected] > 0)
    # the shortest exposure's clipped estimate, a lower bound
    np.testing.assert_allclose(res.mosaic[expected], frame_radiance(raws[0], ts[0], S)[expected], rtol=1e-6)
    assert np.all(res.mosaic[expected] < true[expected])
    # demosaiced values depending on such a photosite are flagged
    np.testing.assert_array_equal(res.clipped, demosaic(expected.astype(float), S.bayer) > 0)
    assert res.clipped[11, 14].all() and not res.clipped[2, 2].any()
    # elsewhere the merge is accurate (0.2 L_sat reaches 80% of saturation in the x4 frame: unsaturated)
    ok = ~res.clipped.any(axis=2)
    assert np.abs(res.radiance[ok] / rad[ok] - 1).mean() < 0.02


def test_no_bias_at_the_exclusion_threshold():
    """Sites whose long-exposure mean sits AT the exclusion threshold, or 5% below it: unbiased (within 4
    standard errors). Before the shorter frames decided (twin.camera.hdr: valid_k), truncating the long
    frame's own noise biased the first band by -0.4% (~0.8 sigma x its weight share)."""
    s = replace(S, prnu=0.0, dsnu_e=0.0)
    ts = [0.001, 0.008]
    e_thr = (saturation_threshold_dn(s) - s.black_level_dn) * s.gain_e_per_dn
    L_at = e_thr / (s.electrons_per_radiance_s * ts[1])
    rad = np.ones((128, 256, 3), np.float32)
    rad[:64] *= 0.95 * L_at
    rad[64:] *= L_at
    raws = _sim(rad, ts, s)
    res = merge_hdr(raws, ts, s)
    true = mosaic(rad.astype(np.float64), s.bayer)
    rel = res.mosaic / true - 1
    for band in (rel[:64], rel[64:]):
        assert abs(band.mean()) < 4 * band.std() / np.sqrt(band.size)
    # the old rule, each frame kept by its own reading, on the same frames (shot-noise-limited weights: the
    # maximum-likelihood sum e / sum k t): the -0.4% it had
    thr = saturation_threshold_dn(s)
    e_all = [(r.astype(np.float64) - s.black_level_dn) * s.gain_e_per_dn - s.dark_current_e_per_s * t
             for r, t in zip(raws, ts)]
    L_own = (sum(np.where(r < thr, e, 0.0) for r, e in zip(raws, e_all))
             / sum(np.where(r < thr, s.electrons_per_radiance_s * t, 0.0) for r, t in zip(raws, ts)))
    assert -0.006 < (L_own[64:] / true[64:] - 1).mean() < -0.002


def test_merge_units_and_errors():
    # a single unsaturated frame: the merge is that frame's radiance estimate, in input units
    rad = np.full((16, 16, 3), 0.5, np.float32)
    r = _sim(rad, [0.01])
    res = merge_hdr(r, [0.01], S)
    np.testing.assert_allclose(res.mosaic, frame_radiance(r[0], 0.01, S), rtol=1e-6)
    assert abs(res.radiance.mean() / 0.5 - 1) < 0.01
    with pytest.raises(ValueError, match="exposures"):
        merge_hdr(r, [0.01, 0.02], S)
    with pytest.raises(TypeError, match="uint16"):
        merge_hdr([r[0].astype(np.int32)], [0.01], S)
    with pytest.raises(ValueError, match="positive"):
        merge_hdr(r, [0.0], S)
    with pytest.raises(ValueError, match="shape"):
        merge_hdr([r[0], r[0][:8]], [0.01, 0.02], S)
    with pytest.raises(ValueError, match="at least one"):
        merge_hdr([], [], S)


@pytest.mark.parametrize("bayer, gain_db, n", [("RG", 0.0, 3), ("GB", 6.0, 5), ("BG", -3.0, 1)])
def test_merge_kernels_are_the_numpy_merge(bayer, gain_db, n, device):
    """merge_kernel + demosaic_kernel (float64, no contraction) against the numpy merge on the same frames, on
    every device: every output identical (same formulas in the same order, correctly rounded sqrt),
    saturated-everywhere sites and the frames the shorter ones rule out included."""
    sensor = replace(S, bayer=bayer)
    rng = np.random.default_rng(n)
    rad = (rng.uniform(0, 1, (37, 50, 3)) ** 4 * 3 * saturation_radiance(sensor, 1e-3, gain_db)).astype(np.float32)
    ts = [1e-3 * 8.0 ** i for i in range(n)][::-1]  # longest first: `shortest` must be found, not assumed
    raws = [simulate_raw(rad, sensor=sensor, exposure_s=t, gain_db=gain_db, seed=3, frame=i, camera_key="c",
                         device=device) for i, t in enumerate(ts)]
    ours, ref = merge_hdr(raws, ts, sensor, gain_db, device=device), merge_hdr_numpy(raws, ts, sensor, gain_db)
    assert ref.saturated_mask.any() and not ref.saturated_mask.all()
    if n > 1:  # some sites drop a frame that its own reading would have kept: the shorter frames' prediction
        own = sum((r < saturation_threshold_dn(sensor, gain_db)).astype(np.uint8) for r in raws)
        assert (ref.frames_used < own).any()
    for f in ("radiance", "saturated_mask", "weights_sum", "mosaic", "clipped", "frames_used"):
        np.testing.assert_array_equal(getattr(ours, f), getattr(ref, f), err_msg=f)


def test_repeated_frames_of_an_exposure_average():
    """A bracket whose every exposure is taken 4 times (as twin.capture.plan.bracket_frames takes the longer
    ones): the merge weighs the repeats alike, so its predicted temporal variance (1 / weights_sum) is a quarter
    of one frame's, and the merged photosites scatter about the truth as that predicts (unit z spread, no bias),
    PRNU's fixed pattern included."""
    rad = np.full((64, 64, 3), 0.3, np.float32) * np.array([1.0, 0.8, 0.6], np.float32)
    ts = choose_bracket(float(rad.max()), S, n=3, ratio=8.0)
    one = merge_hdr(_sim(rad, ts, seed=5), ts, S)
    ts4 = [t for t in ts for _ in range(4)]
    four = merge_hdr(_sim(rad, ts4, seed=5), ts4, S)
    true = mosaic(rad.astype(np.float64), S.bayer)
    ratio = np.median(one.weights_sum.astype(np.float64) / four.weights_sum.astype(np.float64))
    assert ratio == pytest.approx(0.25, rel=0.02)
    assert four.frames_used.min() >= 4
    z = (four.mosaic - true) / np.sqrt(1.0 / four.weights_sum.astype(np.float64) + (S.prnu * true) ** 2)
    assert z.std() == pytest.approx(1.0, abs=0.05) and abs(z.mean()) < 0.05
