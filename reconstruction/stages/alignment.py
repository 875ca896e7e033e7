"""Two-view alignment: where each primary-camera pixel sees, in the secondary camera, the same point of the
sample (paper §8; reference §6.1 step 5 and §6.2).

    al = align_views(primary_hdr, secondary_hdr, rig)          # the uniform-light photos, k = 129
    warped = warp_to_primary(secondary_photo, al)              # any secondary photo in the primary's grid
    alignment_error(al, pixel_texel_primary, pixel_texel_secondary)  # against a twin capture's ground truth

Two steps, as in the reference:

1. **Coarse**: a homography of the sample plane, in UNDISTORTED pixel coordinates of both cameras (each
   camera's own K and distortion from the rig; reference §6.1 step 1 undistorts with the original K).
   Three ways to get it (`AlignConfig.coarse`):
   * "sift": OpenCV SIFT keypoints of both tone-mapped photos, brute-force matching with Lowe's ratio test at
     0.5 and a RANSAC homography (reference §6.1 step 5: threshold 4 px on images half the calibration
     width, i.e. 8 px at the calibration width, scaled here with the image width). Keypoints are detected
     on the raw photos and their coordinates undistorted (no resampling of the photos).
   * "markers": the holder frame's ArUco markers (the paper's "ARTags"; dictionary, ids and 3-D corners from
     `rig.frame`). Each camera's pose is solved from its own detected corners (cv2.solvePnP with its K and
     distortion), and the homography is the one the two poses induce on the SAMPLE plane, which lies
     `rig.frame.height` below the markers: a homography fitted to the marker corners directly would be that
     of the frame's plane, off by the parallax of that height (~1 px in the mini rig's 45 deg view).
   * "calibrated": the homography the two calibrated cameras (rig R, t) induce on the sample plane.
   * "auto" (ours, the default): the first of sift, markers, calibrated that works on these photos and lies within
     `AlignConfig.coarse_tolerance` of the calibrated geometry. SIFT keypoints are taken inside the frame's window
     only (`sample_window`): outside it they lie on the frame, 1.5 mm above the sample plane, and a homography
     fitted to them is the frame's (10-20 px off the sample's on the paper rig, more than a glossy sample's dense
     matches pull back). On both rigs' uniform photos SIFT then rarely finds enough matches, and the markers give it.
2. **Dense** (`AlignConfig.dense`, reference §6.2): dense SIFT descriptors (SIFT Flow) of the primary photo
   and of the secondary photo warped into the primary's pixel grid by the homography, then PatchMatch from
   the primary to the warped secondary over integer offsets, so that offset 0 IS the homography. Ours on
   top of the reference's integer result:
   * a sub-pixel offset from a quadratic fit of the patch cost over the 3 x 3 integer offsets around the
     best one (its Hessian says how well the match is determined in each direction);
   * a refit of the homography to all the dense matches, each weighted by that Hessian (an edge constrains
     only across itself; a flat region not at all) up to a cap, so that no few confident matches decide it
     (`AlignConfig.information_cap`), then matching again relative to the refitted
     homography (`AlignConfig.refine_passes`). The refit changes only the height of the sample plane that
     the calibrated cameras see (`AlignConfig.refit`, "height"; "homography" frees all 8 parameters). For a
     planar sample the refitted homography is the best mapping there is, and it carries the textured parts'
     accuracy into the textureless ones, which PatchMatch alone cannot align;
   * a gate: a pixel keeps its own PatchMatch offset only where that match is distinct and clearly better
     than the homography's (`AlignConfig.gate`, `gain`), i.e. where the sample departs from the plane;
     elsewhere the map is the homography.
   The dense step looks inside the holder frame's window only (`sample_window`).
3. **Pyramid** (ours, `AlignConfig.pyramid_width`): photos wider than 700 px (the paper rig's 2664 px) are
   binned f x f (f = 4 there) and steps 1-2 run on the binned pair with the reference constants scaled to
   it; then the dense step runs once more at full width, where every pixel searches the whole window of
   +-f px around the refitted homography (a cost volume, `patchmatch.exhaustive`) and the refits go on.
   A part of the sample that the binned level matched farther than f px off the plane keeps that offset.
   Why: at full width the reference's PatchMatch evaluates ~10^3 candidate 7 x 7 x 128 patch costs per
   pixel and pass, each a scattered read: minutes per alignment on a GPU, against seconds through the pyramid
   (docs/performance.md). The mini rig's
   222-px photos take one level, as before.

Coordinates: pixel (x = column, y = row), centres at integers (twin.rig.units). The map is returned in RAW
(distorted) pixel coordinates of both cameras, as the photos are stored.

Photos are linear HDR. SIFT needs 8-bit images and gradients that do not depend on the exposure, so each
photo is tone-mapped on its own: divided by the 99.5th percentile of its grey level (mean of RGB), clipped
to [0, 1] and raised to 1/2.2 (a display gamma); SIFT gets that grey image quantised to 8 bits, the dense
descriptors get the same curve applied to each RGB channel, in float.

Scale: the reference's pixel constants (cell 20 px, jumps 20..1, search radii 50..1, initial noise 30) are
for images of the calibration's half resolution, 2664 px wide (reference §1.5, §6.2). They are scaled by
(image width / 2664), rounded to whole pixels (at least 1) where they are integer offsets: the mini rig's
222-px images get a cell of 1.67 px, jumps (2, 1), search radii (4, 2, 1) and offsets within +-4 px.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace, field
from types import SimpleNamespace

import numpy as np
import torch

from reconstruction.stages.patchmatch import PatchCost, dense_sift, exhaustive, patchmatch, subpixel

__all__ = ["AlignConfig", "Alignment", "AlignmentError", "align_views", "warp_to_primary", "alignment_error",
           "tone_map", "REFERENCE_WIDTH"]

REFERENCE_WIDTH = 2664  # px: width of the primary camera's calibration (half sensor resolution, reference §1.5)
COARSE_METHODS = ("auto", "sift", "markers", "calibrated")
AUTO_ORDER = ("sift", "markers", "calibrated")  # "auto": the first that works on these photos
REFIT_MODELS = ("height", "homography")


class AlignmentError(ValueError):
    """Bad input, or a coarse method that cannot be used on these photos (too few matches, no markers)."""


@dataclass(frozen=True)
class AlignConfig:
    """Settings of `align_views`. Pixel constants marked "reference px" are in pixels of a 2664-px-wide image
    and are scaled with the image width (module docstring)."""

    coarse: str = "auto"  # "sift" (reference §6.1), "markers" (paper §8: ARTags), "calibrated" (ours), or
    #                       "auto" (ours): sift, else markers, else calibrated (module docstring)
    dense: bool = True  # dense SIFT + PatchMatch refinement (reference §6.2, paper §8)
    # --- coarse: SIFT (reference §6.1 step 5) ---
    ratio: float = 0.5  # Lowe's ratio test (reference)
    ransac_px: float | None = None  # RANSAC reprojection threshold in undistorted px; None = 8 reference px
    #                                  (the reference's 4 px on its half-size SIFT images)
    min_inliers: int = 12  # ours: fewer RANSAC inliers than this is an error, not a homography
    # ours, "auto" only: a coarse homography that moves the sample window's corners farther than this (reference px)
    # from where the calibrated cameras put them is passed over for the next method: half the dense step's search
    # (max_offset), so that the dense step still reaches the truth from it twice over
    coarse_tolerance: float = 25.0
    # --- coarse: markers (ours: the paper names ARTags, the released code does not use them) ---
    min_markers: int = 2  # per camera, for a stable pose
    marker_upsample: int = 4  # ours: ArUco needs >~ 4 px per marker cell; the mini rig's markers have ~2.5
    # --- dense: SIFT Flow descriptors (reference §6.2) ---
    cell_size: float | None = None  # px per descriptor cell; None = 20 reference px
    orientation_sharpness: float = 9.0  # exponent on the orientation-bin cosine (reference)
    norm_floor: float = 0.01  # descriptor / (|descriptor| + floor) (reference); tone-mapped grey levels per px
    # --- dense: PatchMatch (reference §6.2) ---
    patch: int = 7  # SSD patch side in px (reference and paper; not scaled)
    iterations: int = 10  # (reference and paper)
    jump_radii: tuple[float, ...] = (20, 10, 5, 2, 1)  # reference px (reference code)
    search_radii: tuple[float, ...] = (50, 25, 12, 6, 3, 1)  # reference px (reference code, alpha = 0.5)
    init_noise: float = 30  # reference px: initial offsets uniform in [-n, n) (reference code)
    max_offset: float = 50  # reference px: offsets are limited to |dx|, |dy| <= this (ours; = the search radius)
    # ours, the gate: a pixel takes its sub-pixel PatchMatch offset only where the fitted minimum c* of its patch
    # cost is distinct, smallest eigenvalue of the fitted cost Hessian > gate c* (not a textureless region, not
    # an edge), AND clearly better than the homography's offset 0, c(0) - c* > gain c*; elsewhere the map keeps
    # the homography. c* measures how well the two views' descriptors can agree there at all (noise,
    # view-dependent appearance), so both tests are relative to it.
    gate: float = 2.0
    gain: float = 1.0
    volume_budget_mb: float = 1024.0  # ours: precompute the cost of every offset when it fits, else evaluate
    #                                    each PatchMatch candidate directly (same costs; see PatchCost)
    refine_passes: int = 3  # ours: refit the homography to the dense matches and match again relative to it, up
    #                         to this many times (fewer once it moves < 0.1 px); 0 = the reference's single pass
    # ours, what the refit may change: "height" (default), the height of the sample plane that the calibrated
    # cameras see (the sample lies flat on the board, pressed by the holder frame: its one unknown is its
    # thickness); "homography", all 8 parameters. Measured on the material suite (mini rig, median px,
    # homography -> height): leather 0.52 -> 0.20, wood 0.41 -> 0.24, quadrants 0.34 -> 0.14, paper 0.28 ->
    # 0.02, ramps 0.13 -> 0.12: 8 free parameters follow biases of the dense matches on weakly or anisotropically
    # textured samples (its error grows linearly across the sample: a spurious tilt), one cannot.
    refit: str = "height"
    # ours: no few matches may decide the refit: each pixel's information (its cost Hessian's strongest eigenvalue
    # over its minimum cost) is capped at this percentile of the refit's pixels' (None: no cap). Why: a sharp cost
    # minimum says that a match is precise, not that it is right; where a sample looks different from the two
    # views (a glossy one's shading under uniform light), a minority of confident matches carried +0.3 to +0.6 px
    # and moved the refitted plane: the main job's sample (ramps, mini rig) missed the 0.5 px goal at 7 of 9
    # capture seeds (0.54-0.64 px; seed 1, CI's, 0.13), and with the cap it is at 0.10-0.18 px at all 9; the suite's
    # 15 samples stay or improve (fabric 0.16 -> 0.01 px), the worst 0.26 -> 0.25 px (docs/accuracy.md, "Open").
    information_cap: float | None = 90.0
    # ours, a two-level pyramid for photos wider than this (the paper rig's 2664 px): PatchMatch and the refits
    # run as above on both photos binned by the smallest integer f that makes them at most this wide (2664 ->
    # 666 px, f = 4), and then once more at the full width, where every pixel searches its whole window of
    # +-f px around the refitted homography (`patchmatch.exhaustive`) and the refits go on; a part of the
    # sample that the binned level matched farther off the plane than that keeps the binned offset. At full
    # width the reference-scaled PatchMatch needs ~10^3 candidate evaluations of 7 x 7 x 128 values per pixel
    # and pass, each a scattered read (minutes per alignment on a GPU, docs/performance.md). None: one
    # level at any width
    pyramid_width: int | None = 700
    seed: int = 0  # PatchMatch's random initialisation and search (torch.Generator)
    device: str = "cpu"

    def __post_init__(self):
        if self.coarse not in COARSE_METHODS:
            raise ValueError(f"AlignConfig.coarse must be one of {COARSE_METHODS}, got {self.coarse!r}")
        if self.refit not in REFIT_MODELS:
            raise ValueError(f"AlignConfig.refit must be one of {REFIT_MODELS}, got {self.refit!r}")
        if not 0 < self.ratio <= 1:
            raise ValueError(f"AlignConfig.ratio must be in (0, 1], got {self.ratio}")
        if self.patch < 1 or self.patch % 2 == 0:
            raise ValueError(f"AlignConfig.patch must be a positive odd number of pixels, got {self.patch}")
        if (self.iterations < 0 or self.refine_passes < 0 or self.min_inliers < 4 or self.min_markers < 1
                or self.marker_upsample < 1 or (self.pyramid_width is not None and self.pyramid_width < 64)):
            raise ValueError("AlignConfig: iterations >= 0, refine_passes >= 0, min_inliers >= 4, min_markers >= 1, "
                             "marker_upsample >= 1 and pyramid_width >= 64 (or None) are required")
        if self.information_cap is not None and not (np.isfinite(self.information_cap)
                                                     and 0 < self.information_cap <= 100):
            raise ValueError(f"AlignConfig.information_cap must be a percentile in (0, 100] or None, got "
                             f"{self.information_cap}")
        for name in ("ransac_px", "cell_size"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"AlignConfig.{name} must be positive (or None for the scaled reference), got {v}")
        for name in ("jump_radii", "search_radii"):
            v = getattr(self, name)
            if not v or any(not (np.isfinite(r) and r > 0) for r in v):
                raise ValueError(f"AlignConfig.{name} must be a non-empty tuple of positive radii, got {v}")
        for name in ("init_noise", "max_offset", "coarse_tolerance", "gate", "gain", "orientation_sharpness", "norm_floor",
                     "volume_budget_mb"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"AlignConfig.{name} must be finite and >= 0, got {v}")


@dataclass
class Alignment:
    """map (H0, W0, 2) float32: for every primary pixel (x, y), raw (distorted) coordinates, the secondary
    pixel (x, y), raw coordinates, seeing the same sample point; NaN where unknown (off the secondary image).
    homography: 3x3 float64 from UNDISTORTED primary pixels to UNDISTORTED secondary pixels (each camera's own
    K): [x1, y1, 1] ~ H [x0, y0, 1]; the homography the map uses wherever the dense gate keeps it: the coarse
    step's, refitted by the dense step when that ran (the coarse one is then info["coarse_homography"]).
    info: what was done and measured (method, matches, inliers, markers, dense statistics, seconds)."""

    map: np.ndarray
    homography: np.ndarray
    info: dict = field(default_factory=dict)


# --- small helpers ----------------------------------------------------------------------------------------

def _check_image(name, img, cam) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3):
        raise AlignmentError(f"{name} image must be (H, W) or (H, W, 3), got shape {np.shape(img)}")
    if a.shape[:2] != (cam.height, cam.width):
        raise AlignmentError(f"{name} image is {a.shape[1]}x{a.shape[0]} (W x H) but camera {cam.name!r} is "
                             f"{cam.width}x{cam.height}")
    if not np.issubdtype(a.dtype, np.number):
        raise AlignmentError(f"{name} image must be numeric, got {a.dtype}")
    bad = int((~np.isfinite(a)).any(axis=2).sum())
    if bad:
        raise AlignmentError(f"{name} image has {bad} pixels with NaN or Inf; fill or mask them before aligning")
    if a.max() <= 0:
        raise AlignmentError(f"{name} image has no positive pixel (an empty photo?)")
    return a.astype(np.float32)


def tone_map(img: np.ndarray) -> np.ndarray:
    """Linear HDR (H, W, C) -> [0, 1]: / 99.5th percentile of the grey level, clip, ^(1/2.2) (module doc)."""
    grey = img.mean(axis=2)
    white = float(np.percentile(grey, 99.5))
    if white <= 0:
        white = float(grey.max())
    return np.clip(img / white, 0.0, 1.0) ** (1 / 2.2)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x * 255), 0, 255).astype(np.uint8)


def bilinear_taps(shape, x: np.ndarray, y: np.ndarray) -> tuple:
    """What bilinear samples at float pixel coordinates (x = column, y = row, any shape) of an (H, W, ...) image:
    the four taps' flat pixel indices, the weights' fractions and where the point lies inside [0, W-1] x [0, H-1]
    (False for NaN). Computed once for many images sampled at the same points (a view's photos, extraction)."""
    H, W = shape[:2]
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)  # False for NaN
    xs, ys = np.where(inside, x, 0.0), np.where(inside, y, 0.0)
    x0 = np.minimum(np.floor(xs).astype(np.int64), max(W - 2, 0))
    y0 = np.minimum(np.floor(ys).astype(np.int64), max(H - 2, 0))
    fx, fy = (xs - x0)[..., None], (ys - y0)[..., None]
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    return (y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1), fx, fy, inside, (H, W)


