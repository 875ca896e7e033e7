"""A rig's "true" device for calibration studies (issue #16): the nominal rig with seeded manufacturing and
assembly errors, so that a calibration has something to find. The truth is kept beside the calibrated result
for scoring (`hemicube calibrate --perturb SEED`).

Cameras: focal length uniform within +-1% (fx and fy alike: a lens, not the pixels), principal point N(0, 5 px)
per axis, radial distortion k1, k2, k3 each x N(1, 5%), pose N(0, 1 mm) per axis and a rotation of N(0, 0.2 deg)
about each axis. The issue names the focal and pose figures; the principal point and distortion spreads are
this project's choice (a lens re-mounted on its camera). LEDs, profiles, vignetting and colour: not yet.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .camera import orthonormalise

__all__ = ["perturb_cameras"]


def _rotation(v: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by |v| radians about v."""
    a = float(np.linalg.norm(v))
    if a == 0:
        return np.eye(3)
    k = v / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def perturb_cameras(rig, seed: int):
    """The rig with every camera perturbed as the module docstring says, from `seed` alone."""
    rng = np.random.default_rng([int(seed), 16])
    cams = {}
    for name, c in rig.cameras.items():
        K = c.K.copy()
        K[:2, :2] *= 1 + rng.uniform(-0.01, 0.01)
        K[:2, 2] += rng.normal(0, 5.0, 2)
        dist = c.dist.copy()
        dist[[0, 1, 4]] *= 1 + rng.normal(0, 0.05, 3)
        dR = _rotation(np.radians(rng.normal(0, 0.2, 3)))
        centre = c.centre + rng.normal(0, 1.0, 3)
        R = orthonormalise(dR @ c.R)
        cams[name] = replace(c, K=K, dist=dist, R=R, t=-R @ centre,
                             note=f"perturbed (seed {seed}) from the nominal camera")
    return replace(rig, cameras=cams)
