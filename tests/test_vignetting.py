"""Vignetting / flat-field calibration (issue #16) against the twin's truth: a mini-rig camera whose true falloff
is richer than the rig's radial model (lens falloff, an off-centre hood cutting the corners, dust shadows:
twin.rig.perturb.perturb_vignetting) photographs a flat-field source with a 1% gradient at 0 and 180 degrees
through its full sensor model (shot and read noise, PRNU); calibration.vignetting recovers the falloff from
those photos alone. Goal (issue #16): the flat field within 0.5%, read as 95% of the pixels (up to one factor).
The perturbation seed here (13) is held back: the procedure was written against seeds 3, 5 and 7."""
from __future__ import annotations

import json

import numpy as np
import pytest

import twin
from calibration.cli import FLAT_FIELD_GOAL_PCT, calibrate_vignetting
from calibration.vignetting import FlatFieldError, calibrate_flat_field
from twin.camera.hdr import still_photo
from twin.camera.sensor import apply_optics
from twin.rig.perturb import perturb_vignetting
from twin.targets.flatfield import FlatFieldSource


@pytest.fixture(scope="module")
def calibrated():
    nominal = twin.load_rig("mini")
    truth, extra = perturb_vignetting(nominal, 13)
    return (nominal, truth, extra) + calibrate_vignetting(nominal, truth, extra, frames=32, seed=2, progress=False)


def test_perturbation_is_seeded_and_richer_than_the_radial_model():
    nominal = twin.load_rig("mini")
    (a, ea), (b, eb) = perturb_vignetting(nominal, 3), perturb_vignetting(nominal, 3)
    assert a.digest() == b.digest() != nominal.digest() != perturb_vignetting(nominal, 4)[0].digest()
    for name in a.cameras:
        assert np.array_equal(ea[name], eb[name])
        assert ea[name].shape == (a.cameras[name].height, a.cameras[name].width)
        assert 0.5 <= ea[name].min() < 0.97 and ea[name].max() <= 1.0  # the hood's corners and the dust


def test_each_camera_meets_the_goal_where_the_radial_model_cannot(calibrated):
    *_, report = calibrated
    for name, r in report.items():
        assert r["passed"] and r["flat_field_pct"]["p95"] <= FLAT_FIELD_GOAL_PCT, (name, r)
        assert r["flat_field_pct"]["median"] <= FLAT_FIELD_GOAL_PCT / 2, (name, r)
        # the truth holds what a radial model cannot fit (the hood's corners, the dust): the per-pixel map matters
        assert r["radial_model_pct"]["max"] > 4 * r["flat_field_pct"]["max"], (name, r)


def test_still_photo_is_the_optics_radiance_on_average():
    """Oracle for the photos themselves: a source without gradient through the camera's radial falloff only,
    64 frames averaged, against apply_optics' noise-free radiance. Shot noise at 60% of the 9,800 e- full well
    is 1.3% a frame (0.16% over 64 frames) and PRNU 0.5%: the median ratio must be 1 within 0.1%, and 99% of
    the pixels within 2.5% (5 sigma of their combined spread after demosaicing)."""
    truth, _ = perturb_vignetting(twin.load_rig("mini"), 5)
    cam = truth.camera("primary")
    L = FlatFieldSource(gradient=0.0).radiance(cam)
    img, sat = still_photo(L, cam, seed=0, frames=64, camera_key="primary")
    ratio = img.mean(axis=2) / apply_optics(L, cam).mean(axis=2)
    assert not sat.any()
    assert abs(np.median(ratio) - 1) < 1e-3 and np.percentile(np.abs(ratio - 1), 99) < 0.025


def test_calibrated_rig_and_flat_fields_are_written(tmp_path, capsys):
    from hemicube.cli import main
    from twin.materials.exr import read_exr

    assert main(["calibrate", "vignetting", "--rig", "mini", "--perturb", "13", "--frames", "8",
                 "--no-progress", "-o", str(tmp_path / "out")]) == 0
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    rig = twin.load_rig(str(tmp_path / "out" / "rig"))
    for name, cam in rig.cameras.items():
        assert np.allclose(cam.sensor.vignetting, rep["cameras"][name]["radial"])
        gain = read_exr(tmp_path / "out" / "flat_field" / f"{name}.exr")["Y"]
        assert gain.shape == (cam.height, cam.width) and 0.5 < gain.min() < gain.max() < 1.1
    assert "pass" in capsys.readouterr().out


def test_bad_flat_field_photos_are_named():
    cam = twin.load_rig("mini").camera("primary")
    good = np.ones((cam.height, cam.width, 3))
    with pytest.raises(FlatFieldError, match=r"flat-field photo 1: shape \(10, 10, 3\)"):
        calibrate_flat_field([good, np.ones((10, 10, 3))], cam)
    bad = good.copy()
    bad[3, 4, 0] = np.nan
    with pytest.raises(FlatFieldError, match="flat-field photo 0: 1 values are NaN or Inf"):
        calibrate_flat_field([bad], cam)
    sat = np.zeros((cam.height, cam.width), bool)
    sat[5, 5] = True
    with pytest.raises(FlatFieldError, match="flat-field photo 1: 1 pixels are saturated; shorten the exposure"):
        calibrate_flat_field([good, good], cam, saturated=[np.zeros_like(sat), sat])
    with pytest.raises(FlatFieldError, match="flat-field photo 0: dark"):
        calibrate_flat_field([np.zeros_like(good)], cam)
