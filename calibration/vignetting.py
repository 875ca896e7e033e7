"""Vignetting and flat field: a camera's light falloff from photographs of a flat-field source.

    ff = calibrate_flat_field([photo_0deg, photo_180deg], camera)   # HDR photos of the source (twin.targets.flatfield)
    ff.gain        # (H, W) relative gain of every pixel, 1 at the principal point
    ff.radial      # (a, b, c) of the rig's radial model 1 + a r^2 + b r^4 + c r^6 (Camera.sensor.vignetting)
    score_flat_field(ff, true_gain)                                  # against the twin's truth
    rig, report = calibrate_vignetting(nominal, truth, frames, seed)  # all of it in the twin, every camera

The procedure, as a lab does it (paper §5 calibrates vignetting "with a flat-field source"):
1. photos of a source of uniform radiance that fills the view, at two orientations 180 degrees apart about
   the optical axis (their mean cancels the panel's own linear gradient), each the mean of many frames at one
   exposure (shot noise ~1/sqrt(frames x electrons));
2. the grey level (mean of RGB: the falloff is achromatic; the crosstalk only tints a uniform source);
3. a Gaussian of `smooth_px` over the image, which averages the sensor's shot noise and its per-photosite
   response non-uniformity (PRNU; the camera's own shading correction handles that, as Basler's does) and
   keeps the falloff's structure: lens falloff (the whole frame), mechanical vignetting (the corners) and dust
   shadows (tens of pixels on the paper rig's sensor);
4. the radial model fitted by least squares to that map (robustly: dust shadows are outliers to it), giving
   the rig file's coefficients and the normalisation: the gain is the map over the fitted value at r = 0.
The per-pixel map is the flat field; the radial model is what the rig file holds, and says how much of the
falloff a radial model misses (the dust and an off-centre hood).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FlatField", "FlatFieldError", "calibrate_flat_field", "score_flat_field", "radial_basis",
           "calibrate_vignetting", "FLAT_FIELD_GOAL_PCT"]


class FlatFieldError(ValueError):
    """Bad flat-field photos (wrong size, not finite, dark, saturated): names the photo."""


@dataclass
class FlatField:
    gain: np.ndarray        # (H, W) float32: relative gain, the radial fit's value at the principal point = 1
    radial: tuple           # (a, b, c): the radial model 1 + a r^2 + b r^4 + c r^6 fitted to the map
    photos: int
    fit_rms_pct: float      # RMS of the map about the radial model, % (the falloff a radial model misses)

    def beyond_radial(self, camera) -> np.ndarray:
        """(H, W) float32: the map over its radial model, what a rig keeps per pixel (`Rig.flat_fields`) beside
        the camera's radial coefficients (`radial`)."""
        r2 = radial_basis(camera)
        a, b, c = self.radial
        return (self.gain / (1 + r2 * (a + r2 * (b + r2 * c)))).astype(np.float32)


def radial_basis(camera) -> np.ndarray:
    """(H, W) r^2 of the rig's radial model: squared distance from the principal point over the squared
    half-diagonal (twin.camera.sensor.vignetting_factor's definition)."""
    W, H = camera.width, camera.height
    u = np.arange(W, dtype=np.float64)[None, :] - camera.K[0, 2]
    v = np.arange(H, dtype=np.float64)[:, None] - camera.K[1, 2]
    return (u * u + v * v) / (0.25 * (W * W + H * H))


def calibrate_flat_field(photos, camera, *, saturated=None, smooth_px: float | None = None) -> FlatField:
    """The flat field of `camera` from HDR photos (H, W, 3) of a flat-field source (module docstring).
    `saturated`: the photos' saturation masks, if known; any saturated pixel is an error. `smooth_px`: the
    Gaussian's sigma; None: a quarter of a percent of the width, at least 1 px (6.7 px on the paper rig's
    2664-px photos, whose smallest modelled dust shadow has a sigma of 27 px)."""
    import cv2

    if smooth_px is None:
        smooth_px = max(1.0, 0.0025 * camera.width)
    if len(photos) < 1:
        raise FlatFieldError("flat field: no photos")
    grey = np.zeros((camera.height, camera.width))
    for k, img in enumerate(photos):
        a = np.asarray(img, np.float64)
        if a.shape != (camera.height, camera.width, 3):
            raise FlatFieldError(f"flat-field photo {k}: shape {a.shape}, camera {camera.name!r} is "
                                 f"({camera.height}, {camera.width}, 3)")
        if not np.all(np.isfinite(a)):
            raise FlatFieldError(f"flat-field photo {k}: {int((~np.isfinite(a)).sum())} values are NaN or Inf")
        if saturated is not None and np.any(saturated[k]):
            raise FlatFieldError(f"flat-field photo {k}: {int(np.sum(saturated[k]))} pixels are saturated; "
                                 "shorten the exposure")
        m = a.mean(axis=2)
        if np.percentile(m, 1) <= 0:
            raise FlatFieldError(f"flat-field photo {k}: dark (1st percentile <= 0): is the source on and in view?")
        grey += m / len(photos)
    if smooth_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), sigmaX=smooth_px, borderType=cv2.BORDER_REFLECT)
    r2 = radial_basis(camera)
    A = np.stack([np.ones_like(r2), r2, r2 ** 2, r2 ** 3], axis=-1).reshape(-1, 4)
    y = grey.ravel()
    keep = np.ones(y.size, bool)
    for _ in range(4):  # refit without the pixels far off the model (dust shadows, a hood's corner)
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        res = y / (A @ coef) - 1
        mad = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep])))
        keep = np.abs(res) <= max(3 * mad, 1e-4)
    g0 = coef[0]
    gain = grey / g0
    model = (A @ coef).reshape(grey.shape) / g0
    return FlatField(gain.astype(np.float32), tuple(float(c / g0) for c in coef[1:]), len(photos),
                     float(100 * np.sqrt(np.mean((gain / model - 1) ** 2))))


