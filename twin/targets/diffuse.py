"""A diffuse (Lambertian) reference plate for the LED calibration (calibration.leds): a flat, matte white tile of known
albedo laid in the sample holder, at the sample plane or lifted by spacers of known height.

    plate = DiffusePlate(height_mm=40.0)
    L = plate.radiance(rig, "primary", leds=[0, 1, 2])     # (3, H, W, 3): each LED alone at full drive
    W = plate.lit_radiance(rig, "primary", leds=[0, 1, 2])  # (H, W, 3): the three lit together

Why a diffuse plate (of the targets an LED calibration could use): a Lambertian plate's radiance under one LED is
the LED's own light, I_c Psi(theta_e) cos(theta_e) cos(theta_i) rho / (pi r^2) (paper Eq. 1 with a constant
BRDF), seen the same from every view and over the whole plate, so one photo carries the LED's position (the
pattern's centre and falloff), its tilt and its angular profile (the pattern's shape) and its RGB intensity (its
level), over exactly the directions in which the LED lights a sample. A chrome sphere gives a direction per
highlight (a few pixels, no intensity and no profile) and needs two spheres to triangulate. Photographing the
plate at two heights separates the LED's distance from its intensity and its profile (1/r^2 changes, the
profile barely does).

The radiance is the twin's own forward model (twin.optics.forward.lumitexels, physical convention: rho_s = 0, the holder
frame's shadows included) at the point each pixel's ray meets the plate; pixels off the plate see nothing (0):
the procedure uses the plate only. Units: the sensor's radiance unit (W m^-2 sr^-1); the camera's crosstalk,
falloff and sensor are applied by whoever photographs it (twin.camera.hdr.still_photo).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DiffusePlate"]


@dataclass(frozen=True)
class DiffusePlate:
    albedo: float = 0.8        # diffuse reflectance, grey (a white ceramic tile; Spectralon is 0.99)
    size_mm: float = 140.0     # side of the square plate, centred on the sample plane's origin
    height_mm: float = 0.0     # lifted this far along the sample plane's normal (0: lying on the sample plane)
    # 1: no plate at all, the empty holder's diffusing acrylic, which the bottom LEDs light from below (paper
    # §5; the forward model's Lambertian transmission, twin.optics.lumitexel); the albedo then plays no part
    transparency: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.albedo) and 0 < self.albedo <= 1):
            raise ValueError(f"DiffusePlate.albedo must be in (0, 1], got {self.albedo}")
        if not (np.isfinite(self.size_mm) and self.size_mm > 0):
            raise ValueError(f"DiffusePlate.size_mm must be positive, got {self.size_mm}")
        if not (np.isfinite(self.height_mm) and self.height_mm >= 0):
            raise ValueError(f"DiffusePlate.height_mm must be >= 0, got {self.height_mm}")
        if self.transparency not in (0.0, 1.0) or (self.transparency and self.height_mm):
            raise ValueError(f"DiffusePlate.transparency is 0 (a plate) or 1 (the empty holder's acrylic, at height "
                             f"0), got {self.transparency} at {self.height_mm} mm")

    def origin(self, rig) -> np.ndarray:
        return np.asarray(rig.sample.origin, np.float64) + self.height_mm * np.asarray(rig.sample.normal, np.float64)

    def points(self, rig, camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) world points (mm) where pixels uv (N, 2) see the plate's plane, and (N,) whether they lie on
        the plate."""
        ax, ay = np.asarray(rig.sample.x_axis, np.float64), np.asarray(rig.sample.y_axis, np.float64)
        X = camera.plane_points(uv, self.origin(rig), rig.sample.normal)
        rel = X - self.origin(rig)
        half = self.size_mm / 2
        inside = np.isfinite(X).all(axis=1) & (np.abs(rel @ ax) <= half) & (np.abs(rel @ ay) <= half)
        return X, inside

    def radiance(self, rig, camera_name: str, leds, device="cpu") -> np.ndarray:
        """(len(leds), H, W, 3) float64: the plate's radiance seen by each pixel of the camera, each LED of
        `leds` alone at full drive (0 off the plate)."""
        from dataclasses import replace

        from twin.optics.forward import lumitexels

        leds = np.asarray(leds, dtype=np.int64)
        sub = replace(rig, leds=rig.leds.subset(leds))  # only these LEDs: the paper rig has 16,384
        cam = rig.camera(camera_name)
        uv = np.stack(np.meshgrid(np.arange(cam.width), np.arange(cam.height)), -1).reshape(-1, 2).astype(np.float64)
        X, inside = self.points(rig, cam, uv)
        P = X[inside].astype(np.float32)
        n = len(P)
        normal = np.broadcast_to(np.asarray(rig.sample.normal, np.float32), (n, 3))
        tangent = np.broadcast_to(np.asarray(rig.sample.x_axis, np.float32), (n, 3))
        m = lumitexels(sub, P, normal, tangent, np.full((n, 3), self.albedo, np.float32), np.zeros((n, 3), np.float32),
                            np.full(n, 0.5, np.float32), np.full(n, 0.5, np.float32), convention="physical",
                            camera=camera_name, transparency=np.full(n, self.transparency, np.float32), visibility=True,
                            device=device)
        out = np.zeros((len(leds), cam.height * cam.width, 3))
        out[:, inside] = np.moveaxis(m, 1, 0)
        return out.reshape(len(leds), cam.height, cam.width, 3)

    def lit_radiance(self, rig, camera_name: str, leds, drive=(1.0, 1.0, 1.0), batch: int = 64,
                     device="cpu") -> np.ndarray:
        """(H, W, 3) float64: the plate's radiance with `leds` lit together at the RGB `drive` (0-1 per channel),
        the sum of their `radiance`, `batch` LEDs at a time (a batch's radiance is batch x H x W x 3 float64)."""
        leds = np.asarray(leds, dtype=np.int64)
        cam = rig.camera(camera_name)
        total = np.zeros((cam.height, cam.width, 3))
        for i in range(0, len(leds), batch):
            total += self.radiance(rig, camera_name, leds[i:i + batch], device=device).sum(axis=0)
        return total * np.asarray(drive, np.float64)
