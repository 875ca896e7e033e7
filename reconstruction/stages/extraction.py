"""Measurement extraction: from a capture folder's HDR photos to per-texel measurements (reference §6.1, §6.3).

    session = CaptureSession.open(folder)                   # the capture (twin.capture.session)
    grid = texture_grid(session, rig, resolution=64)        # the texture grid over the sample
    meas = extract(session, rig, grid, alignment)           # per texel: learned (+,-) differences of both
                                                            # views, line measurements, transparency

The texture grid (reference §6.1 step 3): a square grid of texels centred on the sample plane's origin, in the
SVBRDF maps' convention (twin.materials.samples: row i along +y, column j along +x, texel centres at
-s/2 + (j + 0.5) s/R), so that the reconstruction exports straight to OpenSVBRDF maps. Its side: the sample's
extent found in the bottom-lit photos (the sample blocks the light that the empty board lets through:
photo 128 against the empty-board photo 130), as the largest centred square inside that region, shrunk by
6.5% of the extent on every side as the reference does (so no texel straddles the sample's edge).

Per photo and camera (reference §6.3, with the differences stated):
  0. the capture's photos are the HDR merge's bilinear demosaic (twin.camera.hdr); `demosaic="malvar2004"` reads
     each photosite's own colour back from them (a bilinear demosaic keeps it) and demosaics that mosaic by
     Malvar-He-Cutler 2004 instead (ours): its red and blue reach less across an edge, so a texel next
     to a much brighter highlight takes less of it (the bilinear tent gives ~0.2 of a red or blue value to each
     side at the mini rig's 2.2 px a texel), for more noise and false colour where the colours do not move
     together; the pipeline reads it only for such texels (reconstruction.pipeline, ReconstructConfig.spill_ratio);
  1. flat field and colour matrix (twin.camera.correction, from the rig's calibration): camera RGB -> the
     LED-RGB radiance the forward model renders, clamped at >= 0 as the reference does;
  2. the texel's footprint in the photo (`footprint`, ours; one function per method, FOOTPRINTS):
     "point": no filter, the value at the texel centre (step 3), the ~4 photosites around it.
     "cell" (default): the mean over the box of pixels, odd widths kx x ky along the image's axes, whose photosites
     overlap the texel's cell (the parallelogram its two grid steps span in that view): no photosite's centre more
     than half a pixel outside it, step 3's bilinear lookup included; each texel's own box, from its own cell (the
     paper rig at 192^2: 5 x 5 in the primary view, 5.4 px a texel, mostly 5 x 3 in the secondary). Where no box
     fits (both widths 1: cells under 3 px, the mini rig's ~2.1 px a texel at 48^2) but a step is over 1.5 px, the
     mean of the bilinear photo at the midpoints of an m_c x m_r split of the cell (m = ceil of the step along that
     grid axis: midpoints no more than a pixel apart), the same mean over the cell by the midpoint rule, each view
     through its own steps; under 1.5 px (the paper rig's ~1 px at 1024^2) the centre's lookup already spans the
     cell. Why: a texel spanning many photosites is measured by all of them instead of the ~4 a bilinear lookup
     reads (the noise's standard deviation ~sigma / k against ~2 sigma / 3), and a weak, rough lobe (paper stock's,
     fabric's: 0.5-2% of a photo) is decided by that noise: its alpha error grows in proportion to the photos'
     noise per texel (docs/accuracy.md: paper on the paper rig at 192^2, alpha 13.0 / 13.7% at the centre, 7.2 /
     8.8% over the cell; the mini rig's held-back paper@9003, alpha_y 10.9 % at the centre, 9.4 % at the
     midpoints). Why per texel: one width for a whole view is its narrowest cell's, and the secondary view's cells,
     read through the alignment map, are under 3 px at a few percent of the texels (the map's local stretches and
     the sample's rim): one width left the secondary view unfiltered and paper's alpha at 9.6 / 12.5%.
     Its limit: where the maps vary within a texel (maps finer than the grid) the cell's mean is not the BRDF at the
     texel centre the fit models (measured on the mini rig at 24^2 with 64^2 maps: paper's alpha 30 -> 52%).
     "gaussian": the reference's anti-aliasing Gaussian, odd width k = 2 ceil(d/2 + 1) - 1 with d the largest
     pixel step between adjacent texels (only when d > 1.5 px). Why not the default: the GGX fit models the
     BRDF AT the texel centre, and the Gaussian (sigma ~1.1 px for texels 2 px apart) mixes the neighbours'
     light in: a weak lobe next to a glossy one took +1% of the bright lines from its neighbour's highlight
     (the suite's paper, wallpaper). Measured on the material suite (mini rig, 48², same captures,
     docs/accuracy.md): without it the median normal error halved where there is relief (wood 0.18 -> 0.08°,
     leather 0.20 -> 0.11°, wallpaper 0.31 -> 0.15°), alpha was better on 8 of 10 samples (wallpaper 7.5/9.4%
     -> 4.6/6.7%); a point sample is noisier, so rho_s got worse on the weak lobes (fabric 10.2 -> 12.9%,
     paper 13.3 -> 16.4%), which the fit's prior then pools;
  3. the value at the texel centre's projection, BILINEAR (the reference truncates to the pixel, a
     half-pixel bias), through the camera's own distortion (no separate undistortion pass: the projection
     already lands on the raw pixel);
  4. the secondary view through the two-view alignment (reconstruction.stages.alignment): a texel's secondary
     pixel is the alignment map at its primary pixel (the reference's homography + PatchMatch warp);
  5. units: LED-RGB radiance times reconstruction.network.data.LUMITEXEL_SCALE = "network units", those of the
     lumitexels the network was trained on; the learned measurements are the grey (mean RGB) differences
     photo(+) - photo(-) of each pair, which equal sum_l q_kl m_l for the network's signed 8-bit
     patterns q (reconstruction.network.architecture.PatternLayer) exactly when the photos are noise-free.
Transparency (reference §6.3): clip(mean_rgb(bottom / empty), 0, 1) at the texel.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from twin.capture.plan import PlanIndices, indices_of
from twin.capture.session import CaptureSession

# reference §6.1: the texture grid is the sample's bounding box shrunk by 6.5% of its extent on every side
GRID_SHRINK = 0.065
# a pixel is "under the sample" when the sample lets through less than this fraction of the empty board's
# bottom light (the built-in samples are opaque, beta = 0; a sample more translucent than this needs an
# explicit size)
SAMPLE_RATIO = 0.5
# pixels whose empty-board bottom light is below this fraction of the brightest are the holder frame or
# outside the board: not evidence either way
LIT_FRACTION = 0.05
MIN_SAMPLE_PIXELS = 64
# "cell": how far (in texels) past the half-pixel margin a photosite's centre may lie: a perspective view's cells
# shrink across the field (the paper rig's secondary at 192^2: 2.98-3.4 px), and a hundredth of a texel is rounding,
# not another texel's light
CELL_SLACK = 0.01
MIDPOINT_STEP = 1.5  # "cell" without a box: px of a texel's step above which its cell is read at midpoints
READERS = 8  # threads that read photos at once (at most the CPUs): 8 x ~0.3 GB of photo in flight



class ExtractionError(ValueError):
    pass


@dataclass(frozen=True)
class TextureGrid:
    """A square grid of resolution x resolution texels, side size_mm, centred on the sample plane's origin."""

    resolution: int
    size_mm: float

    def __post_init__(self):
        if not isinstance(self.resolution, (int, np.integer)) or self.resolution < 2:
            raise ExtractionError(f"grid resolution (--resolution) must be an integer >= 2, got "
                                  f"{self.resolution!r}")
        if not (math.isfinite(self.size_mm) and self.size_mm > 0):
            raise ExtractionError(f"grid size (--size-mm) must be a positive number of mm, got {self.size_mm!r}")

    def check_rig(self, rig) -> None:
        """The grid fits `rig`: no larger than the largest sample its sample plane holds, and no more texels across
        than the primary camera has photosites across the grid (a finer grid reads no new light, it only costs
        memory and time), else an ExtractionError naming the option to change. Checked before any work."""
        if self.size_mm > rig.sample.max_size:
            raise ExtractionError(f"a {self.size_mm:g} mm grid is larger than the largest sample rig {rig.name!r} "
                                  f"holds ({rig.sample.max_size:g} mm a side); choose a smaller --size-mm")
        cam = rig.camera(next(iter(rig.cameras)))
        uv, _ = cam.project(rig.sample.corners(self.size_mm))
        across = int(np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1).max())  # the square's longest side, px
        if self.resolution > across:
            raise ExtractionError(f"{self.resolution} texels across {self.size_mm:g} mm of the sample, where the "
                                  f"primary camera has {across} photosites across it: a finer grid than the camera "
                                  f"reads no new light; choose --resolution {across} or less")

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.resolution), int(self.resolution))

    @property
    def texel_mm(self) -> float:
        return self.size_mm / self.resolution

    def positions(self, rig) -> np.ndarray:
        """(R*R, 3) float64 world positions (mm) of the texel centres, row-major (i * R + j)."""
        from twin.materials.samples import grid_positions

        return grid_positions(self.size_mm, self.shape, rig.sample).reshape(-1, 3)


