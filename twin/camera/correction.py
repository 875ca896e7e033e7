"""The corrections a photo needs before its values are measurements (reference §6.3 steps 2 and 6), from the
rig's calibrated sensor parameters (twin.rig.camera.SensorParams): the inverse of what twin.camera.sensor
simulates. Producing those parameters from photographs is calibration's job (the `calibration` package
writes rig folders); applying them is the camera's.

Flat field (`plane_scalar[c]` in the reference): the per-pixel factor that undoes the lens's fall-off, so that
a pixel's value is proportional to the radiance it sees wherever it lies: 1 / the rig's radial vignetting
model (`Camera.sensor.vignetting`, twin.camera.sensor.vignetting_factor: 1 + a r^2 + b r^4 + c r^6), times
the rig's per-pixel map for the camera when it has one (`Rig.flat_fields`, from calibration.vignetting), the
twin's counterpart of the released device's `plane_scalar.bin`.

Colour matrix (`color_mat[c]`): camera RGB -> LED RGB. The camera's channels see the LEDs' R, G and B through a
3x3 crosstalk (dye overlap of the Bayer filter and the LED spectra; twin.camera.sensor.apply_crosstalk:
camera_rgb = M @ led_rgb). Measurements are compared with lumitexels rendered per LED channel, so the photos
are brought back to LED RGB with C = M^-1 (`Camera.sensor.crosstalk`, the counterpart of the released
device's `color_mat{0,1}.bin`).
"""
from __future__ import annotations

import numpy as np

from twin.camera.sensor import vignetting_factor

MIN_FACTOR = 1e-3  # a pixel whose light is attenuated 1000x carries no usable signal


def flat_field(camera, falloff=None) -> np.ndarray:
    """(H, W) float32 multiplier for `camera`'s photos: 1 / (vignetting factor x the per-pixel `falloff` map,
    if any: `Rig.flat_fields[camera.name]`)."""
    f = vignetting_factor(camera.K, camera.width, camera.height, camera.sensor.vignetting)
    if falloff is not None:
        f = f * np.asarray(falloff, np.float64)
    if not np.all(np.isfinite(f)) or f.min() < MIN_FACTOR:
        raise ValueError(f"camera {camera.name!r}: vignetting factor below {MIN_FACTOR:g} or not finite "
                         f"(min {np.nanmin(f):.3g}); the flat field is undefined there")
    return (1.0 / f).astype(np.float32)


# a crosstalk matrix this close to singular would amplify photo noise by more than 1e3 (its condition number)
MAX_CONDITION = 1e3


def colour_matrix(camera) -> np.ndarray:
    """C (3, 3) float64 with led_rgb = C @ camera_rgb for `camera` (a twin.rig.camera.Camera)."""
    M = np.asarray(camera.sensor.crosstalk, dtype=np.float64)
    cond = np.linalg.cond(M)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise ValueError(f"camera {camera.name!r}: crosstalk matrix is ill-conditioned (condition {cond:.3g} > "
                         f"{MAX_CONDITION:g}); its colour cannot be corrected")
    return np.linalg.inv(M)


def apply_colour_matrix(rgb, C) -> np.ndarray:
    """rgb (..., 3) camera RGB -> LED RGB (float32)."""
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.shape[-1:] != (3,):
        raise ValueError(f"rgb must end in 3 channels, got shape {rgb.shape}")
    return rgb @ np.asarray(C, dtype=np.float32).T
