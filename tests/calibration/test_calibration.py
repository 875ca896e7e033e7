"""Camera calibration against the twin's truth: ChArUco photos of a perturbed paper rig (2664 x 2304 px
cameras, the paper's device: the mini rig's 222 x 192 px are too small for corner detection) are rendered
through each true camera's full model, and calibration.cameras recovers each camera from them alone. Goals
(calibration.cameras.CAMERA_GOALS): reprojection RMS <= 0.3 px, focal length within 0.1%; and what matters
downstream, where the sample's points land, within 0.1 px where the nominal rig is off by tens of pixels."""
from __future__ import annotations

import numpy as np
import pytest

import twin
from calibration.cameras import CAMERA_GOALS, CalibrationError, calibrate_cameras, detect
from twin.rig.perturb import perturb_cameras
from twin.targets.charuco import CharucoTarget


@pytest.fixture(scope="module")
def calibrated():
    nominal = twin.load_rig("paper")
    truth = perturb_cameras(nominal, 11)  # held back: docs/calibration.md's figures are for perturbation seed 3
    rig, report = calibrate_cameras(nominal, truth, views=4, seed=1, supersample=1, progress=False)
    return nominal, truth, rig, report


def test_perturbation_is_seeded_and_real():
    nominal = twin.load_rig("paper")
    a, b = perturb_cameras(nominal, 3), perturb_cameras(nominal, 3)
    assert a.digest() == b.digest() != nominal.digest() != perturb_cameras(nominal, 4).digest()
    for name, c in a.cameras.items():
        assert 0 < abs(c.K[0, 0] / nominal.cameras[name].K[0, 0] - 1) <= 0.01
        assert np.allclose(c.R @ c.R.T, np.eye(3), atol=1e-12)


def test_each_camera_meets_the_goals(calibrated):
    _, _, _, report = calibrated
    for name, r in report.items():
        assert r["rms_px"] <= CAMERA_GOALS["rms_px"] and r["focal_pct"] <= CAMERA_GOALS["focal_pct"], (name, r)
        assert r["sample_px_median"] <= 0.1 and r["sample_px_max"] <= 0.5, (name, r)
        assert r["nominal_error"]["sample_px_median"] > 10 * max(r["sample_px_median"], 0.1), (name, r)
        assert r["centre_mm"] <= 1.0 and r["rotation_deg"] <= 0.1 and r["passed"], (name, r)


def test_calibrated_rig_round_trips_as_a_folder(calibrated, tmp_path):
    from twin.rig.format import save_rig

    nominal, _, rig, _ = calibrated
    back = twin.load_rig(save_rig(rig, tmp_path / "rig"))
    assert back.digest() == rig.digest() != nominal.digest()
    assert np.array_equal(back.led_positions, nominal.led_positions)  # only the cameras were calibrated
    for name in nominal.cameras:
        assert np.array_equal(back.cameras[name].K, rig.cameras[name].K)


def test_board_photo_matches_the_forward_projection():
    """Oracle for the render: it traces pixel -> world (undistortion by fixed-point iteration, plane
    intersection); the corners OpenCV detects in its photo must sit where the camera's forward model (world ->
    pixel, closed-form distortion) projects the board's corners. On a tilted view of the 45-degree camera, 3 x 3
    rays per pixel, no noise. Tolerances: no bias (mean offset <= 0.02 px: a half-pixel convention slip would
    show as 0.5), scatter <= 0.1 px median and 0.2 px worst, the detector's sub-pixel accuracy on the box-filtered
    edges (measured 0.06 / 0.12; one ray per pixel aliases the edges to 0.25 / 0.39, which is why the
    tolerance names the supersampling)."""
    from twin.targets.charuco import calibration_poses

    rig = twin.load_rig("paper")
    cam, target = rig.camera("secondary"), CharucoTarget()  # the 45-degree view: strong perspective
    R, t = calibration_poses(cam, target, rig.sample, 3, seed=5)[2]
    det = detect(target.photo(cam, R, t, np.random.default_rng(2), noise=0.0, supersample=3), target, "oracle")
    d = det.corners - cam.project(target.corners_mm()[det.ids] @ R.T + t)[0]
    err = np.linalg.norm(d, axis=1)
    assert len(err) >= 50 and np.abs(d.mean(0)).max() <= 0.02, d.mean(0)
    assert np.median(err) <= 0.1 and err.max() <= 0.2, (np.median(err), err.max())


def test_bad_photos_are_named():
    target = CharucoTarget()
    with pytest.raises(CalibrationError, match="blank: the board was not found"):
        detect(np.full((400, 500), 40, np.uint8), target, "blank")
    with pytest.raises(CalibrationError, match="hot: 100.0% of the pixels are saturated"):
        detect(np.full((400, 500), 255, np.uint8), target, "hot")
    with pytest.raises(CalibrationError, match="8-bit grey"):
        detect(np.zeros((40, 50, 3), np.float32), target, "rgb")


def test_an_out_of_focus_board_is_named():
    """A board photo blurred by a Gaussian of 3 px (OpenCV still finds its corners) is refused, naming the photo;
    the same photo in focus passes."""
    import cv2

    from twin.targets.charuco import calibration_poses

    rig = twin.load_rig("paper")
    cam, target = rig.camera("primary"), CharucoTarget()
    R, t = next(iter(calibration_poses(cam, target, rig.sample, 4, 0)))
    img = target.photo(cam, R, t, np.random.default_rng(0), supersample=1)
    assert len(detect(img, target, "sharp").ids) > 20
    with pytest.raises(CalibrationError, match=r"^soft: the board is out of focus \(edge sharpness 0\.1"):
        detect(cv2.GaussianBlur(img, (0, 0), 3), target, "soft")


def test_cli_refuses_too_few_views(tmp_path, capsys):
    from hemicube.cli import main

    assert main(["calibrate", "cameras", "--views", "2", "-o", str(tmp_path / "out")]) == 2
    assert "need >= 4 views" in capsys.readouterr().err and not (tmp_path / "out").exists()