def bilinear_at(img: np.ndarray, taps: tuple) -> np.ndarray:
    """bilinear of img (H, W, C) at the points of `taps` (bilinear_taps of its shape)."""
    (i00, i01, i10, i11), fx, fy, inside, shape = taps
    if img.shape[:2] != shape:
        raise ValueError(f"taps for an image of {shape}, got one of {img.shape[:2]}")
    f = img.reshape(shape[0] * shape[1], *img.shape[2:])
    out = ((f[i00] * (1 - fx) + f[i01] * fx) * (1 - fy) + (f[i10] * (1 - fx) + f[i11] * fx) * fy)
    out = out.astype(np.float64)
    out[~inside] = np.nan
    return out


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) at float pixel coordinates (x = column, y = row), any shape; NaN outside
    [0, W-1] x [0, H-1] or where x, y are NaN."""
    return bilinear_at(img, bilinear_taps(img.shape, x, y))


def _undistort_px(cam, uv: np.ndarray) -> np.ndarray:
    """Raw pixels (N, 2) -> undistorted pixels of the same K."""
    Kinv = np.linalg.inv(cam.K)
    xy = (uv - cam.K[:2, 2]) @ Kinv[:2, :2].T
    return cam.undistort(xy) @ cam.K[:2, :2].T + cam.K[:2, 2]


def _distort_px(cam, uv: np.ndarray) -> np.ndarray:
    """Undistorted pixels (N, 2) -> raw pixels."""
    Kinv = np.linalg.inv(cam.K)
    xy = (uv - cam.K[:2, 2]) @ Kinv[:2, :2].T
    return cam.distort(xy) @ cam.K[:2, :2].T + cam.K[:2, 2]


def _apply_h(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = uv @ H[:, :2].T + H[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


def _coarse_map(cam0, cam1, H: np.ndarray, uv0_raw: np.ndarray) -> np.ndarray:
    """Raw primary pixels (N, 2) -> raw secondary pixels through the undistorted-pixel homography."""
    return _distort_px(cam1, _apply_h(H, _undistort_px(cam0, uv0_raw)))


def _plane_to_pixels(K, R, t, rig) -> np.ndarray:
    """3x3 homography from sample-plane coordinates (a, b) along (x_axis, y_axis) to undistorted pixels."""
    sp = rig.sample
    o, xa, ya = (np.asarray(v, float) for v in (sp.origin, sp.x_axis, sp.y_axis))
    return K @ np.stack([R @ xa, R @ ya, R @ o + t], axis=1)


def _scaled(values, scale) -> tuple[int, ...]:
    """Reference-px integer radii at this image scale: rounded, at least 1, duplicates dropped, order kept."""
    return tuple(dict.fromkeys(max(1, int(round(v * scale))) for v in values))


# --- coarse step ------------------------------------------------------------------------------------------

def _sift_homography(g0, g1, cam0, cam1, rig, cfg, scale):
    import cv2

    sift = cv2.SIFT_create()
    # keypoints on the sample only: the holder frame's markers and edges lie rig.frame.height above the sample
    # plane, so a homography fitted to them is the frame's (10-20 px off the sample's on the paper rig)
    kp0, d0 = sift.detectAndCompute(_to_u8(g0), _window_mask(cam0, rig))
    kp1, d1 = sift.detectAndCompute(_to_u8(g1), _window_mask(cam1, rig))
    info = {"keypoints": [len(kp0), len(kp1)]}
    if d0 is None or d1 is None or len(kp0) < 2 or len(kp1) < 2:
        raise AlignmentError(f"sift: too few keypoints (primary {len(kp0)}, secondary {len(kp1)}); "
                             "is the photo textured and exposed?")
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < cfg.ratio * m[1].distance]
    info["matches"] = len(good)
    if len(good) < cfg.min_inliers:
        raise AlignmentError(f"sift: only {len(good)} matches pass the ratio test {cfg.ratio} (need "
                             f">= {cfg.min_inliers}); try coarse='markers' or 'calibrated'")
    p0 = _undistort_px(cam0, np.array([kp0[m.queryIdx].pt for m in good], np.float64))
    p1 = _undistort_px(cam1, np.array([kp1[m.trainIdx].pt for m in good], np.float64))
    thr = cfg.ransac_px if cfg.ransac_px is not None else 8.0 * scale
    H, inl = cv2.findHomography(p0, p1, cv2.RANSAC, thr, maxIters=10000, confidence=0.9999)
    n_in = int(inl.sum()) if inl is not None else 0
    info.update(inliers=n_in, ransac_px=thr)
    if H is None or n_in < cfg.min_inliers:
        raise AlignmentError(f"sift: only {n_in} RANSAC inliers at {thr:.2f} px among {len(good)} matches "
                             f"(need >= {cfg.min_inliers}); try coarse='markers' or 'calibrated'")
    inl = inl.ravel().astype(bool)
    info["residual_px"] = float(np.median(np.linalg.norm(_apply_h(H, p0[inl]) - p1[inl], axis=1)))
    return H / H[2, 2], info


def _marker_pose(g, cam, rig, cfg, label):
    import cv2

    fr = rig.frame
    if fr is None or len(fr.marker_ids) == 0:
        raise AlignmentError(f"markers: rig {rig.name!r} has no holder-frame markers; use coarse='sift' or "
                             "'calibrated'")
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, fr.marker_dictionary)),
                                  _aruco_parameters())
    f = cfg.marker_upsample
    img = _to_u8(g)
    if f > 1:
        img = cv2.resize(img, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC)
    corners, ids, _ = det.detectMarkers(img)
    known = {int(i): k for k, i in enumerate(fr.marker_ids)}
    found = [] if ids is None else [(int(i), c.reshape(4, 2)) for i, c in zip(ids.ravel(), corners)
                                    if int(i) in known]
    if len(found) < cfg.min_markers:
        raise AlignmentError(
            f"markers: {len(found)} of the frame's {len(fr.marker_ids)} markers found in the {label} photo (need "
            f">= {cfg.min_markers}); at {cam.width}x{cam.height} px a {fr.marker_size:g} mm marker may be too "
            "small to decode. Use coarse='sift' or 'calibrated'")
    img_pts = np.concatenate([(c + 0.5) / f - 0.5 for _, c in found])  # upsampled -> original pixel centres
    obj_pts = np.concatenate([fr.marker_corners[known[i]] for i, _ in found])
    ok, rvec, tvec = cv2.solvePnP(obj_pts, img_pts, cam.K, cam.dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise AlignmentError(f"markers: no camera pose from the {label} photo's markers")
    rvec, tvec = cv2.solvePnPRefineLM(obj_pts, img_pts, cam.K, cam.dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj_pts, rvec, tvec, cam.K, cam.dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_pts) ** 2, axis=1))))
    return cv2.Rodrigues(rvec)[0], tvec.ravel(), {"ids": sorted(i for i, _ in found), "reprojection_px": rms}


def _aruco_parameters():
    import cv2

    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX  # corners to a fraction of a pixel
    return p


def _window_mask(cam, rig) -> np.ndarray | None:
    """uint8 mask of the holder frame's window (sample_window's square) in `cam`'s photo; None without a frame."""
    import cv2

    if rig.frame is None:
        return None
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.fillConvexPoly(mask, np.rint(_window_corners(cam, rig)[[0, 1, 3, 2]]).astype(np.int32), 255)
    return mask


