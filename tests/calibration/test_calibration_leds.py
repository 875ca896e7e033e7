"""LED calibration (positions, normals, profiles Psi, RGB intensities) against the twin's truth: a
perturbed mini rig photographs a diffuse plate at two heights, each LED alone, through its sensor model, and
calibration.leds recovers the LEDs from those photos alone. Goals (calibration.leds.LED_GOALS): LED position
within 0.5 mm (median), Psi within 2% over the directions in which each LED lights the sample."""
from __future__ import annotations

import math

import numpy as np
import pytest

import twin
from calibration.leds import (LED_GOALS, LEDCalibrationError, _log_geometry, calibrate_leds, calibrate_leds_from_plate,
                             plate_samples)
from twin.rig.perturb import perturb_leds
from twin.targets.diffuse import DiffusePlate


@pytest.fixture(scope="module")
def calibrated():
    nominal = twin.load_rig("mini")
    truth = perturb_leds(nominal, 11)  # held back: docs/calibration.md's figures are for perturbation seed 3
    rig, report = calibrate_leds_from_plate(nominal, truth, frames=16, seed=2, step=18, progress=False)
    return nominal, truth, rig, report["leds"]


def test_perturbation_is_seeded_and_moves_only_the_upper_leds():
    nominal = twin.load_rig("mini")
    a, b = perturb_leds(nominal, 3), perturb_leds(nominal, 3)
    assert a.digest() == b.digest() != nominal.digest() != perturb_leds(nominal, 4).digest()
    up = ~nominal.is_bottom
    moved = np.linalg.norm(a.leds.positions - nominal.leds.positions, axis=1)
    assert moved[~up].max() == 0 and 2 < np.median(moved[up]) < 8
    ratio = a.leds.profile[up, 0] / nominal.leds.profile[up, 0]
    assert 0.75 < ratio.min() and ratio.max() < 1.25 and ratio.std() > 0.02
    assert np.allclose(np.linalg.norm(a.leds.normals, axis=1), 1.0)


def test_plate_model_matches_the_forward_model():
    """The procedure's closed form (calibration.leds._log_geometry) against the twin's Warp forward model on a
    perturbed rig (profile exponents != 1), noise-free, at points the frame does not shade: float32 level."""
    rig = perturb_leds(twin.load_rig("mini"), 5)
    plate = DiffusePlate(height_mm=40.0)
    cam = rig.camera("primary")
    uv = np.stack(np.meshgrid(np.arange(20, cam.width - 20, 7), np.arange(20, cam.height - 20, 7)), -1).reshape(-1, 2)
    X, on = plate.points(rig, cam, uv.astype(np.float64))
    X = X[on]
    top = np.flatnonzero(rig.leds.positions[:, 2] > 100)[:5]
    rad = plate.radiance(rig, "primary", top)
    for j, led in enumerate(top):
        want = rad[j].reshape(-1, 3)[np.ravel_multi_index((uv[on, 1], uv[on, 0]), (cam.height, cam.width))]
        g = np.exp(_log_geometry(rig.leds.positions[led], rig.leds.normals[led], rig.leds.profile[led, 0],
                                 X[:, None, :], np.array([0.0, 0.0, 1.0]), plate.albedo))
        got = g[:, None] * rig.leds.intensity[led]
        assert np.abs(got / want - 1).max() < 1e-5, led


def test_noise_free_photos_give_the_truth_back():
    """Identifiability: photos without the sensor (only the camera's optics and their inverse) recover every
    LED of a board exactly, i.e. the model and the plate's two heights pin the LED down."""
    from twin.camera.sensor import apply_optics

    nominal = twin.load_rig("mini")
    truth = perturb_leds(nominal, 7)
    leds = np.flatnonzero((truth.leds.board == 3) & ~truth.is_bottom)[::6]
    samples = {int(k): [] for k in leds}
    for name in truth.cameras:
        cam = truth.camera(name)
        for h in (0.0, 40.0):
            plate = DiffusePlate(height_mm=h)
            for led, rad in zip(leds, plate.radiance(truth, name, leds)):
                if rad.max() > 0:
                    samples[int(led)].append(plate_samples(apply_optics(rad, cam), None, cam, nominal, plate))
    fit = calibrate_leds(nominal, samples, plate.albedo)
    assert np.abs(fit.positions - truth.leds.positions[fit.index]).max() < 0.01
    assert np.abs(fit.exponent - truth.leds.profile[fit.index, 0]).max() < 1e-3
    assert np.abs(fit.intensity / truth.leds.intensity[fit.index] - 1).max() < 1e-3


