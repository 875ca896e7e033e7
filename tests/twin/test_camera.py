"""Camera geometry against OpenCV, and the OpenCV-YAML reader against the released calibration files."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.rig.camera import Camera, SensorParams
from twin.rig.opencv_yaml import OpenCVYamlError, read_opencv_yaml

CAMERAS = ["primary", "secondary"]


def _points_in_view(cam: Camera, rng, n: int = 500) -> np.ndarray:
    """Random world points in front of `cam` whose undistorted projection lies in (a margin around)
    its image: rays through random pixels, at random depths from 200 to 800 mm."""
    uv = rng.uniform([-0.1 * cam.width, -0.1 * cam.height], [1.1 * cam.width, 1.1 * cam.height], (n, 2))
    xy = (uv - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    depth = rng.uniform(200.0, 800.0, n)
    Xc = np.concatenate([xy * depth[:, None], depth[:, None]], axis=1)
    return (Xc - cam.t) @ cam.R  # R^T (Xc - t)


def _cv2_project(cam: Camera, X: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(cam.R)
    uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, cam.t.reshape(3, 1), cam.K, cam.dist)
    return uv.reshape(-1, 2)


# --- projection vs OpenCV ---------------------------------------------------------------------------
@pytest.mark.parametrize("name", CAMERAS)
def test_project_matches_cv2(paper, name):
    cam = paper.camera(name)
    X = _points_in_view(cam, np.random.default_rng(1 + CAMERAS.index(name)))
    uv, z = cam.project(X)
    assert uv.dtype == np.float64
    assert np.all(z > 0)
    np.testing.assert_allclose(z, (X @ cam.R.T + cam.t)[:, 2], rtol=1e-12)
    ref = _cv2_project(cam, X)
    err = np.abs(uv - ref).max()
    assert err <= 1e-6, f"{name}: max |project - cv2.projectPoints| = {err:.3g} px"
    # undistorted projection matches OpenCV without distortion coefficients
    uv0, _ = cam.project(X, distort=False)
    rvec, _ = cv2.Rodrigues(cam.R)
    ref0, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, cam.t.reshape(3, 1), cam.K, np.zeros(5))
    assert np.abs(uv0 - ref0.reshape(-1, 2)).max() <= 1e-6


@settings(max_examples=30, deadline=None)
@given(k=st.lists(st.floats(-0.5, 0.5), min_size=5, max_size=5),
       axis=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1),
       angle=st.one_of(st.just(0.0), st.floats(1e-3, 0.3)), seed=st.integers(0, 2**32 - 1))
def test_project_matches_cv2_for_random_distortion_and_pose(paper, k, axis, angle, seed):
    """The distortion polynomial, its tangential terms and the pose agree with OpenCV for any
    (k1, k2, p1, p2, k3) and a random exact rotation. (Rotations below 1e-5 rad are left out:
    cv2.Rodrigues(R) snaps them to rvec = 0, an OpenCV precision floor, not the twin's.)"""
    k = np.array(k) * [1.0, 1.0, 0.02, 0.02, 1.0]
    base = paper.primary
    R, _ = cv2.Rodrigues(angle * np.asarray(axis) / np.linalg.norm(axis))
    cam = Camera("c", base.width, base.height, base.K, k, R, base.t)
    X = _points_in_view(cam, np.random.default_rng(seed), n=50)
    assert np.abs(cam.project(X)[0] - _cv2_project(cam, X)).max() <= 1e-6


def _rotation_error(cam: Camera) -> float:
    return max(np.abs(cam.R @ cam.R.T - np.eye(3)).max(), abs(np.linalg.det(cam.R) - 1))


def test_camera_rotations_are_orthonormal(paper, mini):
    """project, centre (-R^T t), pixel_rays (R^T) and cv2.Rodrigues all assume R is a rotation: a
    rounded R (|R R^T - I| ~ 1e-6) moves the centre by ~1e-4 mm and reprojected rays by ~3e-3 px."""
    bad = {f"{r.name}/{n}": f"{_rotation_error(c):.2e}" for r in (paper, mini) for n, c in r.cameras.items()
           if _rotation_error(c) >= 1e-12}
    assert not bad, f"cameras whose R is not a rotation to 1e-12 (|R R^T - I|): {bad}"


def test_imported_camera_rotation_is_orthonormal(imported):
    """The released rmat is float32 (orthonormal to ~3e-8); the imported camera must still be an exact
    rotation in float64, or pixel_rays (which uses R^T as the inverse) disagrees with project."""
    err = _rotation_error(imported.primary)
    assert err < 1e-12, f"imported R: |R R^T - I| = {err:.2e}"


def test_camera_centre_and_axis(paper):
    for cam in paper.cameras.values():
        np.testing.assert_allclose(cam.world_to_camera(cam.centre), 0.0, atol=1e-9)
        # the optical axis is the direction in which depth grows one-for-one
        z0 = cam.world_to_camera(cam.centre + 100.0 * cam.optical_axis)
        np.testing.assert_allclose(z0, [0.0, 0.0, 100.0], atol=1e-9)
    primary = paper.primary
    # looking down -z, image columns along world +y (reference §1.5)
    assert primary.optical_axis[2] < -0.999
    assert primary.R[0] @ [0.0, 1.0, 0.0] > 0.999
    secondary = paper.camera("secondary")
    origin = np.asarray(paper.sample.origin)
    to_sample = origin - secondary.centre
    # the secondary camera views the sample centre at 45 deg from +x
    cos = secondary.optical_axis @ (to_sample / np.linalg.norm(to_sample))
    assert cos == pytest.approx(1.0, abs=1e-12)
    assert np.degrees(np.arccos(-secondary.optical_axis[2])) == pytest.approx(45.0, abs=1e-9)


# --- pixel rays invert projection -----------------------------------------------------------------
def _reprojection_error(cam: Camera) -> float:
    """Rays through pixels (random and the four image corners), pushed 150 and 450 mm out, projected back."""
    rng = np.random.default_rng(7)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (400, 2))
    uv = np.concatenate([uv, [[0, 0], [cam.width - 1, 0], [0, cam.height - 1], [cam.width - 1, cam.height - 1]]])
    d = cam.pixel_rays(uv)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.all(d @ cam.optical_axis > 0)  # rays go forward
    err = 0.0
    for s in (150.0, 450.0):
        back, z = cam.project(cam.centre + s * d)
        assert np.all(z > 0)
        err = max(err, np.abs(back - uv).max())
    # undistorted rays invert the undistorted projection
    back0, _ = cam.project(cam.centre + 300.0 * cam.pixel_rays(uv, distorted=False), distort=False)
    return max(err, np.abs(back0 - uv).max())


