"""A rig's "true" device for calibration studies (docs/calibration.md): the nominal rig with seeded manufacturing and
assembly errors, so that a calibration has something to find. The truth is kept beside the calibrated result
for scoring (`hemicube calibrate --perturb SEED`).

Cameras: focal length uniform within +-1% (fx and fy alike: a lens, not the pixels), principal point N(0, 5 px)
per axis, radial distortion k1, k2, k3 each x N(1, 5%), pose N(0, 1 mm) per axis and a rotation of N(0, 0.2 deg)
about each axis. The focal and pose figures are the project's requirements; the principal point and distortion
spreads are this project's choice (a lens re-mounted on its camera).

Vignetting (`perturb_vignetting`): the true light falloff of each camera is richer than the rig's radial
model (1 + a r^2 + b r^4 + c r^6), so that a flat-field calibration has more to find than the model it fits:
- lens falloff: a natural cos^4-like radial term, a = -0.25 x U(0.8, 1.2), b = 0.05 x U(0.5, 1.5), c = 0
  (r is the distance from the principal point over the half-diagonal: ~-20% in the corners);
- mechanical vignetting: the lens hood or filter ring cuts the corners, a quadratic shoulder from 0.85 to 1.0
  of the half-diagonal, up to U(5, 15)% deep, centred N(0, 2% of the width) off the principal point;
- dust on the sensor window: 2-6 soft shadows, Gaussian, sigma U(1, 2.5)% of the width, U(1, 4)% deep.
The rig keeps the radial part in each camera's `vignetting` and the other two as its per-pixel map
(`Rig.flat_fields`), so that a capture with it renders the whole falloff.
LEDs (`perturb_leds`), the upper LEDs, or with bottom=True the bottom LEDs (an independent draw): positions N(0, 3 mm) per axis (the project's figure: a hand-assembled board's LEDs, each
placed on its own; redrawn where two would overlap); each board turned by N(0, 0.5 deg) about each axis about its centre, moving its LEDs'
normals, plus a N(0, 1 deg) tilt of every LED (soldered crooked); the angular profile cos^p with p = the
nominal p x U(0.8, 1.2) per board (the project's +-20%) x N(1, 2%) per LED, so that the truth is richer than a
profile fitted per board; RGB intensity x U(0.9, 1.1) per LED and channel (the project's +-10%). The rig must use
the "cosine" profile family. Colour: twin.camera.spectral.device_spectra (a device's spectra, from which its
cameras' crosstalk follows).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .camera import orthonormalise

__all__ = ["perturb_cameras", "perturb_leds", "perturb_vignetting"]


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


def perturb_vignetting(rig, seed: int):
    """The rig with every camera's radial vignetting drawn as the module docstring says, and the per-pixel
    factor of its mechanical vignetting and dust as the camera's `Rig.flat_fields` map, from `seed` alone.
    twin.camera.imaging.optics_gain(camera, rig.flat_fields[name]) is the camera's whole falloff."""
    rng = np.random.default_rng([int(seed), 22])
    cams, extra = {}, {}
    for name, c in rig.cameras.items():
        radial = (-0.25 * rng.uniform(0.8, 1.2), 0.05 * rng.uniform(0.5, 1.5), 0.0)
        cams[name] = replace(c, sensor=replace(c.sensor, vignetting=radial))
        W, H = c.width, c.height
        u = np.arange(W, dtype=np.float64)[None, :] - c.K[0, 2] - rng.normal(0, 0.02 * W)
        v = np.arange(H, dtype=np.float64)[:, None] - c.K[1, 2] - rng.normal(0, 0.02 * W)
        r = np.sqrt((u * u + v * v) / (0.25 * (W * W + H * H)))
        mech = 1 - rng.uniform(0.05, 0.15) * (np.clip((r - 0.85) / 0.15, 0, None) ** 2)
        dust = np.ones((H, W))
        yy, xx = np.mgrid[0:H, 0:W]
        for _ in range(int(rng.integers(2, 7))):
            cx, cy = rng.uniform(0.1, 0.9) * W, rng.uniform(0.1, 0.9) * H
            sigma, depth = rng.uniform(0.01, 0.025) * W, rng.uniform(0.01, 0.04)
            dust *= 1 - depth * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma * sigma))
        extra[name] = np.clip(mech, 0.5, 1.0) * dust
    return replace(rig, cameras=cams, flat_fields=extra)



LED_SIZE_MM = 4.0  # an LED package: moved LEDs keep at least this far apart


def _apart(p: np.ndarray, rng) -> np.ndarray:
    """(n, 3) offsets N(0, 3 mm) per axis for LEDs at p, redrawn (from rng, so still seeded) for any LED that
    would come within LED_SIZE_MM of another: two packages cannot overlap (on the paper rig's 10 mm pitch
    independent 3 mm offsets bring a few pairs within 1 mm, which the rig rightly refuses)."""
    from scipy.spatial import cKDTree

    d = rng.normal(0.0, 3.0, p.shape)
    for _ in range(100):
        close = cKDTree(p + d).query_pairs(LED_SIZE_MM, output_type="ndarray")
        if not len(close):
            return d
        redo = np.unique(close[:, 1])
        d[redo] = rng.normal(0.0, 3.0, (redo.size, 3))
    raise RuntimeError("could not place the perturbed LEDs apart")


def _perturb_boards(leds, bottom: bool, rng):
    """(positions, normals, profile, intensity) with the upper (bottom=False) or the bottom boards' LEDs drawn
    as the module docstring says."""
    pos, nrm = leds.positions.copy(), leds.normals.copy()
    prof, inten = leds.profile.copy(), leds.intensity.copy()
    for b in np.unique(leds.board[leds.is_bottom == bottom]):
        sel = np.flatnonzero((leds.board == b) & (leds.is_bottom == bottom))
        R = _rotation(np.radians(rng.normal(0.0, 0.5, 3)))
        c = pos[sel].mean(axis=0)
        pos[sel] = (pos[sel] - c) @ R.T + c
        pos[sel] += _apart(pos[sel], rng)
        tilt = np.stack([_rotation(np.radians(rng.normal(0.0, 1.0, 3))) for _ in sel])
        n = np.einsum("kij,kj->ki", tilt, nrm[sel] @ R.T)
        nrm[sel] = n / np.linalg.norm(n, axis=1, keepdims=True)
        prof[sel, 0] *= rng.uniform(0.8, 1.2) * rng.normal(1.0, 0.02, sel.size)
        inten[sel] *= rng.uniform(0.9, 1.1, (sel.size, 3))
    return pos, nrm, prof, inten


def perturb_leds(rig, seed: int, bottom: bool = False):
    """The rig with its upper LEDs' (bottom=True: its bottom LEDs') positions, normals, profiles and intensities
    drawn as the module docstring says, from `seed` alone (the two draws are independent)."""
    if rig.led_profile != "cosine":
        raise ValueError(f"perturb_leds draws cosine-profile exponents; rig {rig.name!r} uses {rig.led_profile!r}")
    rng = np.random.default_rng([int(seed), 20 if bottom else 16])
    pos, nrm, prof, inten = _perturb_boards(rig.leds, bottom, rng)
    return replace(rig, leds=replace(rig.leds, positions=pos, normals=nrm, profile=prof, intensity=inten))