def score_flat_field(ff: FlatField, true_gain: np.ndarray, camera) -> dict:
    """Errors (%) of the per-pixel flat field and of the radial model alone against the true falloff, over the
    whole frame. A flat field is relative (its scale goes with the exposure and the LEDs' intensities), so each
    is compared up to one factor: |est / truth / median(est / truth) - 1|."""
    truth = np.asarray(true_gain, np.float64)
    if truth.shape != ff.gain.shape:
        raise FlatFieldError(f"true gain is {truth.shape}, the flat field {ff.gain.shape}")
    r2 = radial_basis(camera)
    a, b, c = ff.radial
    radial = 1 + r2 * (a + r2 * (b + r2 * c))

    def stats(est):
        ratio = est / truth
        e = 100 * np.abs(ratio / np.median(ratio) - 1)
        return {"median": float(np.median(e)), "p95": float(np.percentile(e, 95)), "p99": float(np.percentile(e, 99)),
                "max": float(e.max())}

    return {"flat_field_pct": stats(ff.gain.astype(np.float64)), "radial_model_pct": stats(radial),
            "true_falloff": [float(truth.min() / truth.max()), 1.0]}


# the flat field "within 0.5%" (docs/calibration.md), read as: 95% of the pixels within 0.5% of the true
# falloff (up to one factor)
FLAT_FIELD_GOAL_PCT = 0.5


def calibrate_vignetting(nominal, truth, frames: int, seed: int, progress: bool = True) -> tuple:
    """Photograph a flat-field source with every camera of the TRUE rig (its radial falloff and its per-pixel
    maps, twin.rig.perturb.perturb_vignetting) at 0 and 180 degrees, `frames` frames each, and calibrate each
    camera's flat field from those photos alone. Returns (the nominal rig with the fitted radial coefficients
    and the per-pixel maps beyond them, a report per camera scored against the truth).

    nominal, truth are Rigs; `seed` draws the photos' noise. The fitted model: each camera's radial falloff
    1 + a r^2 + b r^4 + c r^6 (r: the distance from the principal point over the half-diagonal, both in pixels), its
    sensor's `vignetting` (a, b, c), and the per-pixel factor beyond it, an (H, W) float32 map in the rig's
    `flat_fields` (H, W: the camera's pixels). The report per camera: photos, frames_per_photo, radial and
    true_radial (a, b, c), map_about_radial_rms_pct (%), flat_field_pct and radial_model_pct ({median, p95, p99,
    max} in %, each up to one factor, over every pixel), true_falloff ([darkest / brightest, 1]) and passed (the
    flat field's p95 within FLAT_FIELD_GOAL_PCT = 0.5%)."""
    import sys
    from dataclasses import replace

    from twin.camera.hdr import still_photo
    from twin.camera.imaging import optics_gain
    from twin.targets.flatfield import FlatFieldSource

    source = FlatFieldSource()
    cams, maps, report = {}, {}, {}
    for name, cam in truth.cameras.items():
        shots = [still_photo(source.radiance(cam, angle), cam, seed=seed, frames=frames, first_frame=i * frames,
                             camera_key=name, flat_field=truth.flat_fields.get(name))
                 for i, angle in enumerate((0, 180))]
        ff = calibrate_flat_field([p for p, _ in shots], cam, saturated=[m for _, m in shots])
        nom = nominal.cameras[name]
        cams[name] = replace(nom, sensor=replace(nom.sensor, vignetting=ff.radial))
        maps[name] = ff.beyond_radial(cam)
        s = score_flat_field(ff, optics_gain(cam, truth.flat_fields.get(name)), cam)
        report[name] = {"photos": ff.photos, "frames_per_photo": frames, "radial": list(ff.radial),
                        "true_radial": list(cam.sensor.vignetting), "map_about_radial_rms_pct": ff.fit_rms_pct, **s,
                        "passed": s["flat_field_pct"]["p95"] <= FLAT_FIELD_GOAL_PCT}
        if progress:
            print(f"[calibrate] {name}: flat field from 2 x {frames} frames", file=sys.stderr, flush=True)
    return replace(nominal, cameras=cams, flat_fields=maps), report
