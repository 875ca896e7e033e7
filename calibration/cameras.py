"""Camera calibration from photographs of a ChArUco board: intrinsics and the five OpenCV
distortion coefficients from views of the board at several poses (Zhang's method, cv2.calibrateCamera), then
the camera's pose in the rig's world frame from one view of the board lying at a known place on the sample
plane (cv2.solvePnP).

    views = [detect(img, target, "pose 3") for img in photos]          # corners and their ids per photo
    intr = calibrate_intrinsics(views, target, (W, H))                 # K, dist, RMS reprojection error
    R, t = locate(detect(flat_photo, target), target, intr.K, intr.dist, R_board, t_board)
    cam = calibrated_camera(true_camera, intr, R, t)                   # the rig's Camera with these values
    score(true_camera, cam)                                            # against the twin's truth
    rig, report = calibrate_cameras(nominal, truth, views, seed)       # all of it in the twin, every camera

Goals (`CAMERA_GOALS`, from what good systems reach: a light stage of the same group reports 0.25-0.27 px RMS;
docs/calibration.md): reprojection RMS <= 0.3 px, focal length within 0.1%.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CalibrationError", "Detection", "Intrinsics", "detect", "calibrate_intrinsics", "locate",
           "calibrated_camera", "score", "calibrate_cameras", "CAMERA_GOALS", "MIN_CORNERS", "MIN_VIEWS"]

MIN_CORNERS = 12   # corners a view needs to count (a homography plus redundancy)
MIN_VIEWS = 4      # views with enough corners the intrinsics need (Zhang: >= 3 for K; more for distortion)
# The steepest grey-level step per pixel near each corner, over the local contrast, median over the corners: a
# sharp edge steps within ~2 px (~0.5 measured on the twin's board photos); a Gaussian blur of sigma 1 / 2 / 3 px
# gives 0.33 / 0.19 / 0.14 (measured). OpenCV still finds the corners of a board blurred by 5 px, but each corner
# then rests on a few grey levels' slope: refused below 0.25 (sigma ~1.5 px).
MIN_SHARPNESS = 0.25


class CalibrationError(ValueError):
    """Bad calibration data, named with the photo it came from."""


@dataclass(frozen=True)
class Detection:
    label: str
    corners: np.ndarray   # (N, 2) sub-pixel image positions (OpenCV pixel convention)
    ids: np.ndarray       # (N,) ChArUco corner ids


@dataclass(frozen=True)
class Intrinsics:
    K: np.ndarray
    dist: np.ndarray          # (5,) k1, k2, p1, p2, k3
    rms_px: float             # RMS reprojection error over all corners of all views
    per_view_px: np.ndarray   # RMS per view
    views: int
    corners: int


def detect(image: np.ndarray, target, label: str) -> Detection:
    """The board's inner corners in one 8-bit grey photo. A photo without enough of the board, or saturated
    over much of it, is refused with its label."""
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise CalibrationError(f"{label}: expected an 8-bit grey photo, got {img.dtype} {img.shape}")
    if (img == 255).mean() > 0.05:
        raise CalibrationError(f"{label}: {100 * (img == 255).mean():.1f}% of the pixels are saturated; lower the "
                               "exposure")
    det = cv2.aruco.CharucoDetector(target.board())
    corners, ids, _, _ = det.detectBoard(img)
    n = 0 if ids is None else len(ids)
    if n < MIN_CORNERS:
        raise CalibrationError(f"{label}: the board was not found ({n} corners, need >= {MIN_CORNERS}); is it in "
                               "view, in focus and lit?")
    corners = corners.reshape(-1, 2).astype(np.float64)
    sharp = edge_sharpness(img, corners)
    if sharp < MIN_SHARPNESS:
        raise CalibrationError(f"{label}: the board is out of focus (edge sharpness {sharp:.2f} at its corners, need "
                               f">= {MIN_SHARPNESS}; a focused board gives ~0.5)")
    return Detection(label, corners, ids.ravel().astype(np.int64))


def edge_sharpness(img: np.ndarray, corners: np.ndarray, half: int = 6) -> float:
    """Median over `corners` (N, 2) of max |gradient| / (max - min) in the (2 half + 1)^2 window at each."""
    import cv2

    g = img.astype(np.float64)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_64F, 0, 1, ksize=3)) / 8
    vals = []
    for u, v in np.round(corners).astype(int):
        win = (slice(max(v - half, 0), v + half + 1), slice(max(u - half, 0), u + half + 1))
        vals.append(mag[win].max() / max(float(g[win].max() - g[win].min()), 1.0))
    return float(np.median(vals))


def calibrate_intrinsics(views: list[Detection], target, image_size: tuple[int, int]) -> Intrinsics:
    """K and the five distortion coefficients from `views` (Zhang's method through cv2.calibrateCamera)."""
    import cv2

    if len(views) < MIN_VIEWS:
        raise CalibrationError(f"{len(views)} usable views of the board; the intrinsics need >= {MIN_VIEWS} at "
                               "different tilts")
    obj_all = target.corners_mm()
    obj = [obj_all[v.ids].astype(np.float32) for v in views]
    img = [v.corners.astype(np.float32) for v in views]
    flags = 0
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(
        obj, img, tuple(image_size), None, None, flags=flags, criteria=crit)
    return Intrinsics(np.asarray(K, np.float64), np.asarray(dist, np.float64).ravel()[:5], float(rms),
                      np.asarray(per_view, np.float64).ravel(), len(views), int(sum(len(v.ids) for v in views)))


def locate(view: Detection, target, K: np.ndarray, dist: np.ndarray, R_board: np.ndarray,
           t_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera's world -> camera R, t from one view of the board whose pose in the world (X = R_board b +
    t_board) is known (it lies on the sample plane, registered to the holder)."""
    import cv2

    obj = target.corners_mm()[view.ids]
    ok, rvec, tvec = cv2.solvePnP(obj, view.corners, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError(f"{view.label}: the board's pose could not be solved")
    R_cb = cv2.Rodrigues(rvec)[0]  # board -> camera
    R = R_cb @ np.asarray(R_board, np.float64).T
    t = tvec.ravel() - R @ np.asarray(t_board, np.float64)
    return R, t


def calibrated_camera(camera, intr: Intrinsics, R: np.ndarray, t: np.ndarray):
    """The rig's camera (same name, size, sensor) with the calibrated K, distortion and pose."""
    from dataclasses import replace

    return replace(camera, K=intr.K, dist=intr.dist, R=R, t=t, assumed=False,
                   note=f"calibrated from {intr.views} ChArUco views, RMS {intr.rms_px:.3f} px")


def score(truth, est, sample_plane, size_mm: float) -> dict:
    """How far a calibrated camera is from the true one: focal length (%), principal point (px), centre (mm),
    orientation (deg), and what matters downstream, the pixel each point of the sample area lands on (a 21 x 21
    grid over `size_mm`, through the full model, distortion included)."""
    f_t, f_e = np.diag(truth.K)[:2], np.diag(est.K)[:2]
    dR = est.R @ truth.R.T
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    s = np.linspace(-size_mm / 2, size_mm / 2, 21)
    gx, gy = np.meshgrid(s, s)
    o, x, y = (np.asarray(v, np.float64) for v in (sample_plane.origin, sample_plane.x_axis, sample_plane.y_axis))
    X = o + gx.reshape(-1, 1) * x + gy.reshape(-1, 1) * y
    d = np.linalg.norm(est.project(X)[0] - truth.project(X)[0], axis=1)
    return {"focal_pct": float(np.max(np.abs(f_e / f_t - 1)) * 100),
            "principal_px": float(np.linalg.norm(est.K[:2, 2] - truth.K[:2, 2])),
            "centre_mm": float(np.linalg.norm(est.centre - truth.centre)), "rotation_deg": float(ang),
            "sample_px_median": float(np.median(d)), "sample_px_max": float(d.max())}


# what good systems reach (docs/calibration.md): reprojection RMS <= 0.3 px, the focal length within 0.1%
CAMERA_GOALS = {"rms_px": 0.3, "focal_pct": 0.1}


def calibrate_cameras(nominal, truth, views: int, seed: int, supersample: int = 2, board_scale: int = 1,
                      progress: bool = True) -> tuple:
    """Photograph a ChArUco board with every camera of the TRUE rig (twin), calibrate each camera from those
    photos alone, and return (the nominal rig with the calibrated cameras, a report per camera scoring it
    against the truth, with the nominal camera's own errors beside it for comparison). board_scale s: the board
    is photographed by each camera's lens on a sensor of s x s times its pixels (Camera.resized) and the
    result scaled back: the way for the mini rig, whose 222 x 192 px cameras are too small for corner
    detection (the paper rig's cameras are the mini rig's at s = 12); rms_px is then in those finer pixels.

    nominal, truth   Rigs (lengths in mm): the values known beforehand, and the device the photos are taken of
    views            board poses per camera (at least MIN_VIEWS = 4), plus one view of the board lying flat on the
                     sample plane for the pose
    seed             the poses' and the photos' noise; supersample: rays per pixel side of the board's photos
    The calibrated camera: K (3, 3) in pixels, dist (5,) OpenCV (k1, k2, p1, p2, k3), R (3, 3), t (3,) mm. The
    report per camera: views, corners, rms_px (reprojection RMS, pixels), focal_pct (%), principal_px (pixels),
    centre_mm (mm), rotation_deg (degrees), sample_px_median and sample_px_max (pixels: where the points of the
    sample area land, the calibrated camera against the true one), nominal_error (the same scores of the nominal
    camera), goals (CAMERA_GOALS) and passed."""
    import sys
    from dataclasses import replace

    from twin.targets.charuco import CharucoTarget, calibration_poses, flat_pose

    target = CharucoTarget()
    rng = np.random.default_rng([int(seed), 18])
    size = nominal.sample.max_size * 0.8
    cams, report = {}, {}
    for name, true_cam in truth.cameras.items():
        cam = true_cam.resized(board_scale)
        dets = []
        for k, (R, t) in enumerate(calibration_poses(cam, target, truth.sample, views, seed)):
            label = f"{name} view {k}"
            dets.append(detect(target.photo(cam, R, t, rng, supersample=supersample), target, label))
            if progress:
                print(f"[calibrate] {label}: {len(dets[-1].ids)} corners", file=sys.stderr, flush=True)
        intr = calibrate_intrinsics(dets, target, (cam.width, cam.height))
        Rf, tf = flat_pose(target, truth.sample)
        R, t = locate(detect(target.photo(cam, Rf, tf, rng, supersample=supersample), target, f"{name} flat"),
                      target, intr.K, intr.dist, Rf, tf)
        cams[name] = calibrated_camera(nominal.cameras[name].resized(board_scale), intr, R, t).resized(1 / board_scale)
        s = score(true_cam, cams[name], truth.sample, size)
        goals = {"rms_px": intr.rms_px <= CAMERA_GOALS["rms_px"], "focal_pct": s["focal_pct"] <= CAMERA_GOALS["focal_pct"]}
        report[name] = {"views": intr.views, "corners": intr.corners, "rms_px": intr.rms_px, **s,
                        "nominal_error": score(true_cam, nominal.cameras[name], truth.sample, size),
                        "goals": goals, "passed": all(goals.values())}
    return replace(nominal, cameras=cams), report
