"""Vignetting / flat-field calibration against the twin's truth: a mini-rig camera whose true falloff
is richer than the rig's radial model (lens falloff, an off-centre hood cutting the corners, dust shadows:
twin.rig.perturb.perturb_vignetting) photographs a flat-field source with a 1% gradient at 0 and 180 degrees
through its full sensor model (shot and read noise, PRNU); calibration.vignetting recovers the falloff from
those photos alone. Goal (calibration.vignetting.FLAT_FIELD_GOAL_PCT): the flat field within 0.5%, read as 95% of
the pixels (up to one factor).
The perturbation seed here (13) is held back: the procedure was written against seeds 3, 5 and 7."""
from __future__ import annotations

import json

import numpy as np
import pytest

import twin
from calibration.vignetting import FLAT_FIELD_GOAL_PCT, FlatFieldError, calibrate_flat_field, calibrate_vignetting
from twin.camera.hdr import still_photo
from twin.camera.sensor import apply_optics
from twin.rig.perturb import perturb_vignetting
from twin.targets.flatfield import FlatFieldSource


@pytest.fixture(scope="module")
def calibrated():
    nominal = twin.load_rig("mini")
    truth = perturb_vignetting(nominal, 13)
    return (nominal, truth) + calibrate_vignetting(nominal, truth, frames=32, seed=2, progress=False)


def test_perturbation_is_seeded_and_richer_than_the_radial_model():
    nominal = twin.load_rig("mini")
    a, b = perturb_vignetting(nominal, 3), perturb_vignetting(nominal, 3)
    assert a.digest() == b.digest() != nominal.digest() != perturb_vignetting(nominal, 4).digest()
    for name, cam in a.cameras.items():
        m = a.flat_fields[name]
        assert m.shape == (cam.height, cam.width) and np.array_equal(m, b.flat_fields[name])
        assert 0.5 <= m.min() < 0.97 and m.max() <= 1.0  # the hood's corners and the dust


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
    cam = perturb_vignetting(twin.load_rig("mini"), 5).camera("primary")
    L = FlatFieldSource(gradient=0.0).radiance(cam)
    img, sat = still_photo(L, cam, seed=0, frames=64, camera_key="primary")
    ratio = img.mean(axis=2) / apply_optics(L, cam).mean(axis=2)
    assert not sat.any()
    assert abs(np.median(ratio) - 1) < 1e-3 and np.percentile(np.abs(ratio - 1), 99) < 0.025


def test_calibrated_rig_is_written_and_reads_back(tmp_path, capsys, calibrated):
    from hemicube.cli import main

    assert main(["calibrate", "vignetting", "--rig", "mini", "--perturb", "13", "--frames", "8",
                 "--no-progress", "--validate", "-o", str(tmp_path / "out")]) == 0
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    rig = twin.load_rig(str(tmp_path / "out" / "rig"))
    truth = twin.load_rig(str(tmp_path / "out" / "truth"))
    assert truth.digest() == calibrated[1].digest()  # the truth's per-pixel maps round-trip bit-exactly
    for name, cam in rig.cameras.items():
        assert np.allclose(cam.sensor.vignetting, rep["cameras"][name]["radial"])
        m = rig.flat_fields[name]
        assert m.shape == (cam.height, cam.width) and 0.5 < m.min() < m.max() < 1.1
    assert "pass" in capsys.readouterr().out


def test_the_calibrated_rig_corrects_a_capture_made_with_the_true_falloff(calibrated):
    """Closing the loop for the flat field: the twin renders a uniformly lit flat white sample through the TRUE
    cameras (radial falloff, hood and dust: Rig.flat_fields), and the pipeline's correction
    (twin.camera.correction.flat_field) with the CALIBRATED rig must make it flat again: every pixel within the
    goal of the image's median, 95% of them, and 99% within twice the goal. With the nominal rig (no
    falloff) the corners stay ~30% dark, and with the calibrated radial coefficients alone the hood's corners
    stay more than 5% off."""
    from twin.camera.correction import flat_field
    from twin.camera.imaging import optics_gain

    nominal, truth, rig, _ = calibrated
    for name, cam in truth.cameras.items():
        seen = optics_gain(cam, truth.flat_fields[name])  # the render's factor for a uniform radiance
        errs = {}
        for label, r, m in (("calibrated", rig, rig.flat_fields[name]), ("radial only", rig, None),
                            ("nominal", nominal, None)):
            flat = seen * flat_field(r.cameras[name], m)
            e = 100 * np.abs(flat / np.median(flat) - 1)
            errs[label] = (np.percentile(e, 95), np.percentile(e, 99), e.max())
        assert errs["calibrated"][0] <= FLAT_FIELD_GOAL_PCT and errs["calibrated"][1] <= 2 * FLAT_FIELD_GOAL_PCT, errs
        assert errs["radial only"][2] > 5 and errs["nominal"][0] > 5, (name, errs)  # the hood's corners; the falloff


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


def test_a_vignetting_calibration_keeps_the_network_and_patterns(calibrated):
    """The shipped network and the default patterns depend on the rig's geometry, not on how its cameras record
    light (Rig.geometry_digest): a flat-field calibration keeps them; moving a camera does not."""
    from reconstruction.pipeline import load_network
    from twin.capture.plan import default_learned
    from twin.rig.builtin import serves_for
    from twin.rig.perturb import perturb_cameras

    nominal, truth, rig, _ = calibrated
    assert rig.digest() != nominal.digest() and rig.geometry_digest() == nominal.geometry_digest()
    assert serves_for(rig, nominal.digest()) and serves_for(truth, nominal.digest())
    assert default_learned(rig) is not None and load_network("pretrained", rig) is not None
    moved = perturb_cameras(nominal, 1)
    assert not serves_for(moved, nominal.digest()) and default_learned(moved) is None


@pytest.mark.slow
def test_capture_renders_the_truth_and_records_the_calibration(calibrated, tmp_path):
    """`hemicube capture --truth`: the simulator renders with the true device while the folder records the
    calibrated rig, as a real device's capture records its calibration. The photos are those of the truth
    (same bytes as a capture recording the truth itself), and another device as the truth is refused."""
    from twin.capture.plan import build_patterns, paper_plan
    from twin.capture.runner import CaptureError, capture, open_backends, photos
    from twin.materials.samples import load_sample

    _, truth, rig, _ = calibrated
    maps = load_sample("ramps", resolution=32)
    patterns = build_patterns(rig)
    todo = [p for p in paper_plan(rig, patterns) if p.pattern == "uniform"]
    raws = []
    for recorded, physics in ((rig, truth), (truth, None)):
        with open_backends(recorded, maps, "sim", 1, "cpu", truth=physics) as sims:
            raws.append([r.numpy().copy() for _, r, _, _ in photos(recorded, sims, patterns, todo, "cpu")])
    assert all(np.array_equal(a, b) for a, b in zip(*raws))
    with pytest.raises(CaptureError, match="is not a calibration of it"):
        capture(rig, "ramps", tmp_path / "cap", truth=twin.load_rig("paper"), resolution=32, progress=False)
    assert not (tmp_path / "cap").exists()