@pytest.mark.parametrize("name", CAMERAS)
def test_pixel_rays_invert_project(paper, mini, name):
    errors = {r.name: _reprojection_error(r.camera(name)) for r in (paper, mini)}
    bad = {k: f"{v:.3g} px" for k, v in errors.items() if v > 1e-6}
    assert not bad, f"{name}: pixel_rays -> project reprojection error above 1e-6 px: {bad}"


def test_imported_pixel_rays_invert_project(imported):
    err = _reprojection_error(imported.primary)
    assert err <= 1e-6, f"imported primary: pixel_rays -> project reprojection error {err:.3g} px"


def test_pixel_rays_agree_with_cv2_undistort(paper):
    cam = paper.primary
    uv = np.random.default_rng(3).uniform([0, 0], [cam.width - 1, cam.height - 1], (200, 2))
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)).reshape(-1, 2)
    d_ref = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ cam.R
    d_ref /= np.linalg.norm(d_ref, axis=1, keepdims=True)
    np.testing.assert_allclose(cam.pixel_rays(uv), d_ref, atol=1e-9)



def test_undistort_same_bits_as_every_point_through_every_iteration(paper, monkeypatch):
    """Camera.undistort lets a point leave the fixed-point iteration once it maps to itself exactly, block by block;
    the oracle iterates every point the full count: the same bits, at block edges, for NaNs and any shape."""
    import twin.rig.camera as camera_module

    cam = paper.primary
    every_iteration = cam.undistort_reference

    uv = np.random.default_rng(5).uniform([-50, -50], [cam.width + 50, cam.height + 50], (3001, 2))
    xy = (uv - cam.K[:2, 2]) @ np.linalg.inv(cam.K[:2, :2]).T
    xy[[0, 1000, 3000]] = np.nan
    monkeypatch.setattr(camera_module, "UNDISTORT_BLOCK", 1000)
    for arr in (xy, xy[:3000].reshape(3, 1000, 2), xy[7]):
        got = cam.undistort(arr)
        assert got.shape == arr.shape
        np.testing.assert_array_equal(got, every_iteration(arr))
    assert not np.array_equal(cam.undistort(xy, iterations=2), every_iteration(xy))  # it does iterate
    np.testing.assert_array_equal(cam.undistort(xy, iterations=2), every_iteration(xy, iterations=2))


