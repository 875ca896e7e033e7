"""The colour matrix of a camera (reference §6.3 step 6, `color_mat[c]`): camera RGB -> LED RGB.

The camera's channels see the LEDs' R, G and B through a 3x3 crosstalk (dye overlap of the Bayer filter and
the LED spectra; twin.sensor.apply_crosstalk: camera_rgb = M @ led_rgb). Measurements are compared with
lumitexels rendered per LED channel, so the photos are brought back to LED RGB with C = M^-1.

Source of M: the rig's calibration (`Camera.sensor.crosstalk`), the twin's counterpart of the released
device's `color_mat{0,1}.bin`; it is not re-measured from photos here.
"""
from __future__ import annotations

import numpy as np

# a crosstalk matrix this close to singular would amplify photo noise by more than 1e3 (its condition number)
MAX_CONDITION = 1e3


def colour_matrix(camera) -> np.ndarray:
    """C (3, 3) float64 with led_rgb = C @ camera_rgb for `camera` (a twin.camera.Camera)."""
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
