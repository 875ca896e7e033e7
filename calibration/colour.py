"""Colour calibration: each camera's crosstalk, and its colour matrix to CIE XYZ, from photographs.

1. **The crosstalk** M (camera RGB = M @ LED RGB; `Camera.sensor.crosstalk`, whose inverse is the reference's
   `color_mat`): the white plate (twin.targets.diffuse) photographed three times, every upper LED lit in one
   channel c only. Each pixel then records M[:, c] times the light of channel c, so the ratios of its three
   channels to channel c are M's column c: M[c, c] = 1 is the unit of LED channel c (twin.camera.spectral).
   The ratio is per pixel, so the light's falloff over the plate and the lens's vignetting (achromatic) cancel;
   the median over the plate's pixels beats the noise down. Pixels within 2 px of the plate's edge are left out
   (the bilinear demosaic mixes in the dark beyond it), as are pixels below 5% of the photo's brightest in
   channel c (their ratios are noise) and saturated ones.
2. **The colour matrix to XYZ** under the LEDs' white: a ColorChecker (twin.targets.colorchecker) in the holder,
   every upper LED lit white, and the white plate under the same light. Each patch's camera RGB (the mean over
   its pixels at least 2 px inside its edge, located by projecting the chart's known layout in the holder
   through the calibrated camera) divided by the plate's at the same pixels and times the plate's albedo is
   its white-balanced camera reflectance r; the chart's published spectral reflectances under the LEDs' white
   (its spectrum as a spectroradiometer reads it off the plate) give its reference XYZ. The 3x3 matrix from r
   to XYZ is the least-squares fit of Cheung et al. (2004) with 3 terms (`colour.matrix_colour_correction`),
   the reference device's one linear matrix per camera.
   Scored by CIE ΔE2000 of the 24 patches in CIE Lab under the LEDs' white.

Why patches are located by projection, not detected: the chart lies in the holder at a known place (the
sample's), and the cameras are calibrated before colour (calibration.cameras); the mini rig's 222 x 192 px
cameras give each patch ~11 x 11 px, too few for colour-checker-detection's segmentation. A chart that is not
where the layout says shows up as a patch without enough pixels or an inconsistent white (both named).

`calibrate_colour` runs both in the twin, every camera, scored against its truth (`COLOUR_GOALS`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["ColourCalibrationError", "crosstalk_from_photos", "chart_patches", "matrix_to_xyz", "delta_e2000",
           "calibrate_colour", "COLOUR_GOALS"]

EDGE_PX = 2          # pixels next to a plate's or a patch's edge left out (the demosaic's reach, and a margin)
MIN_SIGNAL = 0.05    # crosstalk: pixels below this fraction of the photo's brightest in the lit channel
MIN_PATCH_PX = 9     # a patch's usable pixels, at least (a 3 x 3 core)


class ColourCalibrationError(ValueError):
    """Photos a colour calibration cannot use; the message names the photo."""


def _check(photo, saturated, camera, label) -> tuple[np.ndarray, np.ndarray]:
    from .photos import checked_photo

    photo = checked_photo(photo, camera, label, ColourCalibrationError)
    return photo, np.zeros(photo.shape[:2], bool) if saturated is None else np.asarray(saturated, bool)


def crosstalk_from_photos(photos, saturated, camera, rig, plate, label: str = "plate") -> np.ndarray:
    """(3, 3) M from three photos (H, W, 3 camera RGB) of `plate` lit by LED channel 0, 1 and 2 alone
    (step 1); `saturated`: their (H, W) saturated-photosite masks (or None)."""
    from scipy import ndimage

    if len(photos) != 3:
        raise ColourCalibrationError(f"{label}: need one photo per LED channel (3), got {len(photos)}")
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    _, on = plate.points(rig, camera, np.stack([u.ravel(), v.ravel()], -1).astype(np.float64))
    on = ndimage.binary_erosion(on.reshape(camera.height, camera.width), iterations=EDGE_PX)
    M = np.eye(3)
    for c, (photo, sat) in enumerate(zip(photos, saturated if saturated is not None else [None] * 3)):
        name = f"{label}, LED channel {'RGB'[c]}"
        photo, sat = _check(photo, sat, camera, name)
        lit = photo[..., c]
        use = on & ~sat & (lit > MIN_SIGNAL * lit[on].max()) if on.any() else on
        if use.sum() < MIN_PATCH_PX:
            raise ColourCalibrationError(f"{name}: {int(use.sum())} usable plate pixels (the plate out of view, "
                                         "unlit or saturated)")
        M[:, c] = np.median(photo[use] / lit[use, None], axis=0)
    return M


def chart_patches(photo, saturated, camera, rig, chart, label: str = "chart") -> np.ndarray:
    """(P, 3) mean camera RGB of each patch of `chart` in one photo (H, W, 3), over its pixels at least EDGE_PX
    inside its edges; the patches located by projecting the chart's layout through `camera` (calibrated)."""
    from scipy import ndimage

    photo, sat = _check(photo, saturated, camera, label)
    idx = chart.patch_map(rig, camera)
    names, _ = chart.names_and_spectra()
    out = np.empty((len(names), 3))
    for p, name in enumerate(names):
        core = ndimage.binary_erosion(idx == p, iterations=EDGE_PX)
        if core.sum() < MIN_PATCH_PX:
            raise ColourCalibrationError(f"{label}: patch {p} ({name!r}) has {int(core.sum())} pixels inside its "
                                         f"edges in camera {camera.name!r} (at least {MIN_PATCH_PX}): the chart is "
                                         "outside the frame or too small in it")
        if sat[core].any():
            raise ColourCalibrationError(f"{label}: patch {p} ({name!r}) is saturated in camera {camera.name!r}")
        out[p] = photo[core].mean(axis=0)
    return out