def _window_corners(cam, rig) -> np.ndarray:
    """(4, 2) raw pixels of the corners of the part of the sample plane that no frame wall hides (sample_window)."""
    sp = rig.sample
    o, xa, ya = (np.asarray(v, float) for v in (sp.origin, sp.x_axis, sp.y_axis))
    h = rig.frame.inner_size / 2 - rig.frame.height
    return cam.project(np.array([o + a * xa + b * ya for a in (-h, h) for b in (-h, h)]))[0]


def _disagreement(H, cam0, cam1, rig) -> float:
    """Largest distance (secondary px) over the window's corners between where H and the calibrated cameras map
    them on the sample plane: how far a coarse homography is from the rig's geometry."""
    Hc = _plane_to_pixels(cam1.K, cam1.R, cam1.t, rig) @ np.linalg.inv(_plane_to_pixels(cam0.K, cam0.R, cam0.t, rig))
    u = _undistort_px(cam0, _window_corners(cam0, rig))
    return float(np.max(np.linalg.norm(_apply_h(H, u) - _apply_h(Hc, u), axis=1)))


def _coarse(g0, g1, cam0, cam1, rig, cfg, scale):
    if cfg.coarse == "auto":
        failed = {}
        for method in AUTO_ORDER:
            try:
                H, info = _coarse(g0, g1, cam0, cam1, rig, replace(cfg, coarse=method), scale)
            except AlignmentError as e:
                failed[method] = str(e)
                continue
            # a measured homography far from the calibrated geometry is not trusted (AlignConfig.coarse_tolerance):
            # the rig's calibration bounds it better than matches on view-dependent highlights do
            off = _disagreement(H, cam0, cam1, rig) if rig.frame is not None else 0.0
            if off > cfg.coarse_tolerance * scale:
                failed[method] = (f"{method}: {off:.1f} px from the calibrated geometry (tolerance "
                                  f"{cfg.coarse_tolerance * scale:.1f} px)")
                continue
            return H, {**info, "coarse_method": method, "coarse_failed": failed, "calibrated_disagreement_px": off}
    if cfg.coarse == "sift":
        return _sift_homography(g0, g1, cam0, cam1, rig, cfg, scale)
    if cfg.coarse == "markers":
        R0, t0, i0 = _marker_pose(g0, cam0, rig, cfg, "primary")
        R1, t1, i1 = _marker_pose(g1, cam1, rig, cfg, "secondary")
        info = {"markers": [i0["ids"], i1["ids"]], "reprojection_px": [i0["reprojection_px"], i1["reprojection_px"]]}
    else:
        (R0, t0), (R1, t1), info = (cam0.R, cam0.t), (cam1.R, cam1.t), {}
    H = _plane_to_pixels(cam1.K, R1, t1, rig) @ np.linalg.inv(_plane_to_pixels(cam0.K, R0, t0, rig))
    return H / H[2, 2], info


