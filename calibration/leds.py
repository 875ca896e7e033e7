"""LED positions, normals, angular profiles Psi and RGB intensities from photographs of a diffuse
plate (twin.targets.diffuse.DiffusePlate) lit by one LED at a time.

    samples = plate_samples(photo, saturated, camera, rig, plate)          # per photo: plate points, radiance
    fit = calibrate_leds(rig, {led: [samples at height 0, samples at height h]})
    rig_calibrated = fit.apply(rig)
    score_leds(rig_calibrated, truth, fit.index)                              # against the twin's truth
    rig, report = calibrate_leds_from_plate(nominal, truth, frames, seed)     # all of it in the twin

Physics (paper Eq. 1 with a Lambertian plate of albedo rho): the LED-RGB radiance at plate point x under LED l,
    L_c(x) = I_c (cos theta_e)^p (rho / pi) cos theta_i / r^2,
r = |p_l - x| (in metres: the physical convention's unit, twin.optics.inputs), cos theta_e = (x - p_l).n_l / r
(the emission angle from the LED's normal; the "cosine" profile family Psi cos = cos^p, twin.optics.emitter),
cos theta_i = (p_l - x).z / r (the plate's normal z).

The procedure, per LED (photos of the plate at two heights, twin.targets.diffuse says why):
1. each photo through the camera's calibration (flat field, colour matrix: reconstruction's first step, done
   here with twin.camera.correction) to LED-RGB radiance, averaged over blocks of `block` x `block` pixels
   wholly on the plate, blocks below 5% of the photo's brightest, or saturated, dropped, and the blocks the
   holder frame may shadow from the LED (`_shadowed`: the frame's lip, 1.5 mm on the mini rig, shades ~15 mm
   of the plate from an LED 6 degrees above it); the model is averaged over each block's pixels as well
   (exact, where a block's centre would be off by the falloff's curvature);
2. in log space the intensities drop out in closed form (log I_c = the mean of log L_c - log g), so only the
   geometry is searched: position (3), normal (2 numbers in the nominal normal's tangent plane) and the
   profile exponent p, per LED; Levenberg-Marquardt (scipy.optimize.least_squares) from the nominal values,
   residuals weighted by sqrt(L / L_max) (shot noise: relative noise ~ 1/sqrt(signal)), robust (soft L1).
   Why the exponent per LED: the plate's pattern fixes the LED's distance only weakly, so a profile shared by
   a board moves every LED whose own profile differs: measured on the mini rig (seed 3, noise-free photos),
   a board's median exponent against the LEDs' own (spread 2%) put the positions 0.39 mm (median) and up to
   1.3 mm off; the exponent per LED recovers them exactly, and is determined to 0.003 with 0.2% noise.
LEDs that light too little of the plate (fewer than `MIN_BLOCKS` usable blocks), or usefully at one height
only (the lowest side LEDs, level with the lifted plate), keep their nominal values and are listed (`skipped`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["LEDCalibrationError", "LEDFit", "PlateView", "plate_view", "plate_samples", "calibrate_leds", "crest_seen",
           "score_leds", "calibrate_leds_from_plate", "LED_GOALS", "PLATE_HEIGHTS_MM", "MIN_BLOCKS"]

MIN_BLOCKS = 40  # usable blocks over both heights below which an LED is not calibrated
DARK_FRACTION = 0.05  # blocks below this fraction of the photo's brightest block are dropped
GRAZING_FRACTION = 0.05  # an LED's photo whose brightest block is below this fraction of its brightest is dropped
# a photo whose LED is (nominally) less than this far above the plate is dropped: at grazing light the plate's
# pattern is the cosine's steep slope, whose value hangs on the LED's height to a fraction of a millimetre
# (measured, mini rig seed 3: two LEDs 3-5 mm above the lifted plate came out 56 and 105 mm off)
MIN_ELEVATION_DEG = 5.0
LENGTH_SCALE = 1e-3  # mm -> m: the physical convention's unit of r (twin.optics.inputs.CONVENTIONS)


class LEDCalibrationError(ValueError):
    """Bad LED-calibration photos (wrong size, not finite, dark, mostly saturated): names the photo."""


@dataclass
class LEDFit:
    """The calibrated upper LEDs: index (K,) into the rig's LEDs, positions (K, 3) mm, normals (K, 3),
    exponent (K,) of the cosine profile, intensity (K, 3); `skipped`: LEDs kept at their nominal values;
    per-LED fit RMS in log radiance."""

    index: np.ndarray
    positions: np.ndarray
    normals: np.ndarray
    exponent: np.ndarray
    intensity: np.ndarray
    rms_log: np.ndarray
    skipped: list = field(default_factory=list)

    def apply(self, rig):
        """The rig with these LEDs' values (the others as they were)."""
        leds = rig.leds
        pos, nrm, prof, inten = (leds.positions.copy(), leds.normals.copy(), leds.profile.copy(),
                                 leds.intensity.copy())
        pos[self.index], nrm[self.index], inten[self.index] = self.positions, self.normals, self.intensity
        prof[self.index, 0] = self.exponent
        return replace(rig, leds=replace(leds, positions=pos, normals=nrm, profile=prof, intensity=inten))