# --- resizing ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("factor", [0.5, 2.0, 1 / 12])
def test_resized_maps_pixel_centres(paper, factor):
    cam = paper.primary
    small = cam.resized(factor)
    assert (small.width, small.height) == (round(cam.width * factor), round(cam.height * factor))
    X = _points_in_view(cam, np.random.default_rng(11), n=300)
    uv, _ = cam.project(X)
    uv_small, _ = small.project(X)
    np.testing.assert_allclose(uv_small, (uv + 0.5) * factor - 0.5, atol=1e-9)
    # same pose and distortion, different pixels
    assert np.array_equal(small.R, cam.R) and np.array_equal(small.t, cam.t)
    assert np.array_equal(small.dist, cam.dist)


def test_resized_half_pixel_centre_example():
    """Pixel (0, 0) at full size covers [-0.5, 0.5]; after 2x2 binning the centre of the new pixel 0 is
    the corner point between old pixels 0 and 1, i.e. old u = 0.5."""
    cam = Camera("c", 4, 2, [[10.0, 0, 1.5], [0, 10.0, 0.5], [0, 0, 1]], np.zeros(5), np.eye(3), [0, 0, 10.0])
    half = cam.resized(0.5)
    assert (half.width, half.height) == (2, 1)
    assert half.K[0, 2] == 0.5 and half.K[1, 2] == 0.0 and half.K[0, 0] == 5.0


def test_resized_rejects_fractional_pixels(paper):
    with pytest.raises(ValueError, match="whole pixels"):
        paper.primary.resized(0.3)


# --- the sample is visible -------------------------------------------------------------------------
@pytest.mark.parametrize("name", CAMERAS)
def test_sample_corners_inside_image(paper, name):
    cam = paper.camera(name)
    corners = paper.sample.corners(150.0)
    assert corners.shape == (4, 3)
    np.testing.assert_allclose(np.ptp(corners, axis=0), [150.0, 150.0, 0.0])
    uv, z = cam.project(corners)
    assert np.all(z > 0)
    assert np.all((uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1)), uv
    assert np.all((uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)), uv
    err = np.abs(uv - _cv2_project(cam, corners)).max()
    assert err <= 1e-6, f"{name}: sample corners differ from cv2.projectPoints by {err:.3g} px"


def test_primary_sample_footprint_matches_reference(paper):
    """Reference §1.5: the 150 mm sample projects to columns 430-2226 and rows 160-1959 (rounded, and
    computed there without stating the distortion handling: a few pixels of slack; a swapped axis or a
    wrong plane would be off by hundreds)."""
    uv, _ = paper.primary.project(paper.sample.corners(150.0))
    assert uv[:, 0].min() == pytest.approx(430, abs=6) and uv[:, 0].max() == pytest.approx(2226, abs=6)
    assert uv[:, 1].min() == pytest.approx(160, abs=6) and uv[:, 1].max() == pytest.approx(1959, abs=6)


def test_imported_camera_centre_is_cam_pos(imported, released_cam_pos):
    cam = imported.primary
    assert np.linalg.norm(cam.centre - released_cam_pos) <= 0.01
    np.testing.assert_allclose(cam.centre, -cam.R.T @ cam.t, atol=1e-12)


def test_look_at_builds_a_rotation():
    cam = Camera.look_at("c", [100.0, 0.0, 100.0], [0.0, 0.0, 0.0], (0.0, 1.0, 0.0),
                         [[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]], 101, 101)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(cam.R) == pytest.approx(1.0)
    np.testing.assert_allclose(cam.centre, [100.0, 0.0, 100.0], atol=1e-12)
    uv, z = cam.project([[0.0, 0.0, 0.0]])
    np.testing.assert_allclose(uv, [[50.0, 50.0]], atol=1e-12)  # the target is on the principal point
    assert z[0] == pytest.approx(np.sqrt(2) * 100)


def test_camera_arrays_are_immutable(paper):
    with pytest.raises(ValueError):
        paper.primary.K[0, 0] = 1.0


def test_sensor_params_validation():
    with pytest.raises(ValueError, match="bit_depth"):
        SensorParams(bit_depth=11)
    with pytest.raises(ValueError, match="bayer"):
        SensorParams(bayer="XX")
    with pytest.raises(ValueError, match="full_well_e"):
        SensorParams(full_well_e=float("nan"))


