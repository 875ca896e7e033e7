"""A flat-field source: a diffuse panel of uniform radiance that fills a camera's view, held in
front of the lens (an LED panel behind a diffuser, or an integrating sphere's port), for the vignetting
calibration (`calibration.vignetting`).

    source = FlatFieldSource()
    L = source.radiance(camera, orientation_deg=0.0)     # (H, W, 3) scene radiance seen by each pixel

Real panels are not perfectly flat: `gradient` is the relative change of radiance from one edge of the view to
the other, linear along the panel's x axis. Photographing the panel a second time turned by 180 degrees about
the optical axis flips that gradient, so that the mean of the two photos has none (the procedure does this).
The radiance is in the sensor's radiance unit (twin.camera.sensor), equal in the three LED-RGB channels; the
camera's crosstalk, falloff and sensor are applied by whoever photographs it (twin.camera.hdr.still_photo).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FlatFieldSource"]


@dataclass(frozen=True)
class FlatFieldSource:
    level: float = 1.0      # radiance, W m^-2 sr^-1, every channel
    gradient: float = 0.01  # relative radiance change across the view (edge to edge), along the panel's x

    def __post_init__(self):
        if not (np.isfinite(self.level) and self.level > 0):
            raise ValueError(f"FlatFieldSource.level must be positive, got {self.level}")
        if not (np.isfinite(self.gradient) and 0 <= self.gradient < 1):
            raise ValueError(f"FlatFieldSource.gradient must be in [0, 1), got {self.gradient}")

    def radiance(self, camera, orientation_deg: float = 0.0) -> np.ndarray:
        """(H, W, 3) float64: the panel's radiance along each pixel's ray, the panel turned by
        `orientation_deg` about the optical axis (its gradient turns with it)."""
        a = np.radians(orientation_deg)
        W, H = camera.width, camera.height
        x = (np.arange(W) - (W - 1) / 2)[None, :] / W
        y = (np.arange(H) - (H - 1) / 2)[:, None] / W
        L = self.level * (1 + self.gradient * (x * np.cos(a) + y * np.sin(a)))
        return np.repeat(L[..., None], 3, axis=2)