@dataclass
class PlateView:
    """What one camera sees of one plate, the same for every photo of it (`plate_view`): the camera, the block
    size, which blocks lie wholly on the plate (Hb, Wb), the plate points of their pixels (M, B, 3) and the
    camera's calibration (flat field (H, W), colour matrix)."""

    camera: object
    block: int
    on: np.ndarray
    points: np.ndarray
    calibration: tuple


def plate_view(camera, rig, plate, block: int = 4) -> PlateView:
    """The photo-independent part of step 1 for `camera` and `plate` (the rig's calibration of the camera)."""
    from scipy import ndimage

    from twin.camera.correction import colour_matrix, flat_field

    H, W = (camera.height // block) * block, (camera.width // block) * block
    v, u = np.mgrid[0:H, 0:W]
    uv = np.stack([u, v], -1).astype(np.float64)
    _, on = plate.points(rig, camera, uv.reshape(-1, 2))
    # 2 px inside the plate's edge: the bilinear demosaic (twin.camera.bayer) mixes a pixel's neighbours, and
    # next to the edge those are off the plate (measured: the R and B of the edge blocks off by up to 50%)
    on = _blocks(ndimage.binary_erosion(on.reshape(H, W), iterations=2), block).all(axis=2)
    X, _ = plate.points(rig, camera, _blocks(uv, block)[on].reshape(-1, 2))
    return PlateView(camera, block, on, X.reshape(int(on.sum()), block * block, 3),
                     (flat_field(camera, rig.flat_fields.get(camera.name)), colour_matrix(camera)))


def _blocks(a: np.ndarray, block: int) -> np.ndarray:
    """(Hb, Wb, block^2, ...) the block x block tiles of a (H, W, ...), H and W multiples of block."""
    H, W = a.shape[:2]
    return a.reshape(H // block, block, W // block, block, *a.shape[2:]).swapaxes(1, 2).reshape(
        H // block, W // block, block * block, *a.shape[2:])


def plate_samples(photo, saturated, camera, rig, plate, *, block: int = 4, label: str = "photo",
                  view: PlateView | None = None):
    """(X (M, B, 3) mm, L (M, 3)) of one HDR photo (H, W, 3) of `plate` by `camera` (step 1): the plate points
    of the B = block^2 pixels of each block wholly on the plate, and the block's mean LED-RGB radiance.
    `saturated` (H, W) marks photosites saturated in any frame. `view`: plate_view(camera, rig, plate, block),
    made once for the many photos of one camera and plate (else made here)."""
    from twin.camera.correction import apply_colour_matrix

    from .photos import checked_photo

    photo = checked_photo(photo, camera, label, LEDCalibrationError)
    view = view or plate_view(camera, rig, plate, block)
    b = view.block
    flat, C = view.calibration
    H, W = view.on.shape[0] * b, view.on.shape[1] * b
    img = apply_colour_matrix(photo[:H, :W] * flat[:H, :W, None], C)
    bad = np.zeros((H, W), bool) if saturated is None else np.asarray(saturated, bool)[:H, :W]
    hit = _blocks(bad, b).any(axis=2)[view.on]
    if hit.mean() > 0.5:
        raise LEDCalibrationError(f"{label}: more than half of the plate is saturated; expose shorter")
    L = _blocks(img, b).mean(axis=2)[view.on]
    grey = L.mean(axis=1)
    keep = ~hit & (grey > DARK_FRACTION * grey[~hit].max() if (~hit).any() and grey[~hit].max() > 0 else False)
    return view.points[keep], L[keep]


def _frame(n0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n0, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n0, e1)


def _log_geometry(p, n, k, X, z, albedo):
    """log of the mean over each block's points X (M, B, 3) of (cos theta_e)^k (albedo / pi) cos theta_i / r^2
    (module docstring), the cosines floored at 1e-4 (a point a trial geometry leaves unlit gets a large, smooth
    residual instead of -inf)."""
    d = X - p
    r = np.linalg.norm(d, axis=2)
    ce = np.maximum((d @ n) / r, 1e-4)
    ci = np.maximum(-(d @ z) / r, 1e-4)
    return np.log((ce ** k * ci / (r * LENGTH_SCALE) ** 2).mean(axis=1) * (albedo / math.pi))


def _elevation_deg(p, X, origin, z) -> float:
    """The LED's elevation (deg) over the plate of the points X (M, B, 3), seen from the plate's centre
    (origin + its height along z)."""
    c = origin + float(np.mean((X - origin) @ z)) * z
    d = p - c
    return math.degrees(math.asin(float(d @ z) / float(np.linalg.norm(d))))


def _shadowed(rig, p, X, margin_mm: float = 2.0) -> np.ndarray:
    """(M,) True for the blocks X (M, B, 3) any of whose points the holder frame (rig.frame: a ring of height
    h around the sample window) may hide from an LED at p: the ray to the LED is still below h + margin when
    it leaves the window shrunk by margin (the margins cover the LED's uncalibrated position)."""
    frame = getattr(rig, "frame", None)
    if frame is None:
        return np.zeros(len(X), bool)
    o, z = np.asarray(rig.sample.origin, np.float64), np.asarray(rig.sample.normal, np.float64)
    ax, ay = np.asarray(rig.sample.x_axis, np.float64), np.asarray(rig.sample.y_axis, np.float64)
    top = frame.height + margin_mm
    hx, hp = (X - o) @ z, float((p - o) @ z)
    if hp <= top:
        return np.ones(len(X), bool)
    t = np.clip((top - hx) / (hp - hx), 0.0, None)  # 0 for points already above the lip
    Q = X + t[..., None] * (p - X) - o
    half = frame.inner_size / 2 - margin_mm
    out = (np.abs(Q @ ax) > half) | (np.abs(Q @ ay) > half)
    return (out & (hx < top)).any(axis=1)


def _fit_one(X, L, z, albedo, p0, n0, k0):
    from scipy.optimize import least_squares

    e1, e2 = _frame(n0)
    logL = np.log(np.maximum(L, 1e-30))
    w = np.sqrt(L.mean(axis=1) / L.mean(axis=1).max())[:, None]

    def unpack(x):
        n = n0 + x[3] * e1 + x[4] * e2
        return p0 + x[:3], n / np.linalg.norm(n), x[5]

    def residuals(x):
        p, n, k = unpack(x)
        g = _log_geometry(p, n, k, X, z, albedo)[:, None]
        logI = (logL - g).mean(axis=0)
        return ((logL - g - logI) * w).ravel()

    x0 = np.zeros(6)
    x0[5] = k0
    sol = least_squares(residuals, x0, method="trf", loss="soft_l1", f_scale=0.02, x_scale="jac")
    p, n, k = unpack(sol.x)
    g = _log_geometry(p, n, k, X, z, albedo)[:, None]
    logI = (logL - g).mean(axis=0)
    rms = float(np.sqrt(np.mean((logL - g - logI) ** 2)))
    return p, n, float(k), np.exp(logI), rms


def crest_seen(rig, leds, half_mm: float) -> np.ndarray:
    """(K,) True for the bottom LEDs `leds` whose light's crest the photos of a square of half-side `half_mm` on
    the sample plane see: the LED's foot on the plane within that square grown by the LED's depth below it (its
    glow falls to ~1/3 at a depth's distance). Elsewhere only the glow's tail is seen, and a LED's distance and
    profile exponent trade off along it (measured, mini rig, 64 frames, both cameras: position 0.02-0.08 mm
    within, 0.4-2.6 mm beyond)."""
    o, z = np.asarray(rig.sample.origin, np.float64), np.asarray(rig.sample.normal, np.float64)
    ax, ay = np.asarray(rig.sample.x_axis, np.float64), np.asarray(rig.sample.y_axis, np.float64)
    d = rig.leds.positions[np.asarray(leds)] - o
    reach = half_mm + np.abs(d @ z)
    return (np.abs(d @ ax) <= reach) & (np.abs(d @ ay) <= reach)


def calibrate_leds(rig, samples: dict, albedo: float, bottom: bool = False) -> LEDFit:
    """The LEDs of `samples` ({led index: [(X, L) per photo]}, plate_samples of the photos of the plate of
    `albedo` lit by that LED alone) calibrated as the module docstring says, starting from `rig`'s values.
    bottom: bottom LEDs photographed through the empty holder's acrylic (DiffusePlate(transparency=1)): the
    same model with the plate's normal facing down and `albedo` the acrylic's transmission (the forward
    model's Lambertian transmission, twin.optics.lumitexel), one height (the acrylic cannot be lifted: the
    glow's width and tail fix the distance, tested noise-free), no frame shadows (the frame stands above)."""
    leds = rig.leds
    if rig.led_profile != "cosine":
        raise LEDCalibrationError(f"the LED calibration fits the cosine profile family; rig {rig.name!r} uses "
                                  f"{rig.led_profile!r}")
    z = np.asarray(rig.sample.normal, np.float64) * (-1.0 if bottom else 1.0)
    origin = np.asarray(rig.sample.origin, np.float64)
    data, skipped = {}, []
    for led, photos in samples.items():
        # a photo in which the LED only grazes the plate (the lifted plate level with a side LED) carries little
        # shape, and the grazing cosine's steep dependence on the LED's height: dropped
        top = max((float(v.mean(axis=1).max()) for _, v in photos if len(v)), default=0.0)
        photos = [(x, v) for x, v in photos if len(v) and v.mean(axis=1).max() >= GRAZING_FRACTION * top
                  and _elevation_deg(leds.positions[led], x, origin, z) >= MIN_ELEVATION_DEG]
        if not bottom:
            photos = [(x[~s], v[~s]) for x, v in photos for s in [_shadowed(rig, leds.positions[led], x)]]
        heights = {round(float((x[0, 0] - origin) @ z), 1) for x, _ in photos if len(x)}
        n = sum(len(x) for x, _ in photos)
        # an upper LED's distance needs both heights (measured: the lowest LEDs of the mini rig, lit usefully at
        # one height only, came out up to 100 mm off)
        if len(heights) < (1 if bottom else 2) or n < MIN_BLOCKS:
            skipped.append(int(led))
            continue
        data[led] = (np.concatenate([x for x, _ in photos]), np.concatenate([v for _, v in photos]))
    index = np.array(sorted(data), dtype=np.int64)
    if index.size == 0:
        raise LEDCalibrationError("no LED lit enough of the plate to be calibrated")
    out = [_fit_one(*data[led], z, albedo, leds.positions[led], leds.normals[led], float(leds.profile[led, 0]))
           for led in index]
    return LEDFit(index, np.array([o[0] for o in out]), np.array([o[1] for o in out]), np.array([o[2] for o in out]),
                  np.array([o[3] for o in out]), np.array([o[4] for o in out]), skipped)


def _emission(rig, leds, X) -> np.ndarray:
    """(K, M, 3) radiant intensity I_c (cos theta_e)^p of the LEDs towards the points X (M, 3)."""
    P, N = rig.leds.positions[leds], rig.leds.normals[leds]
    d = X[None] - P[:, None]
    ce = np.clip(np.einsum("kmi,ki->km", d, N) / np.linalg.norm(d, axis=2), 0.0, None)
    return rig.leds.intensity[leds][:, None, :] * (ce ** rig.leds.profile[leds, 0][:, None])[..., None]


def score_leds(rig, truth, leds=None, grid: int = 9) -> dict:
    """`rig`'s upper LEDs (or `leds`) against the `truth`: position error (mm), normal error (deg), and over
    the directions in which each LED lights the sample (a grid x grid lattice over the sample square, 90% of
    max_size): the profile's shape (the emission ratio calibrated / true over the lattice, relative to its
    value at the centre: LED_GOALS' "Psi within 2% over the used angles"), the intensity at the centre, and
    the whole emission I Psi cos towards the lattice (what a capture's photo depends on). Each as median, p90
    and max over the LEDs, in %."""
    idx = np.flatnonzero(~truth.is_bottom) if leds is None else np.asarray(leds)
    d = np.linalg.norm(rig.leds.positions[idx] - truth.leds.positions[idx], axis=1)
    cosang = np.clip(np.einsum("ij,ij->i", rig.leds.normals[idx], truth.leds.normals[idx]), -1, 1)
    s = (np.arange(grid) / (grid - 1) - 0.5) * 0.9 * truth.sample.max_size
    o, ax, ay = (np.asarray(v, np.float64) for v in (truth.sample.origin, truth.sample.x_axis, truth.sample.y_axis))
    X = (o + s[:, None, None] * ax + s[None, :, None] * ay).reshape(-1, 3)
    centre = (grid * grid) // 2
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = _emission(rig, idx, X) / _emission(truth, idx, X)  # (K, M, 3)
    lit = np.isfinite(ratio).all(axis=2) & (ratio > 0).all(axis=2)
    shape = np.where(lit[..., None], np.abs(ratio / ratio[:, centre:centre + 1] - 1), np.nan)
    whole = np.where(lit[..., None], np.abs(ratio - 1), np.nan)

    def stats(v):
        v = np.asarray(v, np.float64)
        v = v[np.isfinite(v)]
        return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max())}

    return {"leds": int(idx.size), "position_mm": stats(d), "normal_deg": stats(np.degrees(np.arccos(cosang))),
            "profile_shape_pct": stats(100 * np.nanmax(shape, axis=(1, 2))),
            "intensity_pct": stats(100 * np.abs(ratio[:, centre] - 1).max(axis=1)),
            "emission_pct": stats(100 * np.nanmax(whole, axis=(1, 2)))}