@dataclass
class Measurements:
    """Per texel (N = R*R, row-major) of a TextureGrid, in network units (module docstring)."""

    grid: TextureGrid
    lines: np.ndarray          # (N, 64, 3) RGB line-light measurements, primary view
    line_weights: np.ndarray   # (64, L_upper, 3) the line patterns' relative drive (levels / 255)
    transparency: np.ndarray   # (N,) in [0, 1]
    valid: np.ndarray          # (N,) bool: seen by both views, every value finite
    pixel_primary: np.ndarray  # (N, 2) the texel centre's primary pixel (x, y)
    pixel_secondary: np.ndarray  # (N, 2) its aligned secondary pixel (x, y), NaN where unknown
    # the 2K learned-pattern photos (+ and - frames, photos 0 to 2K-1; 64 in the reference's plan) of both views
    # (the secondary through the alignment), RGB, and their patterns' relative drive on the upper LEDs:
    # non-negative measurements like the lines, which the GGX fit uses too
    learned_photos: np.ndarray   # (N, 2, 2K, 3) views [primary, secondary]
    learned_weights: np.ndarray  # (2K, L_upper, 3)

    @property
    def learned(self) -> np.ndarray:
        """(N, 2, K) the network's input: the grey (mean RGB) (+, -) differences of the learned photos, views
        [primary, secondary]."""
        return (self.learned_photos[:, :, 0::2] - self.learned_photos[:, :, 1::2]).mean(axis=3)


