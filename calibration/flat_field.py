"""The flat field of a camera (reference §6.3 step 2, `plane_scalar[c]`): the per-pixel factor that undoes
the lens's fall-off, so that a pixel's value is proportional to the radiance it sees wherever it lies.

Source: the rig's calibrated radial vignetting model (`Camera.sensor.vignetting`, twin.sensor.
vignetting_factor: 1 + a r^2 + b r^4 + c r^6), the twin's counterpart of the released device's
`plane_scalar.bin`; it is not re-measured from photos here.
"""
from __future__ import annotations

import numpy as np

MIN_FACTOR = 1e-3  # a pixel whose light is attenuated 1000x carries no usable signal


def flat_field(camera) -> np.ndarray:
    """(H, W) float32 multiplier for `camera`'s photos: 1 / vignetting factor."""
    from twin.sensor import vignetting_factor

    f = vignetting_factor(camera.K, camera.width, camera.height, camera.sensor.vignetting)
    if not np.all(np.isfinite(f)) or f.min() < MIN_FACTOR:
        raise ValueError(f"camera {camera.name!r}: vignetting factor below {MIN_FACTOR:g} or not finite "
                         f"(min {np.nanmin(f):.3g}); the flat field is undefined there")
    return (1.0 / f).astype(np.float32)