# the LEDs' goals (docs/calibration.md): each LED's position within 0.5 mm, its profile Psi within 2% (medians)
LED_GOALS = {"position_mm_median": 0.5, "profile_shape_pct_median": 2.0}
PLATE_HEIGHTS_MM = (0.0, 40.0)  # the diffuse plate on the sample plane, then on 40 mm spacers


def calibrate_leds_from_plate(nominal, truth, frames: int, seed: int, step: int = 1, binning: int = 1,
                              progress: bool = True, bottom: bool = False) -> tuple:
    """Photograph a diffuse plate (twin.targets.diffuse) with both cameras of the TRUE rig, at the two heights
    PLATE_HEIGHTS_MM, each upper LED alone (every `step`-th: a quicker run; the others keep their nominal
    values), `frames` frames per photo, with the cameras binned `binning` x `binning` (the LEDs' light over the
    plate is smooth; the paper rig's 6 MP photos need not be read whole), and calibrate the LEDs from those photos
    alone (calibration.leds; the cameras, their flat fields and colour matrices as the nominal rig has them:
    calibrated beforehand). bottom: the bottom LEDs instead, each alone, through the empty holder's acrylic
    (one height); those whose light's crest the photos do not see (calibration.leds.crest_seen) keep their
    nominal values. Returns (the nominal rig with the calibrated LEDs, a report scored against the truth, with
    the nominal rig's own errors beside it).

    nominal, truth are Rigs (mm); `seed` draws the photos' noise. Calibrated per LED: position (3,) mm, unit
    normal (3,), intensity (3,) RGB and the cosine profile's exponent (profile[0]; twin.optics.emitter). The
    report, {"leds": ...} (or {"bottom": ...}): photos, frames_per_photo, led_step, binning, camera_pixels
    ({camera: [W, H]} binned, pixels), plate_heights_mm, calibrated and skipped LEDs, fit_rms_log (median RMS of
    the fit in log radiance), then score_leds' figures, each {median, p90, max} over the LEDs: position_mm (mm),
    normal_deg (degrees), profile_shape_pct, intensity_pct and emission_pct (%); nominal_error (the same of the
    nominal rig), goals (LED_GOALS) and passed."""
    import sys

    from twin.camera.hdr import still_photo
    from twin.targets.diffuse import DiffusePlate

    from .photos import LED_BATCH, binned_rig

    chosen = np.flatnonzero(truth.is_bottom if bottom else ~truth.is_bottom)[::step]
    plates = [DiffusePlate(transparency=1.0)] if bottom else [DiffusePlate(height_mm=h) for h in PLATE_HEIGHTS_MM]
    beyond = []
    if bottom:
        seen_crest = crest_seen(nominal, chosen, plates[0].size_mm / 2)
        chosen, beyond = chosen[seen_crest], chosen[~seen_crest].tolist()
    samples = {int(led): [] for led in chosen}
    shot = 0
    seen, known = binned_rig(truth, binning), binned_rig(nominal, binning)
    for cam_name in truth.cameras:
        cam, cal_cam = seen.camera(cam_name), known.camera(cam_name)
        for plate in plates:
            view = plate_view(cal_cam, known, plate)  # the same for every photo of this plate by this camera
            what = "the acrylic" if bottom else f"plate at {plate.height_mm:g} mm"
            for i in range(0, len(chosen), LED_BATCH):
                batch = chosen[i:i + LED_BATCH]
                for led, rad in zip(batch, plate.radiance(seen, cam_name, batch)):
                    if not rad.max() > 0:
                        continue  # the LED does not reach the plate at this height (a side LED below it)
                    photo, sat = still_photo(rad, cam, seed=seed, frames=frames, first_frame=shot * frames,
                                             camera_key=cam_name, flat_field=seen.flat_fields.get(cam_name))
                    shot += 1
                    samples[int(led)].append(plate_samples(photo, sat, cal_cam, known, plate, view=view,
                                                           label=f"{cam_name}, {what}, LED {led}"))
            if progress:
                print(f"[calibrate] {cam_name}: {what}, {len(chosen)} LEDs", file=sys.stderr, flush=True)
    albedo = nominal.bottom.acrylic_transmission if bottom else plates[0].albedo
    fit = calibrate_leds(nominal, samples, albedo, bottom=bottom)
    rig = fit.apply(nominal)
    s = score_leds(rig, truth, fit.index)
    goals = {"position_mm_median": s["position_mm"]["median"] <= LED_GOALS["position_mm_median"],
             "profile_shape_pct_median": s["profile_shape_pct"]["median"] <= LED_GOALS["profile_shape_pct_median"]}
    target = ({"target": "the empty holder's acrylic, lit from below", "crest_not_seen": beyond} if bottom else
              {"plate_heights_mm": list(PLATE_HEIGHTS_MM)})
    report = {"photos": shot, "frames_per_photo": frames, "led_step": step, "binning": binning,
              "camera_pixels": {n: [c.width, c.height] for n, c in seen.cameras.items()}, **target,
              "calibrated": int(fit.index.size), "skipped": fit.skipped, "fit_rms_log": float(np.median(fit.rms_log)),
              **s, "nominal_error": score_leds(nominal, truth, fit.index), "goals": goals,
              "passed": all(goals.values())}
    return rig, {"bottom" if bottom else "leds": report}
