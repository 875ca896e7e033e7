"""Is an alignment right? A check that needs no ground truth, for real captures (ours; the paper and the reference
have none).

    check = check_alignment(primary_hdr, secondary_hdr, alignment, rig)
    check["flagged"]     # True: the views disagree by more than CheckConfig.flag_px; the pipeline stops
    check["verified"]    # False: too little texture of the sample's own to tell (the map is then the rig's geometry)

How. The secondary photo is resampled into the primary's grid through the alignment (warp_to_primary) and the
two are compared tile by tile inside the holder frame's window (alignment.sample_window): the residual shift
that would bring the warped secondary onto the primary, its whole pixels from OpenCV's phase correlation (Kuglin &
Hines 1975; cv2.phaseCorrelate, Hanning-windowed), its fraction from the enhanced correlation coefficient
(Evangelidis & Psarakis 2008; cv2.findTransformECC, a translation). Right, it is ~0 wherever the sample has
texture. It is independent of the aligner: no descriptors, no PatchMatch, no homography model.

What it must not trust. Under the uniform light both photos share the sample's own texture, but not its shading:
a glossy sample's highlights and the LEDs' reflections move with the view. Each tile is high-passed (its blur over a
quarter of the tile subtracted: shading is smooth at that scale), and a tile counts only where the
correlation peak is distinct (its response >= CheckConfig.min_response, the peak's share of the normalised
cross-power) and within the dense step's search (CheckConfig.reach_px: farther is a reflection). A tile fixes the shift only across its texture (stripes, a weave: the aperture problem),
so the verdict is the one shift that agrees best, in the L1 sense, with every tile in the directions its texture
fixes (a robust median: a few tiles of moving reflections do not decide it), and none along a direction that no
tile fixes, in secondary pixels (the unit of the goal). Fewer than CheckConfig.min_tiles tiles, or fewer than a third
of them: not verified (a sample with too little texture of its own, where the map is the rig's geometry).

Threshold (from the goal, not from measured values): the alignment goal is 0.5 px; a fault of 1 px (a secondary
camera moved by a pixel, a wrong height of the sample plane) must be caught: flag_px = 0.75, between the two.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruction.stages.alignment import REFERENCE_WIDTH, Alignment, sample_window, tone_map, warp_to_primary

__all__ = ["CheckConfig", "check_alignment"]


@dataclass(frozen=True)
class CheckConfig:
    flag_px: float = 0.75  # the residual shift (secondary px) above which an alignment is flagged (docstring)
    tiles: int = 6  # tiles along the window's shorter side (half-overlapping)
    min_tile: int = 32  # px: the smallest tile (phase correlation needs room for the shift and the window)
    min_response: float = 0.1  # the correlation peak's least strength for a tile to count
    reach_px: float = 50.0  # reference px (scaled with the width): shifts beyond the dense step's search are view-
    #                         dependent reflections, not a residual of the alignment
    min_tiles: int = 4  # fewer tiles that count, or fewer than min_share of them: not verified
    min_share: float = 1 / 3
    blur_px: float = 1.0  # Gaussian sigma (px) of the band-pass's low side (_band_pass)
    min_anisotropy: float = 0.3  # a tile fixes the shift in its texture's weaker direction too above this ratio

    def __post_init__(self):
        if not (self.flag_px > 0 and self.tiles >= 1 and self.min_tile >= 8 and 0 <= self.min_response < 1
                and self.min_tiles >= 1):
            raise ValueError(f"CheckConfig: flag_px > 0, tiles >= 1, min_tile >= 8, 0 <= min_response < 1 and "
                             f"min_tiles >= 1 are required, got {self}")


def _band_pass(tile: np.ndarray, k: int, sigma: float) -> np.ndarray:
    """tile blurred by a Gaussian of `sigma` px (what the two views cannot both resolve: the secondary sees the
    sample foreshortened, and its finer texture aliases when warped), less its smooth part (two passes of a k x k
    box filter, ~ a Gaussian of sigma k / 2.5 at a cost that does not grow with k: the shading)."""
    import cv2

    k = max(k | 1, 3)
    if sigma > 0:
        tile = cv2.GaussianBlur(tile, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    smooth = cv2.blur(cv2.blur(tile, (k, k), borderType=cv2.BORDER_REFLECT), (k, k), borderType=cv2.BORDER_REFLECT)
    return tile - smooth


def check_alignment(primary: np.ndarray, secondary: np.ndarray, alignment: Alignment, rig,
                    config: CheckConfig = CheckConfig(), primary_camera: str = "primary") -> dict:
    """The residual shift between the primary photo and the secondary photo warped by `alignment` (docstring):
    {"flagged", "verified", "median_shift_px" (its length; None if not verified), "shift_px" (dx, dy), "directions"
    (how many the tiles' texture fixes), "tiles", "tiles_used", "tile_px", "flag_px"}."""
    import cv2

    cfg = config
    cam0 = rig.camera(primary_camera)
    g0 = tone_map(np.atleast_3d(np.asarray(primary, np.float32))).mean(axis=2)
    g1 = warp_to_primary(tone_map(np.atleast_3d(np.asarray(secondary, np.float32))).mean(axis=2), alignment)
    x0, y0, x1, y1 = sample_window(cam0, rig, 0)
    side = max(cfg.min_tile, int(min(x1 - x0, y1 - y0) // max(cfg.tiles, 1) * 2))
    side = min(side, x1 - x0, y1 - y0)
    step = max(side // 2, 1)
    hann = cv2.createHanningWindow((side, side), cv2.CV_64F)
    reach = max(2.0, cfg.reach_px * cam0.width / REFERENCE_WIDTH)
    shifts, normals, responses = [], [], []
    for ty in range(y0, y1 - side + 1, step):
        for tx in range(x0, x1 - side + 1, step):
            a, b = g0[ty:ty + side, tx:tx + side], g1[ty:ty + side, tx:tx + side]
            if not np.isfinite(b).all():
                continue
            a = _band_pass(a, side // 4, cfg.blur_px).astype(np.float64)
            b = _band_pass(b, side // 4, cfg.blur_px).astype(np.float64)
            (dx, dy), response = cv2.phaseCorrelate(a, b, hann)
            responses.append(response)
            if response >= cfg.min_response and max(abs(dx), abs(dy)) <= reach:
                # phase correlation's sub-pixel peak (a centroid) leans toward the nearest whole pixel: from it,
                # the enhanced correlation coefficient's Gauss-Newton (Evangelidis & Psarakis 2008,
                # cv2.findTransformECC) finds the sub-pixel shift, insensitive to the views' gain and offset
                try:
                    _, warp = cv2.findTransformECC(a.astype(np.float32), b.astype(np.float32),
                                                   np.float32([[1, 0, dx], [0, 1, dy]]), cv2.MOTION_TRANSLATION,
                                                   (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4),
                                                   None, 1)
                except cv2.error:  # no convergence: a tile without a shift to measure
                    continue
                dx, dy = float(warp[0, 2]), float(warp[1, 2])
                shifts.append((dx, dy))
                normals.append(_constrained(a * hann, cfg.min_anisotropy))
    shift, rank = _robust_shift(np.array(shifts).reshape(-1, 2), normals)
    verified = len(shifts) >= max(cfg.min_tiles, cfg.min_share * len(responses)) and rank > 0
    # in secondary px, as the alignment's goal and its error against the truth (alignment_error) are: through the
    # map's Jacobian at the window's centre
    cy, cx = (y0 + y1) // 2, (x0 + x1) // 2
    m = alignment.map  # four pixels read, not the whole map copied (2664 x 2304 on the paper rig)
    J = np.stack([(m[cy, cx + 1] - m[cy, cx - 1]) / 2, (m[cy + 1, cx] - m[cy - 1, cx]) / 2], axis=1).astype(np.float64)
    shift = J @ shift
    med = float(np.linalg.norm(shift)) if verified else None
    return {"flagged": bool(verified and med > cfg.flag_px), "verified": bool(verified), "median_shift_px": med,
            "shift_px": shift.tolist() if verified else None, "directions": rank, "tiles": len(responses),
            "tiles_used": len(shifts), "tile_px": int(side), "flag_px": cfg.flag_px}


def _constrained(tile: np.ndarray, min_anisotropy: float) -> np.ndarray:
    """(k, 2) unit directions in which a tile's texture fixes a shift (the aperture problem): the structure
    tensor's strongest eigenvector, and the other one too where its eigenvalue is at least `min_anisotropy` of
    the strongest (a texture that varies both ways; stripes fix a shift only across themselves)."""
    gy, gx = np.gradient(tile)
    T = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]])
    lam, vec = np.linalg.eigh(T)
    return vec[:, ::-1].T[: 2 if lam[0] >= min_anisotropy * lam[1] else 1]


def _robust_shift(shifts: np.ndarray, normals: list) -> tuple[np.ndarray, int]:
    """The one shift s that agrees with the tiles' shifts in the directions their texture fixes, n . s = n . s_i,
    in the L1 sense (iteratively reweighted least squares: the median's robustness to a minority of tiles on
    reflections). Returns s and how many directions the tiles fix together (0, 1 or 2); a direction none fixes
    gets no shift (minimum norm)."""
    if len(shifts) == 0:
        return np.zeros(2), 0
    N = np.concatenate(normals)
    d = np.concatenate([n @ s for n, s in zip(normals, shifts)])
    lam = np.linalg.eigvalsh(N.T @ N)
    rank = int(np.sum(lam > 0.05 * len(N)))  # a direction that at least ~5 % of the constraints fix
    s, w = np.zeros(2), np.ones(len(N))
    for _ in range(20):
        A = N * w[:, None]
        s = np.linalg.lstsq(A.T @ N, A.T @ d, rcond=0.05)[0]
        w = 1 / np.maximum(np.abs(N @ s - d), 0.02)
    return s, rank
