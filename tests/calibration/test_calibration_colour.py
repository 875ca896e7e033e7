"""Colour calibration: the spectral model against colour-science's own integrations, the chart's
layout and its agreement with the twin's RGB renders, the procedure on noise-free photos, a whole calibration
of a perturbed mini rig (a seed held back from the one documented) and its bad-input errors."""
import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

import colour  # noqa: E402

import twin  # noqa: E402
from calibration.colour import ColourCalibrationError, chart_patches, crosstalk_from_photos, delta_e2000  # noqa: E402
from twin.camera.spectral import chart_radiance, device_spectra, with_crosstalk  # noqa: E402
from twin.optics.spectra import WAVELENGTHS, spectral_shape  # noqa: E402
from twin.targets.colorchecker import FRAME, OFF, ColorChecker  # noqa: E402
from twin.targets.diffuse import DiffusePlate  # noqa: E402


@pytest.fixture(scope="module")
def rig():
    return twin.load_rig("mini")


def _sd(values, name="sd"):
    return colour.SpectralDistribution(dict(zip(WAVELENGTHS, values)), name=name)


def test_xyz_is_colour_sciences_integration():
    """spectra.xyz against colour.sd_to_XYZ (integration method, the LEDs' white as the illuminant): 1e-9."""
    sp = device_spectra(["primary"], 5)
    _, rho = ColorChecker().names_and_spectra()
    w = np.array([0.9, 1.0, 0.7])
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(spectral_shape())
    ill = _sd(sp.white(w), "LED white")
    ref = np.stack([colour.sd_to_XYZ(_sd(r), cmfs, ill, method="Integration") for r in rho]) / 100
    np.testing.assert_allclose(sp.xyz(rho, w), ref, rtol=1e-9)


def test_transfer_is_colour_sciences_camera_rgb():
    """T[k, c] against colour.characterisation.training_data_sds_to_RGB (the chart under LED channel c alone,
    the camera's sensitivities), each column over the white's: 1e-9. And T(1) is the crosstalk, diagonal 1."""
    from colour.characterisation import RGB_CameraSensitivities, training_data_sds_to_RGB

    sp = device_spectra(["primary"], 5)
    _, rho = ColorChecker().names_and_spectra()
    sens = RGB_CameraSensitivities(dict(zip(WAVELENGTHS, sp.sensitivity("primary"))), labels=("R", "G", "B"))
    data = colour.MultiSpectralDistributions(dict(zip(WAVELENGTHS, np.vstack([rho, np.ones(len(WAVELENGTHS))]).T)))
    T = sp.transfer("primary", rho)
    for c in range(3):
        rgb, rgb_w = training_data_sds_to_RGB(data, sens, _sd(sp.emission()[:, c]))
        raw = rgb / rgb_w
        np.testing.assert_allclose(T[:, :, c], raw[:-1] / raw[-1, c], rtol=1e-9)
    M = sp.crosstalk("primary")
    np.testing.assert_allclose(np.diag(M), 1.0, rtol=1e-12)
    assert 0.02 < M[1, 2] < 0.8 and np.linalg.cond(M) < 10  # a real Bayer filter's overlap, well conditioned


def test_device_spectra_are_seeded():
    a, b = device_spectra(["p", "s"], 7), device_spectra(["p", "s"], 7)
    assert a == b and a != device_spectra(["p", "s"], 8) and device_spectra(["p"]).leds[0] == (630.0, 20.0)


def test_chart_layout(rig):
    """Each patch's centre projects onto its own label; 24 patches of equal area; the surround and beyond."""
    chart, cam = ColorChecker(), rig.camera("primary")
    idx = chart.patch_map(rig, cam)
    uv, _ = cam.project(chart.patch_centres(rig))
    assert [idx[int(round(v)), int(round(u))] for u, v in uv] == list(range(24))
    counts = np.bincount(idx[idx >= 0], minlength=24)
    assert counts.min() >= 0.85 * counts.max() and (idx == FRAME).any() and (idx == OFF).any()
    assert chart.size_mm == pytest.approx((82.5, 55.5))