# --- OpenCV YAML ---------------------------------------------------------------------------------------
def test_read_intrinsic_yml(reference_dir):
    d = read_opencv_yaml(reference_dir / "intrinsic.yml")
    assert (d["image_width"], d["image_height"]) == (2664, 2304)
    assert d["nframes"] == 218 and (d["board_width"], d["board_height"]) == (21, 9)
    assert d["calibration_time"] == "Fri May 20 17:32:08 2022"
    K = d["camera_matrix"]
    assert K.shape == (3, 3) and K.dtype == np.float64
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[2, 2]) == (4923.0, 4923.43, 1322.3, 1120.98, 1.0)
    dist = d["distortion_coefficients"]
    assert dist.shape == (1, 5)
    np.testing.assert_allclose(dist.ravel(), [0.078406, -0.602699, 0.000278, -0.000606, -1.975753], atol=1e-6)
    err = d["per_view_reprojection_errors"]
    assert err.shape == (218, 1) and err.dtype == np.float32
    assert d["extrinsic_parameters"].shape == (218, 6)
    # the mean of the per-view errors is close to the stated average
    assert d["avg_reprojection_error"] == pytest.approx(0.2095, abs=1e-4)


@pytest.mark.parametrize("fname", ["intrinsic.yml", "extrinsic.yml"])
def test_yaml_reader_agrees_with_cv2_filestorage(reference_dir, fname):
    ours = read_opencv_yaml(reference_dir / fname)
    fs = cv2.FileStorage(str(reference_dir / fname), cv2.FILE_STORAGE_READ)
    try:
        for key, value in ours.items():
            node = fs.getNode(key)
            assert not node.empty(), key
            if isinstance(value, np.ndarray):
                ref = node.mat()
                assert ref.shape == value.shape, key
                assert ref.dtype == value.dtype, key
                assert np.array_equal(ref, value), key
            elif isinstance(value, str):
                assert node.string() == value, key
            else:
                assert node.real() == value, key
    finally:
        fs.release()


def test_read_extrinsic_yml(reference_dir):
    d = read_opencv_yaml(reference_dir / "extrinsic.yml")
    R, t = d["rmat"], d["tvec"]
    assert R.shape == (3, 3) and R.dtype == np.float32
    assert t.shape == (3, 1)
    np.testing.assert_allclose(R.astype(float) @ R.T.astype(float), np.eye(3), atol=1e-5)
    np.testing.assert_allclose(t.ravel(), [-1.0900, -4.7868, 289.0184], atol=1e-4)


def test_yaml_without_header_is_refused(reference_dir, tmp_path):
    text = (reference_dir / "intrinsic.yml").read_text()
    p = tmp_path / "no_header.yml"
    p.write_text(text.split("\n", 1)[1])  # drop "%YAML:1.0"
    with pytest.raises(OpenCVYamlError, match=r"no %YAML header"):
        read_opencv_yaml(p)


def test_yaml_matrix_with_wrong_count_is_refused(reference_dir, tmp_path):
    text = (reference_dir / "extrinsic.yml").read_text()
    p = tmp_path / "short.yml"
    p.write_text(text.replace("-0.99991702 ]", "]"))  # rmat loses its last value
    with pytest.raises(OpenCVYamlError, match=r"short.yml: not a valid OpenCV YAML file \(.*Parsing error"):
        read_opencv_yaml(p)


def test_yaml_other_errors(tmp_path):
    p = tmp_path / "a.yml"
    p.write_text("%YAML:1.0\n---\nm: !!opencv-matrix\n   rows: 1\n   cols: 2\n   dt: d\n   data: [ 1., x ]\n")
    with pytest.raises(OpenCVYamlError, match="not a valid OpenCV YAML file .*plain sequences of numbers"):
        read_opencv_yaml(p)
    p.write_text("%YAML:1.0\n---\nm: !!opencv-matrix\n   rows: 1\n   cols: 2\n   data: [ 1., 2. ]\n")
    with pytest.raises(OpenCVYamlError, match=r"not a valid OpenCV YAML file .*dt"):
        read_opencv_yaml(p)
    with pytest.raises(OpenCVYamlError, match="cannot read"):
        read_opencv_yaml(tmp_path / "missing.yml")
    p.write_text("%YAML:1.0\n---\nm: !!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: f\n"
                 "   data: [ 1., 2.,\n       3., 4. ]\nn: 3\ns: \"hi\"\n")
    d = read_opencv_yaml(p)
    assert np.array_equal(d["m"], np.array([[1, 2], [3, 4]], np.float32)) and d["m"].dtype == np.float32
    assert d["n"] == 3 and d["s"] == "hi"


def test_plane_points_invert_the_projection(mini):
    """Closed form: the rays through the projections of points on a plane meet the plane at those points."""
    cam = mini.camera("secondary")
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-60, 60, (50, 2)), np.full(50, -122.0)]
    uv, _ = cam.project(X)
    np.testing.assert_allclose(cam.plane_points(uv, (0, 0, -122.0), (0, 0, 1.0)), X, atol=1e-6)