def plan_indices(session: CaptureSession) -> PlanIndices:
    """The capture's plan layout (twin.capture.plan.indices_of), its faults as ExtractionError."""
    try:
        return indices_of(session)
    except ValueError as e:
        raise ExtractionError(str(e)) from None


def capture_patterns(session: CaptureSession, rig, names) -> np.ndarray:
    """(len(names), L, 3) float32 relative drive of the named frames in the capture's own patterns (what the
    LEDs really showed), checked against the rig."""
    from twin.capture.patterns import PatternError

    try:
        pats = session.patterns()
        pats.check_rig(rig)
    except PatternError as e:
        raise ExtractionError(f"{session.dir}: {e}") from None
    index = {n: k for k, n in enumerate(pats.names)}
    missing = [n for n in names if n not in index]
    if missing:
        raise ExtractionError(f"{session.dir}: its patterns lack frames {missing[:3]}{'...' if len(missing) > 3 else ''}")
    return pats.weights[[index[n] for n in names]].astype(np.float32)


def calibration_of(camera, falloff=None) -> tuple[np.ndarray, np.ndarray]:
    """(flat field (H, W, 1), colour matrix (3, 3)) of a camera, with the rig's per-pixel `falloff` map for it
    if any (`Rig.flat_fields`): computed once per camera, used per photo."""
    from twin.camera.correction import colour_matrix, flat_field

    return flat_field(camera, falloff)[..., None], colour_matrix(camera)