def matrix_to_xyz(rgb, xyz, method: str = "Cheung 2004", **kwargs) -> np.ndarray:
    """(3, 3) A with xyz ≈ A @ rgb: colour-science's colour correction `method` (Cheung 2004, 3 terms: the
    linear 3x3) fitted to the patches' camera reflectances rgb (P, 3) and reference XYZ (P, 3)."""
    import colour

    A = np.asarray(colour.matrix_colour_correction(np.asarray(rgb, np.float64), np.asarray(xyz, np.float64),
                                                   method=method, **({"terms": 3} | kwargs)), np.float64)
    if A.shape != (3, 3):
        raise ValueError(f"{method} with {kwargs} is not a 3x3 matrix ({A.shape})")
    return A


def delta_e2000(xyz, xyz_ref, white_xyz) -> np.ndarray:
    """(P,) CIE ΔE2000 between two sets of XYZ (P, 3), both in CIE Lab under the white `white_xyz` (3,)."""
    import colour

    w = colour.XYZ_to_xy(np.asarray(white_xyz, np.float64))
    return np.asarray(colour.delta_E(colour.XYZ_to_Lab(np.asarray(xyz, np.float64), w),
                                     colour.XYZ_to_Lab(np.asarray(xyz_ref, np.float64), w), method="CIE 2000"))


# the colour's goals (docs/calibration.md): ColorChecker ΔE2000 <= 1 (median); ours: the crosstalk left
# after correction within 0.5%, the flat field's goal
COLOUR_GOALS = {"delta_e2000_median": 1.0, "crosstalk_max": 0.005}