def test_a_grey_chart_is_the_rgb_render(rig):
    """A chart whose patches are all a flat grey is what the twin's RGB render gives (crosstalk @ albedo x
    light): the spectral path and the capture's agree where they must. 1e-12."""
    class Grey(ColorChecker):
        def names_and_spectra(self):
            names, rho = super().names_and_spectra()
            return names, np.full_like(rho, 0.4)

    sp = device_spectra(rig.cameras, 2)
    chart, upper = Grey(frame_reflectance=0.4), np.flatnonzero(~rig.is_bottom)[::20]
    white = DiffusePlate(albedo=1.0).lit_radiance(rig, "secondary", upper)
    got = chart_radiance(chart, rig, sp, "secondary", white)
    on = chart.patch_map(rig, rig.camera("secondary")) != OFF
    np.testing.assert_allclose(got[on], 0.4 * white[on] @ sp.crosstalk("secondary").T, rtol=1e-12, atol=1e-15)
    assert got.max() > 0 and not got[~on].any()


def test_crosstalk_from_noise_free_photos(rig):
    """Three noise-free photos of the plate, one LED channel each, give the crosstalk back to 1e-12."""
    plate, cam = DiffusePlate(), rig.camera("primary")
    M = device_spectra(rig.cameras, 4).crosstalk("primary")
    light = plate.radiance(rig, "primary", np.flatnonzero(~rig.is_bottom)[::10]).sum(axis=0)
    photos = [(light * np.eye(3)[c]) @ M.T for c in range(3)]
    np.testing.assert_allclose(crosstalk_from_photos(photos, None, cam, rig, plate), M, rtol=1e-12)


def test_delta_e2000_is_zero_for_equal_and_grows(rig):
    xyz = np.array([[0.2, 0.3, 0.25], [0.5, 0.5, 0.4]])
    white = np.array([0.95, 1.0, 1.05])
    assert np.allclose(delta_e2000(xyz, xyz, white), 0)
    assert (delta_e2000(xyz * [1.05, 1, 1], xyz, white) > 1).all()


def test_bad_chart_photos_are_named(rig):
    cam = rig.camera("primary")
    photo = np.full((cam.height, cam.width, 3), 0.5)
    with pytest.raises(ColourCalibrationError, match=r"^chart A: patch 0 \('dark skin'\) has 0 pixels .* outside the frame"):
        chart_patches(photo, None, cam, rig, ColorChecker(offset_mm=(400.0, 0.0)), label="chart A")
    sat = np.zeros(photo.shape[:2], bool)
    sat[ColorChecker().patch_map(rig, cam) == 5] = True
    with pytest.raises(ColourCalibrationError, match=r"^chart B: patch 5 \('bluish green'\) is saturated"):
        chart_patches(photo, sat, cam, rig, ColorChecker(), label="chart B")
    photo[3, 4, 1] = np.nan
    with pytest.raises(ColourCalibrationError, match="^chart C: photo contains NaN or Inf$"):
        chart_patches(photo, None, cam, rig, ColorChecker(), label="chart C")
    with pytest.raises(ColourCalibrationError, match="^plate: need one photo per LED channel"):
        crosstalk_from_photos([photo], None, cam, rig, DiffusePlate())