def corrected(img: np.ndarray, camera, calibration=None) -> np.ndarray:
    """Step 1: flat field and colour matrix (`calibration_of(camera)` unless given), camera RGB -> LED-RGB
    radiance, clamped at >= 0 (reference §6.3 step 6: read noise makes dark pixels slightly negative; no
    light is)."""
    from twin.camera.correction import apply_colour_matrix

    if img.shape != (camera.height, camera.width, 3):
        raise ExtractionError(f"photo of camera {camera.name!r} is {img.shape}, the rig says "
                              f"({camera.height}, {camera.width}, 3)")
    flat, C = calibration if calibration is not None else calibration_of(camera)
    return np.maximum(apply_colour_matrix(img * flat, C), 0.0)


def detect_sample_size(session: CaptureSession, rig) -> float:
    """Side (mm) of the largest square centred on the plane origin inside the region where the sample blocks
    the bottom light (photo 128 against 130, primary camera), before the reference's 6.5% shrink."""
    cam = rig.camera(next(iter(rig.cameras)))
    ix = plan_indices(session)
    lit = session.photo(ix.empty_bottom, 0).mean(axis=2)
    sample = session.photo(ix.bottom, 0).mean(axis=2)
    ok = lit > LIT_FRACTION * lit.max()
    under = ok & (sample < SAMPLE_RATIO * lit)
    if under.sum() < MIN_SAMPLE_PIXELS:
        raise ExtractionError(f"{session.dir}: no opaque sample found in the bottom-lit photos ({int(under.sum())} "
                              "pixels block the light); give the sample size explicitly (--size-mm)")
    ys, xs = np.nonzero(under)
    p = cam.plane_points(np.stack([xs, ys], axis=1).astype(np.float64), rig.sample.origin, rig.sample.normal)
    p -= np.asarray(rig.sample.origin)
    u, v = p @ np.asarray(rig.sample.x_axis), p @ np.asarray(rig.sample.y_axis)
    lo_u, hi_u = np.percentile(u, [0.5, 99.5])  # robust to single noisy pixels
    lo_v, hi_v = np.percentile(v, [0.5, 99.5])
    half = min(-lo_u, hi_u, -lo_v, hi_v)
    if half <= 0:
        raise ExtractionError(f"{session.dir}: the sample region does not contain the plane origin; give the sample "
                              "size explicitly (--size-mm)")
    return 2.0 * half


def texture_grid(session: CaptureSession, rig, resolution: int, size_mm: float | None = None) -> TextureGrid:
    """The reconstruction's texture grid: `size_mm` when given, else the detected sample square shrunk by
    GRID_SHRINK of its extent on every side (reference §6.1)."""
    if size_mm is None:
        size_mm = detect_sample_size(session, rig) * (1.0 - 2.0 * GRID_SHRINK)
    return TextureGrid(int(resolution), float(size_mm))


def _pixel_steps(uv: np.ndarray, shape) -> np.ndarray:
    """The finite pixel distances between adjacent texels (both grid axes) of one view."""
    g = uv.reshape(*shape, 2)
    steps = np.concatenate([np.linalg.norm(np.diff(g, axis=a), axis=-1).ravel() for a in (0, 1)])
    return steps[np.isfinite(steps)]


def _texel_jacobians(uv: np.ndarray, shape) -> np.ndarray:
    """(n, 2, 2) each texel's J: its pixel steps (image x, y rows) along the grid's columns and rows (columns of J),
    central differences inside the grid, one-sided on its border; NaN where a neighbour's pixel is unknown."""
    g = uv.reshape(*shape, 2).astype(np.float64)
    along_cols, along_rows = (np.gradient(g, axis=a) for a in (1, 0))
    return np.stack([along_cols, along_rows], axis=-1).reshape(-1, 2, 2)