def calibrate_colour(nominal, truth, spectra, frames: int, seed: int, step: int = 1, binning: int = 1,
                     progress: bool = True) -> tuple:
    """Photograph the white plate (each LED channel alone, then white) and a ColorChecker (white) with every
    camera of the TRUE rig, whose colour is `spectra`'s (twin.camera.spectral), and calibrate each camera's
    crosstalk and colour matrix to XYZ from those photos alone (calibration.colour; the cameras and flat fields
    as the nominal rig has them: calibrated beforehand). The light is every `step`-th upper LED (the white need
    not be uniform: each patch is divided by the plate at the same pixels), the cameras binned `binning` x
    `binning`. Returns (the nominal rig with the calibrated crosstalks, a report per camera scored against the
    truth, with the nominal crosstalk's own error beside it).

    nominal, truth are Rigs; `spectra` the true device's spectral sensitivities and LED spectra
    (twin.camera.spectral.device_spectra); `frames` frames averaged per photo; `seed` draws the photos' noise.
    The calibrated crosstalk is each camera's sensor.crosstalk, a (3, 3) matrix from LED RGB to camera RGB. The
    report per camera: photos, frames_per_photo, leds_lit, binning, camera_pixels ([W, H] binned, pixels),
    crosstalk and true_crosstalk ((3, 3) lists), crosstalk_residual_max (the largest entry of M^-1 M_true - I: a
    fraction, 0.005 = 0.5%), nominal_error, to_xyz_from_camera_rgb and to_xyz_from_led_rgb ((3, 3) lists to CIE
    XYZ), white_led_rgb (3 values, the brightest 1), delta_e2000 ({median, p90, max, per_patch}: CIE ΔE2000 of
    the 24 patches), goals (COLOUR_GOALS) and passed."""
    import itertools
    import sys
    from dataclasses import replace

    from twin.camera.hdr import still_photo
    from twin.camera.spectral import chart_radiance
    from twin.targets.colorchecker import ColorChecker
    from twin.targets.diffuse import DiffusePlate

    from .photos import LED_BATCH, binned_rig

    upper = np.flatnonzero(~truth.is_bottom)[::step]
    plate, chart = DiffusePlate(), ColorChecker()
    names, rho = chart.names_and_spectra()
    cams, report = {}, {}
    seen, binned = binned_rig(truth, binning), binned_rig(nominal, binning)
    for name, cam in seen.cameras.items():
        known = binned.camera(name)
        shots = itertools.count(0, frames)  # each photo its own noise draws

        def photo(radiance, camera_rgb=False):
            return still_photo(radiance, cam, seed=seed, frames=frames, first_frame=next(shots), camera_key=name,
                               flat_field=seen.flat_fields.get(name), camera_rgb=camera_rgb)

        light = plate.lit_radiance(seen, name, upper, batch=LED_BATCH)  # LED RGB: every upper LED at full drive
        channel = [photo(light * np.eye(3)[c]) for c in range(3)]
        M = crosstalk_from_photos([p for p, _ in channel], [m for _, m in channel], known, binned, plate,
                                  label=f"{name}, white plate")
        white = chart_patches(*photo(light), known, binned, chart, label=f"{name}, white plate")
        # the chart lies where the plate lay (140 mm, the chart 82.5 mm): the plate's light over its albedo is
        # what a perfect white there receives, no second evaluation of the LEDs
        r = chart_patches(*photo(chart_radiance(chart, seen, spectra, name, light / plate.albedo), camera_rgb=True),
                          known, binned, chart, label=f"{name}, ColorChecker") / white * plate.albedo
        # the LEDs' white as a spectroradiometer reads it off the plate where the chart lies: its LED-RGB mix
        weights = light[chart.patch_map(seen, cam) >= 0].mean(axis=0)
        ref = spectra.xyz(rho, weights)
        A = matrix_to_xyz(r, ref)
        dE = delta_e2000(r @ A.T, ref, spectra.xyz(np.ones(rho.shape[1]), weights))
        Mt = np.asarray(cam.sensor.crosstalk, np.float64)
        residual = lambda Mc: float(np.abs(np.linalg.solve(Mc, Mt) - np.eye(3)).max())  # noqa: E731
        nom = nominal.camera(name)  # unbinned
        cams[name] = replace(nom, sensor=replace(nom.sensor, crosstalk=tuple(map(tuple, M.tolist()))))
        goals = {"delta_e2000_median": float(np.median(dE)) <= COLOUR_GOALS["delta_e2000_median"],
                 "crosstalk_max": residual(M) <= COLOUR_GOALS["crosstalk_max"]}
        report[name] = {"photos": 6, "frames_per_photo": frames, "leds_lit": len(upper), "binning": binning,
                        "camera_pixels": [cam.width, cam.height], "crosstalk": M.tolist(), "true_crosstalk": Mt.tolist(),
                        "crosstalk_residual_max": residual(M),
                        "nominal_error": {"crosstalk_residual_max": residual(np.asarray(known.sensor.crosstalk))},
                        "to_xyz_from_camera_rgb": A.tolist(), "to_xyz_from_led_rgb": (A @ M).tolist(),
                        "white_led_rgb": (weights / weights.max()).tolist(),
                        "delta_e2000": {"median": float(np.median(dE)), "p90": float(np.percentile(dE, 90)),
                                        "max": float(dE.max()), "per_patch": dict(zip(names, dE.round(3).tolist()))},
                        "goals": goals, "passed": all(goals.values())}
        if progress:
            print(f"[calibrate] {name}: crosstalk from 3 plate photos, colour matrix from the ColorChecker",
                  file=sys.stderr, flush=True)
    return replace(nominal, cameras=cams), report
