"""A ColorChecker for the colour calibration (calibration.colour): the X-Rite ColorChecker Classic Mini (4 x 6 patches,
the Classic's 24 colours on a 13.5 mm pitch, 55.5 x 82.5 mm; the real one is 57 x 83) lying in the sample holder,
lit by the rig's LEDs.

    chart = ColorChecker()
    idx = chart.patch_map(rig, camera)                     # (H, W): patch 0-23, FRAME, or OFF

The patches' colours are spectral reflectances (`reflectances`: colour-science's "ColorChecker N Ohta", the
Classic's 24 patches measured at 5 nm), not RGB triplets: what a camera records of them depends on the LEDs'
spectra and its own filters (twin.camera.spectral.chart_radiance turns them into camera RGB, from the light a
white plate in the chart's place receives: twin.targets.diffuse), which is the point of photographing a chart.
The surround is a matte black of 3% reflectance. Why the Mini: the mini rig sees a 150 mm sample square and the
Classic is 279 x 216 mm; the Mini fits with room to spare on both rigs.

Patch order and layout as printed: row-major from 'dark skin' (top left) to 'black 2 (1.5 D)' (bottom right),
columns along the sample plane's x axis, the top row towards +y. Patches are Lambertian (the chart's matte
finish; its sheen is below what a 3x3 colour matrix is meant to see).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ColorChecker", "FRAME", "OFF"]

FRAME, OFF = -1, -2  # patch_map's labels for the chart's black surround and for pixels not on the chart


@dataclass(frozen=True)
class ColorChecker:
    reflectances: str = "ColorChecker N Ohta"  # colour.SDS_COLOURCHECKERS key
    rows: int = 4
    columns: int = 6
    pitch_mm: float = 13.5        # patch centre to patch centre
    patch_mm: float = 11.0        # side of a square patch
    border_mm: float = 2.0        # surround beyond the outer patches' edges: 82.5 x 55.5 mm in all
    frame_reflectance: float = 0.03
    offset_mm: tuple[float, float] = (0.0, 0.0)  # chart centre on the sample plane (x, y)
    height_mm: float = 0.0        # lifted along the sample plane's normal

    def __post_init__(self):
        if not (0 < self.patch_mm < self.pitch_mm) or self.border_mm < 0:
            raise ValueError(f"ColorChecker: need 0 < patch_mm < pitch_mm and border_mm >= 0, got {self.patch_mm}, "
                             f"{self.pitch_mm}, {self.border_mm}")

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width along x, height along y) of the whole chart."""
        edge = self.patch_mm + 2 * self.border_mm
        return ((self.columns - 1) * self.pitch_mm + edge, (self.rows - 1) * self.pitch_mm + edge)

    def names_and_spectra(self) -> tuple[list[str], np.ndarray]:
        """The patches' names and (P, N) spectral reflectances on twin.optics.spectra.WAVELENGTHS."""
        import colour

        from twin.optics.spectra import resample

        sds = colour.SDS_COLOURCHECKERS[self.reflectances]
        if len(sds) != self.rows * self.columns:
            raise ValueError(f"{self.reflectances!r} has {len(sds)} patches, the chart {self.rows} x {self.columns}")
        return list(sds), np.stack([resample(sd) for sd in sds.values()])

    def _local(self, rig, X: np.ndarray) -> np.ndarray:
        """(N, 2) chart coordinates (mm from the chart's centre along x, y) of world points X (N, 3)."""
        ax, ay = np.asarray(rig.sample.x_axis, np.float64), np.asarray(rig.sample.y_axis, np.float64)
        rel = X - self.origin(rig)
        return np.stack([rel @ ax, rel @ ay], axis=1) - np.asarray(self.offset_mm, np.float64)

    def origin(self, rig) -> np.ndarray:
        return np.asarray(rig.sample.origin, np.float64) + self.height_mm * np.asarray(rig.sample.normal, np.float64)

    def patch_centres(self, rig) -> np.ndarray:
        """(P, 3) world points (mm) of the patches' centres, in patch order."""
        ax, ay = np.asarray(rig.sample.x_axis, np.float64), np.asarray(rig.sample.y_axis, np.float64)
        i, j = np.divmod(np.arange(self.rows * self.columns), self.columns)
        x = (j - (self.columns - 1) / 2) * self.pitch_mm + self.offset_mm[0]
        y = ((self.rows - 1) / 2 - i) * self.pitch_mm + self.offset_mm[1]
        return self.origin(rig) + x[:, None] * ax + y[:, None] * ay

    def patch_map(self, rig, camera) -> np.ndarray:
        """(H, W) int: the patch each pixel's ray meets (0..P-1), FRAME on the surround, OFF beside the chart."""
        v, u = np.mgrid[0:camera.height, 0:camera.width]
        uv = np.stack([u.ravel(), v.ravel()], -1).astype(np.float64)
        X = camera.plane_points(uv, self.origin(rig), rig.sample.normal)
        ok = np.isfinite(X).all(axis=1)
        xy = np.full((len(uv), 2), np.inf)
        xy[ok] = self._local(rig, X[ok])
        w, h = self.size_mm
        out = np.full(len(uv), OFF, np.int64)
        on = (np.abs(xy[:, 0]) <= w / 2) & (np.abs(xy[:, 1]) <= h / 2)
        out[on] = FRAME
        col = np.round(xy[:, 0] / self.pitch_mm + (self.columns - 1) / 2)
        row = np.round((self.rows - 1) / 2 - xy[:, 1] / self.pitch_mm)
        cx = (col - (self.columns - 1) / 2) * self.pitch_mm
        cy = ((self.rows - 1) / 2 - row) * self.pitch_mm
        inside = on & (np.abs(xy[:, 0] - cx) <= self.patch_mm / 2) & (np.abs(xy[:, 1] - cy) <= self.patch_mm / 2) \
            & (col >= 0) & (col < self.columns) & (row >= 0) & (row < self.rows)
        out[inside] = (row * self.columns + col)[inside].astype(np.int64)
        return out.reshape(camera.height, camera.width)