def test_leds_meet_the_goals(calibrated):
    nominal, truth, rig, r = calibrated
    assert r["passed"], r
    assert r["position_mm"]["median"] <= LED_GOALS["position_mm_median"]
    assert r["profile_shape_pct"]["median"] <= LED_GOALS["profile_shape_pct_median"]
    # what a capture depends on: the light each LED sends towards the sample, 10x better than nominal
    assert r["emission_pct"]["median"] * 10 < r["nominal_error"]["emission_pct"]["median"]
    assert r["position_mm"]["median"] * 5 < r["nominal_error"]["position_mm"]["median"]


def test_calibrated_rig_is_a_rig(calibrated, tmp_path):
    _, truth, rig, r = calibrated
    twin.save_rig(rig, tmp_path / "rig")
    back = twin.load_rig(tmp_path / "rig")
    assert back.digest() == rig.digest()
    assert back.leds.board.tolist() == truth.leds.board.tolist()


def test_bad_photos_are_named():
    rig = twin.load_rig("mini")
    cam, plate = rig.camera("primary"), DiffusePlate()
    ok = np.full((cam.height, cam.width, 3), 0.01)
    with pytest.raises(LEDCalibrationError, match="LED 7.*is"):
        plate_samples(ok[:-1], None, cam, rig, plate, label="LED 7")
    bad = ok.copy()
    bad[5, 5, 1] = math.nan
    with pytest.raises(LEDCalibrationError, match="LED 8.*NaN"):
        plate_samples(bad, None, cam, rig, plate, label="LED 8")
    with pytest.raises(LEDCalibrationError, match="LED 9.*saturated"):
        plate_samples(ok, np.ones((cam.height, cam.width), bool), cam, rig, plate, label="LED 9")
    with pytest.raises(LEDCalibrationError, match="no LED"):
        calibrate_leds(rig, {3: []}, 0.8)


def test_cli_writes_nothing_on_a_bad_setting(tmp_path, capsys):
    from hemicube.cli import main

    assert main(["calibrate", "leds", "--rig", "mini", "--led-step", "0", "-o", str(tmp_path / "cal")]) == 2
    assert "--led-step" in capsys.readouterr().err and not (tmp_path / "cal").exists()


def test_a_calibration_is_the_same_device():
    """Rig.layout_digest, which `hemicube capture --truth` checks: a rig whose LEDs (moved, tilted, re-profiled,
    re-weighted) or cameras (lens and pose) were calibrated is the same device; one with other LEDs, or a camera
    of another pixel grid, is not."""
    from dataclasses import replace

    from twin.rig.perturb import perturb_cameras

    nominal = twin.load_rig("paper")
    truth = perturb_leds(nominal, 3)
    assert truth.geometry_digest() != nominal.geometry_digest()
    assert truth.layout_digest() == nominal.layout_digest()
    assert perturb_cameras(nominal, 3).layout_digest() == nominal.layout_digest()
    assert twin.load_rig("mini").layout_digest() != nominal.layout_digest()
    binned = replace(nominal, cameras={n: c.resized(0.5) for n, c in nominal.cameras.items()})
    assert binned.layout_digest() != nominal.layout_digest()


# --- the bottom LEDs: through the empty holder's acrylic, one height ----------------------------------------
def test_bottom_perturbation_moves_only_the_bottom_leds_and_leaves_the_upper_draw():
    nominal = twin.load_rig("mini")
    a = perturb_leds(nominal, 3, bottom=True)
    moved = np.linalg.norm(a.leds.positions - nominal.leds.positions, axis=1)
    assert moved[~nominal.is_bottom].max() == 0 and 2 < np.median(moved[nominal.is_bottom]) < 8
    assert a.digest() == perturb_leds(nominal, 3, bottom=True).digest()
    both = perturb_leds(a, 3)  # the upper draw does not depend on the bottom one
    assert np.array_equal(both.leds.positions[~nominal.is_bottom], perturb_leds(nominal, 3).leds.positions[~nominal.is_bottom])


