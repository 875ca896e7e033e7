"""Shared building blocks of the procedural samples (twin.materials.samples, twin.materials.suite): texel-centre
coordinates, unit rows, streak noise. Conventions (twin.materials.samples): row i along +y, column j along +x."""
from __future__ import annotations

import numpy as np

__all__ = ["grid_uv", "streak_noise", "unit_rows"]


def streak_noise(rng: np.random.Generator, res: int, psi: np.ndarray) -> np.ndarray:
    """Fine 1-D noise in [−1, 1] as a function of the streak coordinate psi (units of the sample side):
    three octaves (about ½, 2 and 16 texels across) of linearly interpolated white noise."""
    lo, hi = float(psi.min()) - 1e-6, float(psi.max()) + 1e-6
    out = np.zeros_like(psi)
    for spacing, weight in ((0.5, 0.5), (2.0, 0.3), (16.0, 0.2)):
        h = spacing / res
        knots = np.arange(lo, hi + 2 * h, h)
        out += weight * np.interp(psi, knots, rng.uniform(-1.0, 1.0, knots.size))
    return out / max(float(np.abs(out).max()), 1e-12)


def unit_rows(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def grid_uv(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised texel-centre coordinates u (along x, columns) and v (along y, rows) in (0, 1), (H, W)."""
    c = (np.arange(res) + 0.5) / res
    return np.meshgrid(c, c, indexing="xy")  # u[i, j] = c[j], v[i, j] = c[i]