def _cell_widths(uv: np.ndarray, shape) -> np.ndarray:
    """Step 2, "cell": each texel's odd box widths (kx, ky) (n, 2), (0, 0) (no filter) where both are 1. With the
    lookup's pixel, the photosite centres read lie within h = k / 2 + 1/2 of the texel centre, and none is more than
    half a pixel outside the texel's cell when m_r0 k_x / 2 + m_r1 k_y / 2 <= 1/2 for both rows r of m = |J^-1|, J
    the texel's own pixel steps along the grid's columns and rows (a pixel offset p is J^-1 p in texel units). Per
    texel, so that a perspective view's larger cells (the near side of a tilted camera's field) are read whole too."""
    jac = _texel_jacobians(uv, shape)
    ok = np.isfinite(jac).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.nan_to_num(jac))) > 1e-12)
    m = np.ones((len(jac), 2, 2))  # unknown texels: any width > 1 fails, so none
    m[ok] = np.abs(np.linalg.inv(jac[ok]))  # rows: the grid axes; columns: the image axes x, y

    def fits(k):
        return (m[:, :, 0] * k[:, :1] / 2 + m[:, :, 1] * k[:, 1:] / 2 <= 0.5 + CELL_SLACK).all(axis=1)

    # each axis alone, then the wider shrunk until both fit together (a grid turned in the image)
    k = np.maximum(1, 2 * np.floor((1.0 + 2 * CELL_SLACK) / np.maximum(m.max(axis=1), 1e-12) / 2 - 0.5) + 1)
    k = k.astype(np.int64)
    while True:
        todo = ~fits(k) & (k.max(axis=1) > 1)
        if not todo.any():
            break
        kx, ky = k[todo, 0], k[todo, 1]  # the wider first, both alike when equal (no favoured axis)
        k[todo] = np.stack([np.maximum(1, kx - 2 * (kx >= ky)), np.maximum(1, ky - 2 * (ky >= kx))], axis=1)
    k[(k == 1).all(axis=1) | ~fits(k)] = 0
    return k