def test_acrylic_model_matches_the_forward_model():
    """The closed form with the plate's normal facing down and the acrylic's transmission as the albedo, against
    the twin's Warp forward model of a bottom LED's light through the empty holder: float32 level."""
    rig = perturb_leds(twin.load_rig("mini"), 5, bottom=True)
    acrylic = DiffusePlate(transparency=1.0)
    cam = rig.camera("secondary")
    uv = np.stack(np.meshgrid(np.arange(20, cam.width - 20, 7), np.arange(20, cam.height - 20, 7)), -1).reshape(-1, 2)
    X, on = acrylic.points(rig, cam, uv.astype(np.float64))
    X = X[on]
    bottom = np.flatnonzero(rig.is_bottom)[[27, 28, 35]]  # under the sample
    rad = acrylic.radiance(rig, "secondary", bottom)
    for j, led in enumerate(bottom):
        want = rad[j].reshape(-1, 3)[np.ravel_multi_index((uv[on, 1], uv[on, 0]), (cam.height, cam.width))]
        assert want.min() > 0, led
        g = np.exp(_log_geometry(rig.leds.positions[led], rig.leds.normals[led], rig.leds.profile[led, 0],
                                 X[:, None, :], np.array([0.0, 0.0, -1.0]), rig.bottom.acrylic_transmission))
        assert np.abs(g[:, None] * rig.leds.intensity[led] / want - 1).max() < 1e-5, led
    assert DiffusePlate().radiance(rig, "secondary", bottom).max() == 0  # a plate on the holder blocks them


def test_bottom_leds_from_one_height_noise_free():
    """Identifiability with one height: the acrylic cannot be lifted, yet noise-free photos give every bottom
    LED whose crest is seen back exactly (the glow's width and tail fix its distance)."""
    from twin.camera.sensor import apply_optics
    from calibration.leds import crest_seen

    nominal = twin.load_rig("mini")
    truth = perturb_leds(nominal, 7, bottom=True)
    acrylic = DiffusePlate(transparency=1.0)
    leds = np.flatnonzero(nominal.is_bottom)
    leds = leds[crest_seen(nominal, leds, acrylic.size_mm / 2)]
    assert 4 <= leds.size < nominal.is_bottom.sum()
    samples = {int(k): [] for k in leds}
    for name in truth.cameras:
        cam = truth.camera(name)
        for led, rad in zip(leds, acrylic.radiance(truth, name, leds)):
            samples[int(led)].append(plate_samples(apply_optics(rad, cam), None, cam, nominal, acrylic))
    fit = calibrate_leds(nominal, samples, nominal.bottom.acrylic_transmission, bottom=True)
    assert fit.index.tolist() == leds.tolist()
    assert np.abs(fit.positions - truth.leds.positions[fit.index]).max() < 0.01
    assert np.abs(fit.exponent - truth.leds.profile[fit.index, 0]).max() < 1e-3
    assert np.abs(fit.intensity / truth.leds.intensity[fit.index] - 1).max() < 1e-3


def test_calibrate_bottom_leds_cli(tmp_path):
    """`hemicube calibrate bottom`, perturbation seed 11 (held back): the goals, far better than nominal, the
    LEDs beyond the crest's reach listed and kept nominal, only bottom LEDs changed."""
    import json
    import subprocess
    import sys

    out = tmp_path / "cal"
    r = subprocess.run([sys.executable, "-m", "hemicube.cli", "calibrate", "bottom", "--rig", "mini", "--perturb", "11",
                        "-o", str(out), "--no-progress", "--validate"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads((out / "report.json").read_text())["cameras"]["bottom"]
    assert rep["passed"] and rep["calibrated"] >= 8
    assert rep["position_mm"]["median"] * 5 < rep["nominal_error"]["position_mm"]["median"]
    assert rep["emission_pct"]["median"] * 10 < rep["nominal_error"]["emission_pct"]["median"]
    nominal, cal = twin.load_rig("mini"), twin.load_rig(str(out / "rig"))
    changed = np.flatnonzero(np.linalg.norm(cal.leds.positions - nominal.leds.positions, axis=1) > 0)
    assert nominal.is_bottom[changed].all() and changed.size == rep["calibrated"]
    assert not set(changed) & set(rep["crest_not_seen"]) and len(rep["crest_not_seen"]) > 0


def test_calibrate_bottom_on_a_rig_without_bottom_leds_is_refused(tmp_path, capsys):
    from dataclasses import replace

    from hemicube.cli import main

    rig = twin.load_rig("mini")
    upper_only = replace(rig, name="mini-upper", leds=rig.leds.subset(np.flatnonzero(~rig.is_bottom)), bottom=None)
    twin.save_rig(upper_only, tmp_path / "rig")
    assert main(["calibrate", "bottom", "--rig", str(tmp_path / "rig"), "-o", str(tmp_path / "cal")]) == 2
    assert "has no bottom LEDs" in capsys.readouterr().err and not (tmp_path / "cal").exists()
