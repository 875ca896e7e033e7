"""Pinhole camera with OpenCV's 5-coefficient distortion model (Brown-Conrady: k1, k2, p1, p2, k3).

Frames and pixel conventions are those of `twin.rig.units`. The projection is checked against
`cv2.projectPoints` in the tests.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np


UNDISTORT_BLOCK = 1 << 14  # points a block of Camera.undistort: its float64 temporaries stay in cache


@dataclass(frozen=True)
class SensorParams:
    """Per-camera sensor parameters, used by the virtual capture (kept in the rig so that a rig file
    fully describes the device). Defaults describe a Sony IMX540-class sensor as in the Basler
    a2A5328-15ucPRO (paper §5); they are assumptions, not released calibration."""

    bit_depth: int = 12
    bayer: str = "RG"  # colour filter layout of the top-left 2x2 cell (GenICam BayerRG)
    pixel_pitch_um: float = 2.74
    gain_e_per_dn: float = 2.4  # electrons per digital number at gain 0 dB
    full_well_e: float = 9800.0
    read_noise_e: float = 2.3
    dark_current_e_per_s: float = 0.6
    prnu: float = 0.005  # photo-response non-uniformity, relative sigma
    dsnu_e: float = 0.3  # dark-signal non-uniformity, sigma in electrons
    black_level_dn: float = 16.0
    # Radiometric sensitivity: photo-electrons per second per unit scene radiance (W m^-2 sr^-1) reaching
    # one pixel. Derived for the modelled lens and sensor: image-plane irradiance E = pi L / (4 N^2) at
    # f-number N = 8, times the pixel area (2.74 um)^2, divided by the photon energy at 550 nm
    # (3.61e-19 J), times a quantum efficiency of 0.65: 1.66e5 e-/s. ASSUMED (no released radiometry).
    electrons_per_radiance_s: float = 1.66e5
    vignetting: tuple[float, float, float] = (0.0, 0.0, 0.0)  # radial: 1 + a r^2 + b r^4 + c r^6, r normalised
    crosstalk: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    def __post_init__(self):
        if self.bit_depth not in (8, 10, 12, 16):
            raise ValueError(f"sensor bit_depth must be 8, 10, 12 or 16, got {self.bit_depth}")
        if self.bayer not in ("RG", "GR", "GB", "BG"):
            raise ValueError(f"sensor bayer must be one of RG, GR, GB, BG, got {self.bayer!r}")
        for name in ("pixel_pitch_um", "gain_e_per_dn", "full_well_e", "electrons_per_radiance_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"sensor {name} must be a positive finite number, got {v}")
        for name in ("read_noise_e", "dark_current_e_per_s", "prnu", "dsnu_e", "black_level_dn"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"sensor {name} must be finite and >= 0, got {v}")
        if len(self.vignetting) != 3 or not np.all(np.isfinite(self.vignetting)):
            raise ValueError("sensor vignetting must be 3 finite coefficients (a, b, c)")
        m = np.asarray(self.crosstalk, dtype=float)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ValueError("sensor crosstalk must be a finite 3x3 matrix (LED RGB -> camera RGB)")


def unit3(v) -> np.ndarray:
    """A 3-vector divided by its length, in plain IEEE double arithmetic (Python floats: no BLAS, SIMD
    or FMA), so that rigs built from it are bit-identical on every machine (their digest seeds the
    sensor's fixed patterns and names captures)."""
    x, y, z = (float(c) for c in v)
    n = math.sqrt(x * x + y * y + z * z)
    return np.array([x / n, y / n, z / n])


def cross3(a, b) -> np.ndarray:
    a0, a1, a2 = (float(c) for c in a)
    b0, b1, b2 = (float(c) for c in b)
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def dot3(a, b) -> float:
    return float(a[0]) * float(b[0]) + float(a[1]) * float(b[1]) + float(a[2]) * float(b[2])


def orthonormalise(R) -> np.ndarray:
    """Gram-Schmidt on the rows of a nearly orthonormal 3x3 matrix (first row kept, third = first x
    second): an exact rotation, computed reproducibly (see unit3)."""
    r0 = unit3(R[0])
    r1 = unit3(np.asarray(R[1], float) - dot3(r0, R[1]) * r0)
    return np.stack([r0, r1, cross3(r0, r1)])


def _frozen(a, dtype=np.float64):
    a = np.array(a, dtype=dtype)
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class Camera:
    """A calibrated camera. K (3x3), dist (5,), R|t world->camera (OpenCV), resolution in pixels."""

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    sensor: SensorParams = field(default_factory=SensorParams)
    assumed: bool = False  # True when the calibration is derived, not released (e.g. the 45 deg camera)
    note: str = ""

    def __post_init__(self):
        object.__setattr__(self, "K", _frozen(self.K))
        object.__setattr__(self, "dist", _frozen(np.ravel(self.dist)))
        object.__setattr__(self, "R", _frozen(self.R))
        object.__setattr__(self, "t", _frozen(np.ravel(self.t)))

    # --- geometry -----------------------------------------------------------------------------
    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates, C = -R^T t."""
        return -self.R.T @ self.t

    @property
    def optical_axis(self) -> np.ndarray:
        """Viewing direction (camera +z) in world coordinates."""
        return self.R[2].copy()

    def world_to_camera(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(X, dtype=np.float64) @ self.R.T + self.t

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply OpenCV's distortion to normalised image coordinates (N, 2)."""
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert `distort` by fixed-point iteration (as cv2.undistortPoints does), in blocks of points that
        stay in the processor's cache. A point that the iteration maps to itself exactly stays there, so it
        leaves the loop then with the bits it would end with (where every point through all 20 iterations made a
        paper-rig camera's pixel grid slow; docs/performance.md)."""
        xy_d = np.asarray(xy_d, dtype=np.float64)
        xd, yd = xy_d[..., 0].ravel(), xy_d[..., 1].ravel()
        out = np.empty((xd.size, 2))
        for i in range(0, xd.size, UNDISTORT_BLOCK):
            out[i:i + UNDISTORT_BLOCK] = self._undistort_block(xd[i:i + UNDISTORT_BLOCK], yd[i:i + UNDISTORT_BLOCK],
                                                               iterations)
        return out.reshape(xy_d.shape)

    def undistort_reference(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """`undistort` as it was before the blocks: every point through every iteration. The oracle of
        tests/twin/test_camera.py."""
        xy = np.array(xy_d, dtype=np.float64)
        for _ in range(iterations):
            xy = np.stack(self._undistort_step(xy[..., 0], xy[..., 1], xy_d[..., 0], xy_d[..., 1]), axis=-1)
        return xy

    def _undistort_step(self, x, y, xd, yd):
        """One fixed-point step of `undistort`: the point whose distortion of (x, y) moved to (xd, yd)."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return (xd - dx) / radial, (yd - dy) / radial

    def _undistort_block(self, xd: np.ndarray, yd: np.ndarray, iterations: int) -> np.ndarray:
        out = np.stack([xd, yd], axis=-1)
        live = np.arange(xd.size)  # the points still iterated: x, y, their targets xd, yd
        x, y = xd, yd
        for _ in range(iterations):
            xn, yn = self._undistort_step(x, y, xd, yd)
            moving = (xn != x) | (yn != y)
            x, y = xn, yn
            if moving.sum() < 0.75 * live.size:  # drop the settled points (a copy pays only when many have)
                out[live, 0], out[live, 1] = x, y
                live, x, y, xd, yd = live[moving], x[moving], y[moving], xd[moving], yd[moving]
                if not live.size:
                    return out
        out[live, 0], out[live, 1] = x, y
        return out

    def project(self, X: np.ndarray, distort: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> pixels (N, 2) and depth along the optical axis (N,)."""
        Xc = self.world_to_camera(np.atleast_2d(X))
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = Xc[:, :2] / z[:, None]
        if distort:
            xy = self.distort(xy)
        uv = xy @ self.K[:2, :2].T + self.K[:2, 2]
        return uv, z

    def pixel_rays(self, uv: np.ndarray, distorted: bool = True) -> np.ndarray:
        """Unit world-space ray directions through pixels (N, 2)."""
        uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
        xy = (uv - self.K[:2, 2]) @ np.linalg.inv(self.K[:2, :2]).T
        if distorted:
            xy = self.undistort(xy)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ self.R
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def plane_points(self, uv: np.ndarray, origin, normal, distorted: bool = True) -> np.ndarray:
        """World points (N, 3) where the rays through pixels uv (N, 2) meet the plane through `origin` with
        `normal` (rays parallel to the plane give inf/nan)."""
        d = self.pixel_rays(uv, distorted)
        c = self.centre
        n, o = np.asarray(normal, dtype=np.float64), np.asarray(origin, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            return c + d * (((o - c) @ n) / (d @ n))[:, None]

    def resized(self, factor: float, name: str | None = None) -> "Camera":
        """The same camera with the image scaled by `factor` (0.5 = 2x2 binning). Pixel centres follow
        OpenCV's convention, so c' = (c + 0.5) * factor - 0.5."""
        w, h = self.width * factor, self.height * factor
        if abs(w - round(w)) > 1e-9 or abs(h - round(h)) > 1e-9:
            raise ValueError(f"resizing {self.width}x{self.height} by {factor} does not give whole pixels")
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return replace(self, name=name or self.name, width=int(round(w)), height=int(round(h)), K=K)

    @staticmethod
    def look_at(name, centre, target, up_hint, K, width, height, dist=(0, 0, 0, 0, 0), **kw) -> "Camera":
        """Build R|t for a camera at `centre` looking at `target`; camera +x is `up_hint` made orthogonal
        to the view direction (the image columns run along it)."""
        centre = np.asarray(centre, float)
        z = unit3(np.asarray(target, float) - centre)
        x = unit3(np.asarray(up_hint, float) - dot3(up_hint, z) * z)
        R = np.stack([x, cross3(z, x), z])
        return Camera(name, width, height, K, dist, R, -np.array([dot3(r, centre) for r in R]), **kw)
