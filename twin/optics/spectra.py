"""The wavelength grid on which the twin's colour is computed from spectra: LED emission and surface
reflectance here, camera sensitivities in twin.camera.spectral.

400-700 nm in 5 nm steps: the CIE 1931 observer, the LEDs' emission (each within 3 half-widths of its peak) and
the cameras' sensitivities all lie within it, and 5 nm is the ColorChecker data's own step.
"""
from __future__ import annotations

import numpy as np

__all__ = ["WAVELENGTHS", "resample", "spectral_shape"]

WAVELENGTHS = np.arange(400.0, 701.0, 5.0)


def spectral_shape():
    """WAVELENGTHS as a colour-science SpectralShape."""
    import colour

    return colour.SpectralShape(WAVELENGTHS[0], WAVELENGTHS[-1], WAVELENGTHS[1] - WAVELENGTHS[0])


def resample(sd) -> np.ndarray:
    """A colour-science spectral distribution's values on WAVELENGTHS (interpolated; extrapolated as constant)."""
    return np.asarray(sd.copy().align(spectral_shape()).values, np.float64)