def _height_homography(h: float, cam0, cam1, rig) -> np.ndarray:
    """The homography (undistorted primary -> secondary pixels) that the calibrated cameras induce on the sample
    plane lifted by h mm along its normal."""
    sp = rig.sample
    normal = np.cross(np.asarray(sp.x_axis, float), np.asarray(sp.y_axis, float))  # y = normal x x (twin.materials.samples)
    origin = np.asarray(sp.origin, float) + h * normal
    lifted = SimpleNamespace(sample=SimpleNamespace(origin=origin, x_axis=sp.x_axis, y_axis=sp.y_axis))
    H = _plane_to_pixels(cam1.K, cam1.R, cam1.t, lifted) @ np.linalg.inv(
        _plane_to_pixels(cam0.K, cam0.R, cam0.t, lifted))
    return H / H[2, 2]


def _refit(H, field, roi, box, cam0, cam1, cfg, rig):
    """Refit the homography to the dense matches (ours). cfg.refit "height": H' = the homography the calibrated
    cameras induce on the sample plane lifted by h mm (_height_homography, 1 parameter); "homography": H' =
    H T^-1 (I + E) T (E: 8 parameters, T normalising the undistorted primary pixels). H' minimises sum_p w_p r_p' A_p r_p, where r_p is the difference
    between the offset that H' implies at pixel p (in the primary grid, through the local Jacobian of the
    mapping by H) and the matched sub-pixel offset, and A_p is the information of the match: the fitted cost
    Hessian (positive part) over the fitted minimum cost (the noise level of an SSD), so that an edge
    constrains only across itself and a flat region not at all (the aperture problem), scaled down where its
    strongest direction's exceeds cfg.information_cap's percentile (to that value). Pixels used: in the
    ROI, away from the offset window's edge, with a Hessian eigenvalue above cfg.gate x the minimum cost in
    at least one direction. Robust: iteratively reweighted by the residual m (px along the match's strongest
    direction), first Huber (w = 1 / m beyond 1 px), then Cauchy (w = 1 / (1 + (m / s)^2), s = 1.48 x the
    median m, at least 0.05 px), so that a part of the sample off the plane does not pull the plane's fit.
    Gauss-Newton with numerical derivatives."""
    bx0, by0 = box[:2]
    hess = field["hess"]
    lam, vec = np.linalg.eigh(np.nan_to_num(hess))
    use = roi & field["known"] & np.isfinite(field["lam_min"]) & \
        (lam[..., 1] > cfg.gate * np.maximum(field["cmin"], 0)) & (lam[..., 1] > 0)
    ys, xs = np.nonzero(use)
    ys, xs = ys[::max(1, len(ys) // 20000)], xs[::max(1, len(xs) // 20000)]  # <= ~20k pixels: plenty for 8 numbers
    if len(ys) < 64:
        return H, {"pixels": int(len(ys)), "applied": False}
    P = np.stack([xs + bx0, ys + by0], axis=1).astype(np.float64)
    f = field["flow"][ys, xs]
    Hp = np.einsum("nij,nj,nkj->nik", vec[ys, xs], np.maximum(lam[ys, xs], 0), vec[ys, xs])
    lmax = lam[ys, xs, 1]
    cs = np.maximum(field["cmin"][ys, xs], 0)
    noise = np.maximum(cs, 1e-3 * np.median(cs) + 1e-12)
    A = Hp / noise[:, None, None]  # information: Hessian / noise level
    if cfg.information_cap is not None:  # no few confident matches decide the fit (AlignConfig.information_cap)
        strength = lmax / noise
        A = A * np.minimum(1.0, np.percentile(strength, cfg.information_cap) / strength)[:, None, None]
    u = _undistort_px(cam0, P)
    base = _distort_px(cam1, _apply_h(H, u))
    ex, ey = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    J = np.stack([(_coarse_map(cam0, cam1, H, P + ex) - _coarse_map(cam0, cam1, H, P - ex)) / 2,
                  (_coarse_map(cam0, cam1, H, P + ey) - _coarse_map(cam0, cam1, H, P - ey)) / 2], axis=2)
    Jinv = np.linalg.inv(J)
    c, s = u.mean(axis=0), u.std()
    T = np.array([[1 / s, 0, -c[0] / s], [0, 1 / s, -c[1] / s], [0, 0, 1]])
    Tinv = np.linalg.inv(T)

    def homography(theta):
        if cfg.refit == "height":
            return _height_homography(theta[0], cam0, cam1, rig)
        E = np.zeros(9)
        E[:8] = theta
        return H @ Tinv @ (np.eye(3) + E.reshape(3, 3)) @ T

    def offsets(theta):  # the primary-grid offset at which H maps to where homography(theta) maps
        return np.einsum("nij,nj->ni", Jinv, _distort_px(cam1, _apply_h(homography(theta), u)) - base)

    k_params = 1 if cfg.refit == "height" else 8
    theta = np.zeros(k_params)
    w = np.ones(len(P))
    h = 1e-4 if cfg.refit == "height" else 1e-6  # mm of height; relative homography entries
    for it in range(8):
        g = offsets(theta)
        G = np.stack([(offsets(theta + h * np.eye(k_params)[k]) - g) / h for k in range(k_params)], axis=2)
        GtWA = G.transpose(0, 2, 1) @ (w[:, None, None] * A)  # (N, 8, 2)
        normal = (GtWA @ G).sum(axis=0)
        rhs = (GtWA @ (f - g)[..., None]).sum(axis=0)[:, 0]
        theta = theta + np.linalg.lstsq(normal, rhs, rcond=None)[0]
        res = f - offsets(theta)
        m = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", res, Hp, res), 0) / lmax)  # px along the strong direction
        if it < 3:  # Huber first (convex: gets close from any start), then Cauchy at the residuals' own scale
            w = 1 / np.maximum(m, 1)
        else:
            sigma = max(1.4826 * float(np.median(m)), 0.05)
            w = 1 / (1 + (m / sigma) ** 2)
    Hn = homography(theta)
    shift = np.linalg.norm(offsets(theta), axis=1)
    return Hn / Hn[2, 2], {"pixels": int(len(P)), "applied": True, "median_residual_px": float(np.median(m)),
                           "median_shift_px": float(np.median(shift))}


# --- the two views ------------------------------------------------------------------------------------------

def sample_window(cam0, rig, reach: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) exclusive, in the primary photo: where the dense step looks. The reference crops to the
    sample's texture area plus 25 px (§6.1 step 4), known from its mask; we use what holds any sample: the
    holder frame's window on the sample plane, less the frame's height (its inner walls hide up to that much
    of the plane from a camera at 45 deg), projected, less `reach` px (the descriptors' and patches' reach), so
    that no cost compares the frame, 1.5 mm above the sample plane, with the plane. Without a frame: the
    whole photo less `reach`."""
    x0, y0, x1, y1 = 0, 0, cam0.width, cam0.height
    if rig.frame is not None:
        uv = _window_corners(cam0, rig)
        x0, y0 = np.ceil(uv.min(0)).astype(int)
        x1, y1 = np.floor(uv.max(0)).astype(int) + 1
    x0, y0 = max(x0, 0) + reach, max(y0, 0) + reach
    x1, y1 = min(x1, cam0.width) - reach, min(y1, cam0.height) - reach
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise AlignmentError(f"dense: the region to match ({x0}..{x1} x {y0}..{y1} px) is too small; the photo is "
                             "too small for the descriptors (cell_size, patch, max_offset)")
    return int(x0), int(y0), int(x1), int(y1)


def align_views(primary: np.ndarray, secondary: np.ndarray, rig, config: AlignConfig = AlignConfig(),
                primary_camera: str = "primary", secondary_camera: str = "secondary") -> Alignment:
    """Align the secondary photo to the primary (module docstring). Both are linear HDR (H, W, 3) or (H, W)
    photos of the same scene, normally the uniform-light pair (k = 129) of a capture."""
    cfg = config
    t_start = time.perf_counter()
    cam0, cam1 = rig.camera(primary_camera), rig.camera(secondary_camera)
    im0 = _check_image("primary", primary, cam0)
    im1 = _check_image("secondary", secondary, cam1)
    scale = cam0.width / REFERENCE_WIDTH
    t0, t1 = tone_map(im0), tone_map(im1)
    f = 1 if cfg.pyramid_width is None else -(-cam0.width // cfg.pyramid_width)
    # the pyramid's binned level (AlignConfig.pyramid_width): the coarse step runs there too, since it only has
    # to land within the dense search's reach (SIFT on a 2664 x 2304 photo finds ~10^5 keypoints to match)
    level = _binned_level(im0, im1, cam0, cam1, f) if f > 1 else SimpleNamespace(t0=t0, t1=t1, cam0=cam0, cam1=cam1)
    S = _binning(f)
    H, coarse_info = _coarse(level.t0.mean(2), level.t1.mean(2), level.cam0, level.cam1, rig, cfg, scale / f)
    if not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
        raise AlignmentError(f"{cfg.coarse}: degenerate homography {H.tolist()}")
    H = np.linalg.inv(S) @ H @ S
    H = H / H[2, 2]
    method = coarse_info.pop("coarse_method", cfg.coarse)
    info = {"method": method, **coarse_info, "scale": scale, "pyramid_factor": f, "coarse_homography": H.tolist(),
            "coarse_s": time.perf_counter() - t_start}
    u0 = _undistorted_grid(cam0)
    grid = np.stack(np.meshgrid(np.arange(cam0.width), np.arange(cam0.height)), axis=2).astype(np.float64)
    u = u0
    if cfg.dense:
        if f > 1:
            H, corrections, dense_info = _dense_pyramid(level, t0, t1, cam0, cam1, H, u0, rig, cfg, scale, f)
        else:
            H, corrections, dense_info = _dense(t0, t1, cam0, cam1, H, u0, rig, cfg, scale, None)
        info.update(dense_info)
        moved = (corrections != 0).any(axis=2)
        u = u0.copy()
        u[moved] = _undistort_px(cam0, grid[moved] + corrections[moved])
    result = _distort_px(cam1, _apply_h(H, u.reshape(-1, 2))).reshape(cam0.height, cam0.width, 2)
    out = ~((result[..., 0] >= 0) & (result[..., 0] <= cam1.width - 1) & (result[..., 1] >= 0)
            & (result[..., 1] <= cam1.height - 1))
    result[out] = np.nan
    info["seconds"] = time.perf_counter() - t_start
    return Alignment(result.astype(np.float32), H, info)


def _undistorted_grid(cam) -> np.ndarray:
    """(H, W, 2) undistorted coordinates of every pixel (computed once per level: the iterative undistortion of
    a 2664 x 2304 grid takes seconds)."""
    yy, xx = np.mgrid[0:cam.height, 0:cam.width]
    uv = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
    return _undistort_px(cam, uv).reshape(cam.height, cam.width, 2)


def _binning(f: int) -> np.ndarray:
    """Pixel coordinates -> those of f x f binned pixels (Camera.resized: c' = (c + 0.5) / f - 0.5), raw or
    undistorted alike (the binned camera's K is this matrix times K)."""
    return np.array([[1 / f, 0, (1 / f - 1) / 2], [0, 1 / f, (1 / f - 1) / 2], [0, 0, 1]])


def _binned_level(im0, im1, cam0, cam1, f: int):
    """Both photos binned f x f (the mean of each block: what a camera with f-times larger pixels records; the
    last H % f rows and W % f columns dropped), tone-mapped, with their cameras."""
    def binned(img):
        H, W, C = img.shape
        return tone_map(img[:H // f * f, :W // f * f].reshape(H // f, f, W // f, f, C).mean(axis=(1, 3)))

    def camera(cam):
        return replace(cam, width=cam.width // f * f, height=cam.height // f * f).resized(1 / f)

    return SimpleNamespace(t0=binned(im0), t1=binned(im1), cam0=camera(cam0), cam1=camera(cam1))


def _dense_pyramid(level, t0, t1, cam0, cam1, H, u0, rig, cfg, scale, f):
    """The dense step on the pyramid's two levels (AlignConfig.pyramid_width): PatchMatch and refits on the
    binned level, then the whole +-f px window around its homography at full width."""
    t = time.perf_counter()
    S = _binning(f)
    Hb, binned, binned_info = _dense(level.t0, level.t1, level.cam0, level.cam1, S @ H @ np.linalg.inv(S),
                                     _undistorted_grid(level.cam0), rig, cfg, scale / f, None)
    H = np.linalg.inv(S) @ Hb @ S
    H, corrections, info = _dense(t0, t1, cam0, cam1, H / H[2, 2], u0, rig, cfg, scale, f)
    # the binned level's offsets in full-width px, at the nearest binned pixel; those beyond the full-width
    # window (|o| > f) are parts of the sample off the plane that only the binned level could follow
    yy = np.clip(np.rint((np.arange(cam0.height) + 0.5) / f - 0.5).astype(int), 0, binned.shape[0] - 1)
    xx = np.clip(np.rint((np.arange(cam0.width) + 0.5) / f - 0.5).astype(int), 0, binned.shape[1] - 1)
    up = f * binned[yy[:, None], xx[None, :]]
    beyond = (np.abs(up) > f).any(axis=2)
    corrections[beyond] = up[beyond]
    info["dense"]["binned"] = {**binned_info["dense"], "seconds": binned_info["dense_s"],
                               "beyond_window_fraction": float(beyond.mean())}
    info["dense_s"] = time.perf_counter() - t
    return H, corrections, info


def _dense(t0, t1, cam0, cam1, H, u0, rig, cfg, scale, window):
    """The dense step on one level: PatchMatch (window None) or the whole window of +-window px searched
    (`exhaustive`), the refits (cfg.refine_passes), the gate. u0: the level's undistorted primary pixel grid.
    Returns the homography the map falls back on, the per-pixel corrections (H0, W0, 2) in primary px (the map
    is H applied at pixel + correction; 0 where the gate keeps the homography), and info."""
    t = time.perf_counter()
    p = {"cell": cfg.cell_size if cfg.cell_size is not None else 20.0 * scale,
         # one more than the largest offset: an offset at the limit still has the 3 x 3 neighbours of the
         # sub-pixel fit
         "R": (max(1, int(round(cfg.max_offset * scale))) if window is None else window) + 1,
         "jumps": _scaled(cfg.jump_radii, scale), "searches": _scaled(cfg.search_radii, scale),
         "init": max(1, int(round(cfg.init_noise * scale))), "exhaustive": window is not None}
    # how far from a pixel its cost looks: offset window, patch, descriptor cells (2 cells + the tent) and Sobel
    pad = p["R"] + cfg.patch // 2 + int(np.ceil(3 * p["cell"])) + 1
    x0, y0, x1, y1 = sample_window(cam0, rig, pad)
    box = (max(x0 - pad, 0), max(y0 - pad, 0), min(x1 + pad, cam0.width), min(y1 + pad, cam0.height))
    bx0, by0, bx1, by1 = box
    roi = np.zeros((by1 - by0, bx1 - bx0), bool)
    roi[y0 - by0:y1 - by0, x0 - bx0:x1 - bx0] = True
    gen = torch.Generator().manual_seed(int(cfg.seed))
    passes = []
    field = _match(t0, t1, cam1, H, u0, box, cfg, p, gen)
    for _ in range(cfg.refine_passes):
        H, refit = _refit(H, field, roi, box, cam0, cam1, cfg, rig)
        passes.append(refit)
        if not refit["applied"]:
            break
        field = _match(t0, t1, cam1, H, u0, box, cfg, p, gen)
        if refit["median_shift_px"] < 0.1:  # converged to within the matches' own noise
            break
    # the gate (AlignConfig.gate, gain): a distinct minimum, clearly better than the homography's offset 0
    cmin = np.maximum(field["cmin"], 0)
    accept = roi & field["known"] & (field["lam_min"] > cfg.gate * cmin) & (field["c_zero"] - cmin > cfg.gain * cmin)
    corrections = np.zeros((cam0.height, cam0.width, 2))
    corrections[by0:by1, bx0:bx1][accept] = field["flow"][accept]
    search = {"search": "exhaustive"} if p["exhaustive"] else {
        "search": "patchmatch", "jumps": list(p["jumps"]), "search_radii": list(p["searches"]),
        "init_noise_px": p["init"]}
    info = {"dense": {"cell_px": p["cell"], "max_offset_px": p["R"] - 1, **search, "roi_xyxy": [x0, y0, x1, y1],
                      "cost": field["cost"], "refit": passes, "accepted_fraction": float(accept.sum() / roi.sum()),
                      "median_accepted_offset_px": float(np.median(np.linalg.norm(field["flow"][accept], axis=1)))
                      if accept.any() else 0.0},
            "dense_s": time.perf_counter() - t}
    return H, corrections, info


def _match(t0, t1, cam1, H, u0, box, cfg, p, gen) -> dict:
    """Dense SIFT + PatchMatch (or the exhaustive search) inside `box` of the primary photo against the secondary photo warped by H (its
    offset 0), with the quadratic fit of the cost around the best offset. Arrays over the box: flow (h, w, 2)
    the sub-pixel offset in primary px, hess (h, w, 2, 2) the fitted cost Hessian, lam_min (smallest
    eigenvalue, NaN at the offset window's edge), cmin (fitted minimum cost), known (target had pixels)."""
    bx0, by0, bx1, by1 = box
    m = _distort_px(cam1, _apply_h(H, u0[by0:by1, bx0:bx1].reshape(-1, 2)))
    warped = bilinear(t1, m[:, 0], m[:, 1]).reshape(by1 - by0, bx1 - bx0, -1)
    known = np.isfinite(warped).all(axis=2)
    warped = np.where(known[..., None], warped, 0.0)
    dev = torch.device(cfg.device)
    src = torch.from_numpy(np.ascontiguousarray(t0[by0:by1, bx0:bx1].transpose(2, 0, 1))).float().to(dev)
    tgt = torch.from_numpy(np.ascontiguousarray(warped.transpose(2, 0, 1))).float().to(dev)
    d_src = dense_sift(src, p["cell"], cfg.orientation_sharpness, cfg.norm_floor)
    d_tgt = dense_sift(tgt, p["cell"], cfg.orientation_sharpness, cfg.norm_floor)
    budget = cfg.volume_budget_mb * 2 ** 20
    if p["exhaustive"]:
        r = exhaustive(d_src, d_tgt, cfg.patch, p["R"], budget)
        kind = "volume in bands"
    else:
        cost = PatchCost(d_src, d_tgt, cfg.patch, p["R"], budget)
        off, _ = patchmatch(cost, init_noise=p["init"], jumps=p["jumps"], searches=p["searches"],
                            iterations=cfg.iterations, generator=gen)
        step, cmin, hess, lam_min = subpixel(cost, off)
        r = {"off": off, "step": step, "cmin": cmin, "hess": hess, "lam_min": lam_min,
             "c_zero": cost(cost.encode(torch.zeros_like(off))[None])[0]}
        kind = "volume" if cost.volume is not None else "direct"

    def host(x):
        return x.cpu().numpy().astype(np.float64)

    return {"flow": host((r["off"].to(r["step"].dtype) + r["step"]).permute(1, 2, 0)), "hess": host(r["hess"]),
            "cmin": host(r["cmin"]), "lam_min": host(r["lam_min"]), "known": known, "c_zero": host(r["c_zero"]),
            "cost": kind}


def warp_to_primary(image_secondary: np.ndarray, alignment: Alignment) -> np.ndarray:
    """A secondary photo (H1, W1, C) or (H1, W1) resampled into the primary's pixel grid (H0, W0, C): bilinear
    at alignment.map, NaN where the map is NaN or leaves the secondary photo."""
    img = np.asarray(image_secondary)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    if img.ndim != 3:
        raise AlignmentError(f"image_secondary must be (H, W) or (H, W, C), got shape {np.shape(image_secondary)}")
    m = alignment.map
    out = bilinear(img.astype(np.float64), m[..., 0], m[..., 1]).astype(np.float32)
    return out[..., 0] if squeeze else out


def alignment_error(alignment: Alignment, pixel_texel_primary: np.ndarray, pixel_texel_secondary: np.ndarray,
                    mask: np.ndarray | None = None) -> dict:
    """Error of the map against the twin's ground-truth sidecars (pixel -> true texel (row, col), NaN off the
    sample), in SECONDARY pixels.

    For a primary pixel p with true texel tau0(p), the pixel of the secondary that truly sees that texel is
    q* with tau1(q*) = tau0(p) (tau1 bilinear on the secondary sidecar). Starting from the aligned pixel
    q = map(p), Newton steps q <- q - J(q)^-1 (tau1(q) - tau0(p)) find q*, J the Jacobian of tau1 (central
    differences of +-1 px); the error is |map(p) - q*|. Its first step is the linearised |J^-1 (tau1(q) -
    tau0(p))|; the further steps make it exact where the error is not small. Scored pixels: primary pixels
    whose 3 x 3 neighbourhood is on the sample (the sidecar of an edge pixel averages only the sub-rays that
    hit the sample, so it is biased), with `mask` if given, whose map is finite and lands on the secondary's
    sample; `off_sample` counts those whose aligned pixel does not."""
    tp = np.asarray(pixel_texel_primary, np.float64)
    ts = np.asarray(pixel_texel_secondary, np.float64)
    H0, W0 = alignment.map.shape[:2]
    if tp.shape != (H0, W0, 2):
        raise AlignmentError(f"pixel_texel_primary must be {(H0, W0, 2)} like the map, got {tp.shape}")
    if ts.ndim != 3 or ts.shape[2] != 2:
        raise AlignmentError(f"pixel_texel_secondary must be (H1, W1, 2), got {ts.shape}")
    on = np.isfinite(tp).all(axis=2)
    interior = on.copy()
    interior[1:-1, 1:-1] = np.lib.stride_tricks.sliding_window_view(on, (3, 3)).all(axis=(2, 3))
    interior[[0, -1], :] = False
    interior[:, [0, -1]] = False
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (H0, W0):
            raise AlignmentError(f"mask must be {(H0, W0)}, got {mask.shape}")
        interior &= mask
    m = alignment.map.astype(np.float64)
    sel = interior & np.isfinite(m).all(axis=2)
    ys, xs = np.nonzero(sel)
    q0 = m[ys, xs]
    target = tp[ys, xs]

    def tau(q):
        return bilinear(ts, q[:, 0], q[:, 1])

    q = q0.copy()
    ok = np.isfinite(tau(q)).all(axis=1)
    n_off = int((~ok).sum())
    q, q0, target = q[ok], q0[ok], target[ok]
    for _ in range(6):
        e = tau(q) - target
        jx = (tau(q + [1.0, 0.0]) - tau(q - [1.0, 0.0])) / 2  # d tau / dx: (d row, d col)
        jy = (tau(q + [0.0, 1.0]) - tau(q - [0.0, 1.0])) / 2
        J = np.stack([jx, jy], axis=2)  # (N, 2 tau, 2 px)
        good = np.isfinite(J).all(axis=(1, 2)) & np.isfinite(e).all(axis=1)
        good[good] = np.abs(np.linalg.det(J[good])) > 1e-9
        step = np.zeros_like(q)
        step[good] = np.linalg.solve(J[good], e[good][..., None])[..., 0]
        q = np.where(good[:, None], q - step, np.nan)
    err = np.linalg.norm(q0 - q, axis=1)
    err = err[np.isfinite(err)]
    if err.size == 0:
        raise AlignmentError("alignment_error: no primary pixel could be scored (map and sidecars do not overlap "
                             "on the sample)")
    return {"median_px": float(np.median(err)), "mean_px": float(err.mean()), "p90_px": float(np.percentile(err, 90)),
            "count": int(err.size), "off_sample": n_off}