def _cell_points(jac: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Step 2, "cell" where no box fits: each texel's midpoint counts (m_c, m_r) (n, 2) along the grid's columns and
    rows from its pixel steps `jac` (_texel_jacobians), m = ceil of its step that way, where its widths are (0, 0) and
    a step is over MIDPOINT_STEP px; (1, 1) (the centre alone) elsewhere and where a step is unknown."""
    steps = np.linalg.norm(jac, axis=1)  # (n, 2): along the grid's columns, rows
    known = np.isfinite(steps).all(axis=1)
    m = np.ones((len(jac), 2), np.int64)
    on = known & (widths == 0).all(axis=1) & (np.nan_to_num(steps).max(axis=1) > MIDPOINT_STEP)
    m[on] = np.ceil(steps[on]).astype(np.int64)
    return m


def _midpoints(m) -> np.ndarray:
    """(m_c m_r, 2) the midpoints of an m_c x m_r split of a cell, in texel units (along its columns, rows) from its
    centre."""
    a = (np.arange(m[0]) + 0.5) / m[0] - 0.5
    b = (np.arange(m[1]) + 0.5) / m[1] - 0.5
    return np.stack(np.meshgrid(a, b), axis=-1).reshape(-1, 2)


def _gaussian_width(uv: np.ndarray, shape) -> np.ndarray:
    """Step 2, "gaussian" (reference §6.1 step 4): every texel's odd width 2 ceil(d/2 + 1) - 1 from the view's
    largest step d; 0 (no blur) when texels are under 1.5 px."""
    steps = _pixel_steps(uv, shape)
    d = float(steps.max()) if steps.size else 0.0
    k = 0 if d <= 1.5 else 2 * math.ceil(d / 2 + 1) - 1
    return np.full((len(uv), 2), k, np.int64)


def _box(img: np.ndarray, k: tuple[int, int]) -> np.ndarray:
    import cv2

    return cv2.blur(img, k, borderType=cv2.BORDER_REFLECT)


def _gaussian(img: np.ndarray, k: tuple[int, int]) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, k, 0, borderType=cv2.BORDER_REFLECT)


# step 2's methods: (each texel's filter widths (n, 2) (kx, ky) from a view's texel pixels (uv, grid shape), the
# filter) (colour-science style dispatch)
FOOTPRINTS = {"point": (lambda uv, shape: np.zeros((len(uv), 2), np.int64), None), "cell": (_cell_widths, _box),
              "gaussian": (_gaussian_width, _gaussian)}


def _taps(shape, uv: np.ndarray) -> tuple:
    """The bilinear taps (reconstruction.stages.alignment.bilinear_taps) of the points uv (N, 2) in an image of `shape`:
    computed once per view, as every photo of a view is sampled at the same points (ours: a photo
    sampled at 1024^2 texels then skips the taps' share of its time; docs/performance.md)."""
    from reconstruction.stages.alignment import bilinear_taps

    return bilinear_taps(shape, uv[:, 0], uv[:, 1])


def _reader(shape, uv: np.ndarray, widths: np.ndarray, grid_shape=None) -> list:
    """How a view's photos are read at the points uv (N, 2) with per-point filter widths (N, 2) (a FOOTPRINTS width
    function's): one (points, taps, (kx, ky), window, s) per distinct width, computed once per view (_taps). A filtered
    group is read from the window of the photo its boxes reach (its points' bounds, half a box and the lookup's pixel
    more), which holds the same filtered values there as the whole photo: a paper-rig sample fills ~5% of a photo.
    With the texels' `grid_shape`, "cell"'s texels without a box are read at their cells' s midpoints
    (_cell_points): their taps are the midpoints', uv + J (a, b) with J the texel's own pixel steps."""
    H, W = shape[:2]
    jac = None if grid_shape is None else _texel_jacobians(uv, grid_shape)
    points = np.ones_like(widths) if jac is None else _cell_points(jac, widths)
    groups = []
    for row in np.unique(np.concatenate([widths, points], axis=1), axis=0):
        k, m = row[:2], row[2:]
        idx = np.flatnonzero((widths == k).all(axis=1) & (points == m).all(axis=1))
        p = uv[idx]
        if m.prod() > 1:
            p = (p[:, None, :] + np.einsum("nij,sj->nsi", np.nan_to_num(jac[idx]), _midpoints(m))).reshape(-1, 2)
        known = p[np.isfinite(p).all(axis=1)]
        y0, y1, x0, x1 = 0, H, 0, W
        if k.max() > 1 and len(known):
            mx, my = int(k[0]) // 2 + 2, int(k[1]) // 2 + 2
            x0, x1 = max(0, int(np.floor(known[:, 0].min())) - mx), min(W, int(np.ceil(known[:, 0].max())) + mx + 1)
            y0, y1 = max(0, int(np.floor(known[:, 1].min())) - my), min(H, int(np.ceil(known[:, 1].max())) + my + 1)
        groups.append((idx, _taps((y1 - y0, x1 - x0), p - np.array([x0, y0], np.float64)), (int(k[0]), int(k[1])),
                       (slice(y0, y1), slice(x0, x1)), int(m.prod())))
    return groups


def _sample(img: np.ndarray, reader: list, footprint: str = "point") -> np.ndarray:
    """Steps 2-3: (N, C) float32 bilinear values of img (H, W, C) at the points of `reader` (_reader), NaN outside
    the image, each after the footprint's filter of its widths (kx, ky; none when both <= 1) (exact weights:
    cv2.remap would quantise the sub-pixel position to 1/32 px)."""
    from reconstruction.stages.alignment import bilinear_at

    out = np.empty((sum(len(idx) for idx, *_ in reader), *img.shape[2:]), np.float32)
    for idx, taps, k, window, s in reader:
        part = img[window]
        if max(k) > 1:
            part = FOOTPRINTS[footprint][1](np.ascontiguousarray(part), k)
        out[idx] = bilinear_at(part, taps).reshape(len(idx), s, *img.shape[2:]).mean(axis=1)
    return out


def secondary_pixels(uv_primary: np.ndarray, alignment) -> np.ndarray:
    """Step 4: each texel's secondary pixel, the alignment map (H0, W0, 2) sampled bilinearly at its primary
    pixel (NaN where the map is unknown)."""
    return _sample(alignment.map, _reader(alignment.map.shape, uv_primary, np.zeros((len(uv_primary), 2), np.int64)))


def extract(session: CaptureSession, rig, grid: TextureGrid, alignment, *, footprint: str = "cell",
            demosaic: str = "bilinear", progress: bool = False) -> Measurements:
    """Per-texel measurements of a capture (module docstring; step 2's method: `footprint`, one of FOOTPRINTS;
    step 0's `demosaic`, one of twin.camera.bayer.DEMOSAICS)."""
    from twin.camera.bayer import DEMOSAICS, mosaic
    from twin.camera.bayer import demosaic as demosaiced

    from reconstruction.network.data import LUMITEXEL_SCALE

    if footprint not in FOOTPRINTS:
        raise ExtractionError(f"footprint must be one of {tuple(FOOTPRINTS)}, got {footprint!r}")
    if demosaic not in DEMOSAICS:
        raise ExtractionError(f"demosaic must be one of {tuple(DEMOSAICS)}, got {demosaic!r}")
    if session.rig_digest != rig.digest():
        raise ExtractionError(f"{session.dir} was captured with another rig (digest {session.rig_digest}) than "
                              f"{rig.name!r} ({rig.digest()})")
    cams = [rig.camera(c) for c in rig.cameras]
    if len(cams) != 2:
        raise ExtractionError(f"the pipeline needs a two-camera rig, {rig.name!r} has {len(cams)}")
    pos = grid.positions(rig)
    uv0, _ = cams[0].project(pos)
    uv1 = secondary_pixels(uv0, alignment)
    k0, k1 = (FOOTPRINTS[footprint][0](uv, grid.shape) for uv in (uv0, uv1))
    scale = np.float32(LUMITEXEL_SCALE)

    calibrations = [calibration_of(c, rig.flat_fields.get(c.name)) for c in cams]

    def photo(k, c):
        img = session.photo(k, c)
        if demosaic != "bilinear":  # step 0: the HDR merge's bilinear demosaic keeps each photosite's own colour
            bayer = cams[c].sensor.bayer
            img = demosaiced(mosaic(img, bayer), bayer, method=demosaic).astype(np.float32)
        return corrected(img, cams[c], calibrations[c])

    from twin.progress import progress_bar

    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    ix = plan_indices(session)
    weights = capture_patterns(session, rig, [f"line_{j:02d}" for j in range(len(ix.lines))])[:, upper, :]
    shown = session.shown_patterns(0)
    learned_weights = capture_patterns(session, rig, [shown[k] for k in ix.learned])[:, upper, :]

    views = [_reader((cam.height, cam.width), uv, k, grid.shape if footprint == "cell" else None)
             for cam, uv, k in zip(cams, (uv0, uv1), (k0, k1))]

    def sampled(job):
        k, c = job
        return _sample(photo(k, c), views[c], footprint)

    # the photos are read, checked, corrected and sampled by a pool of threads (EXR decoding, sha256 and numpy
    # release the GIL): a paper-rig capture is 196 photos of 74 MB, each a long read on one core
    jobs = [(k, c) for c in (0, 1) for k in ix.learned] + [(k, 0) for k in ix.lines] + [(ix.bottom, 0), (ix.empty_bottom, 0)]
    with ThreadPoolExecutor(max_workers=min(READERS, os.cpu_count() or 1)) as pool:
        values = dict(zip(jobs, progress_bar(pool.map(sampled, jobs), total=len(jobs), desc="extract",
                                             enabled=progress)))
    n = len(pos)
    learned_photos = np.empty((n, 2, len(ix.learned), 3), np.float32)
    for c in (0, 1):
        for k in ix.learned:
            learned_photos[:, c, k] = values[k, c] * scale
    lines = np.empty((n, len(ix.lines), 3), np.float32)
    for j, k in enumerate(ix.lines):
        lines[:, j] = values[k, 0] * scale
    bottom = values[ix.bottom, 0].mean(axis=1)
    empty = values[ix.empty_bottom, 0].mean(axis=1)
    transparency = np.clip(bottom / (empty + 1e-6), 0.0, 1.0).astype(np.float32)  # reference §6.3
    valid = (np.isfinite(learned_photos).all(axis=(1, 2, 3)) & np.isfinite(lines).all(axis=(1, 2))
             & np.isfinite(transparency))
    return Measurements(grid, lines, weights, transparency, valid, uv0.astype(np.float32), uv1.astype(np.float32),
                        learned_photos, learned_weights)