def test_calibrate_colour_on_a_perturbed_mini_rig(tmp_path, rig):
    """`hemicube calibrate colour`, perturbation seed 11 (held back: docs/calibration.md shows seed 3): every
    camera meets the goals (ΔE2000 median <= 1 on the ColorChecker under the LEDs' white; the crosstalk left
    after correction <= 0.5%), far better than the nominal rig's identity, and the calibrated rig folder loads
    with the calibrated crosstalks and nothing else changed."""
    out = tmp_path / "cal"
    r = subprocess.run([sys.executable, "-m", "hemicube.cli", "calibrate", "colour", "--rig", "mini", "--perturb",
                        "11", "--frames", "8", "-o", str(out), "--no-progress", "--validate"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["spectra"] == device_spectra(rig.cameras, 11).to_dict()
    cal, truth = twin.load_rig(str(out / "rig")), twin.load_rig(str(out / "truth"))
    for name, c in rep["cameras"].items():
        assert c["passed"] and c["delta_e2000"]["median"] <= 1.0 and c["crosstalk_residual_max"] <= 0.005
        assert c["nominal_error"]["crosstalk_residual_max"] > 20 * c["crosstalk_residual_max"]
        np.testing.assert_allclose(cal.camera(name).sensor.crosstalk, c["crosstalk"], rtol=1e-6)
        np.testing.assert_allclose(truth.camera(name).sensor.crosstalk,
                                   device_spectra(rig.cameras, 11).crosstalk(name), rtol=1e-6)
        assert replace(cal.camera(name).sensor, crosstalk=rig.camera(name).sensor.crosstalk) == rig.camera(name).sensor
        # a perfect white's white-balanced camera RGB is (1, 1, 1): the matrix takes it to the LEDs' white, Y = 1
        # (to the fit's accuracy: it is one of 24 equally weighted patches, not a constraint)
        white = device_spectra(rig.cameras, 11).xyz(np.ones(len(WAVELENGTHS)), c["white_led_rgb"])
        np.testing.assert_allclose(np.asarray(c["to_xyz_from_camera_rgb"]) @ np.ones(3), white, rtol=0.02)
    assert cal.geometry_digest() == rig.geometry_digest()  # the same device: only how it records light changed


def test_with_crosstalk_changes_only_the_crosstalk(rig):
    t = with_crosstalk(rig, device_spectra(rig.cameras, 1))
    for n in rig.cameras:
        assert replace(t.camera(n).sensor, crosstalk=rig.camera(n).sensor.crosstalk) == rig.camera(n).sensor


def test_calibrate_several_procedures_in_a_labs_order(tmp_path, rig):
    """`hemicube calibrate leds colour vignetting`: run in the lab's order (vignetting, colour, LEDs) against ONE
    true device with all three perturbations (seed 12, held back), each on the rig the ones before calibrated.
    Every stage meets its goals, and the written rig carries all three results. (`all` adds the cameras, which
    the mini rig calibrates at --board-scale 12, and the bottom LEDs: minutes, in docs/calibration.md.)"""
    from twin.rig.perturb import perturb_leds, perturb_vignetting

    out = tmp_path / "cal"
    r = subprocess.run([sys.executable, "-m", "hemicube.cli", "calibrate", "leds", "colour", "vignetting", "--rig",
                        "mini", "--perturb", "12", "--led-step", "36", "-o", str(out),
                        "--no-progress", "--validate"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads((out / "report.json").read_text())
    assert list(rep["stages"]) == ["vignetting", "colour", "leds"]
    assert all(c["passed"] for st in rep["stages"].values() for c in st["cameras"].values())
    lines = r.stdout.splitlines()
    assert [ln.split()[0] for ln in lines[:-1]] == ["vignetting"] * 2 + ["colour"] * 2 + ["leds"]
    truth = perturb_leds(with_crosstalk(perturb_vignetting(rig, 12), device_spectra(rig.cameras, 12)), 12)
    assert twin.load_rig(str(out / "truth")).digest() == truth.digest()
    cal = twin.load_rig(str(out / "rig"))
    for name, c in rep["stages"]["colour"]["cameras"].items():
        assert cal.camera(name).sensor.crosstalk == tuple(map(tuple, c["crosstalk"]))
        assert cal.camera(name).sensor.vignetting == tuple(rep["stages"]["vignetting"]["cameras"][name]["radial"])
    assert not np.array_equal(cal.led_positions, rig.led_positions)
    bad = subprocess.run([sys.executable, "-m", "hemicube.cli", "calibrate", "all", "leds", "-o", str(tmp_path / "x")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "name each procedure once, or 'all' alone" in bad.stderr
    assert not (tmp_path / "x").exists()


def test_validate_makes_a_missed_goal_the_exit_status(tmp_path, monkeypatch, capsys):
    """A calibration that misses a goal (here: a goal no calibration meets) writes its rig and report and exits
    0; with --validate it exits 1. Both print FAIL."""
    import calibration.colour
    from hemicube.cli import main

    monkeypatch.setitem(calibration.colour.COLOUR_GOALS, "delta_e2000_median", 1e-6)
    args = ["calibrate", "colour", "--rig", "mini", "--frames", "2", "--led-step", "12", "--no-progress"]
    assert main([*args, "-o", str(tmp_path / "a")]) == 0
    assert main([*args, "--validate", "-o", str(tmp_path / "b")]) == 1
    assert capsys.readouterr().out.count("FAIL") == 4
    assert (tmp_path / "a" / "rig").is_dir() and (tmp_path / "b" / "report.json").is_file()
