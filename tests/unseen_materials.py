"""Held-back material folders that no builder of this project draws: the kinds of sample that users brought and
the suite never had (docs/accuracy.md, "Unseen materials"), written as OpenSVBRDF map folders and run through
`hemicube validate --sample DIR`, the path a user takes.

    write_unseen(kind, seed, directory)      one composition of KIND (UNSEEN_KINDS) as a map folder
    UNSEEN = [(kind, seed), ...]             the twelve that the tests hold to the goals: seeds 9201-9203,
                                             fixed before any of them was run

Independent of twin.materials.suite on purpose (its own fields, its own parameter ranges): a generator that
shared the suite's builders would share their blind spots. Each kind follows the ranges of the materials that
missed: glossy and weakly textured (ceramic-like glaze, brushed metal), anisotropic satin-like cloth, and bright
paper-like stock with a printed motif, a weak rough specular lobe and embossing. Features are kept to what a 48²
grid over 120 mm resolves (>= ~10 mm, the suite's band limit), so that a miss measures the pipeline, not the
footprint of a texel.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from twin.materials.samples import BUILTIN_SIZE_MM, SVBRDFMaps, write_maps

UNSEEN_KINDS = ("ceramic_like", "brushed_like", "satin_like", "paper_like")
UNSEEN = [(kind, seed) for kind in UNSEEN_KINDS for seed in (9201, 9202, 9203)]
RESOLUTION = 128


def _field(rng: np.random.Generator, res: int, feature_mm: float) -> np.ndarray:
    """A smooth random field, zero mean and unit standard deviation, with features of about `feature_mm`."""
    sigma = feature_mm / BUILTIN_SIZE_MM * res / 2.5
    f = gaussian_filter(rng.standard_normal((res, res)), sigma, mode="reflect")
    return (f - f.mean()) / (f.std() + 1e-12)


def _normals_from_height(height: np.ndarray, max_tilt_deg: float) -> np.ndarray:
    gy, gx = np.gradient(height)
    scale = np.tan(np.radians(max_tilt_deg)) / max(np.abs(np.stack([gx, gy])).max(), 1e-12)
    n = np.stack([-gx * scale, -gy * scale, np.ones_like(height)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _tangent(phi: np.ndarray, normal: np.ndarray) -> np.ndarray:
    d = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)
    t = d - np.sum(d * normal, -1, keepdims=True) * normal
    return t / np.linalg.norm(t, axis=-1, keepdims=True)


def _rgb(v, res):
    v = np.asarray(v, np.float64)
    return np.broadcast_to(v[..., None] if v.ndim == 2 else v, (res, res, 3)).copy()


def ceramic_like(rng, res):
    """A glossy glaze with almost no texture: one colour (ρd 0.3-0.85) varying by ±2 % over ~40 mm, ρs 0.6-3,
    α 0.012-0.05 isotropic, undulation up to 1.5°."""
    base = rng.uniform(0.3, 0.85, 3)
    rho_d = base * (1 + 0.02 * _field(rng, res, 40)[..., None])
    rho_s = rng.uniform(0.6, 3.0) * (1 + 0.03 * _field(rng, res, 30))
    a = np.exp(rng.uniform(np.log(0.012), np.log(0.025)) + 0.35 * (0.5 + 0.5 * np.tanh(_field(rng, res, 40))))
    n = _normals_from_height(_field(rng, res, 40), rng.uniform(0.5, 1.5))
    return rho_d, _rgb(rho_s, res), np.stack([a, a], -1), n, rng.uniform(0, np.pi) + np.zeros((res, res))


def brushed_like(rng, res):
    """Brushed metal: ρd 0.005-0.04, tinted ρs 2-9, one brushing direction (±5° over the sample), α across the
    grooves 0.08-0.3 and along them 0.02-0.06, streaks of ±8 % along the grooves; flat to 1°."""
    phi0 = rng.uniform(0, np.pi)
    phi = phi0 + np.radians(5) * np.tanh(_field(rng, res, 60))
    tint = rng.uniform(0.7, 1.0, 3)
    rho_d = _rgb(rng.uniform(0.005, 0.04) * tint, res)
    rho_s = rng.uniform(2, 9) * tint * (1 + 0.05 * _field(rng, res, 30)[..., None])
    along = np.array([np.cos(phi0), np.sin(phi0)])
    yy, xx = np.mgrid[0:res, 0:res] / res
    across = -xx * along[1] + yy * along[0]  # streaks vary across the brushing direction only
    streak = np.interp(across, np.linspace(-1.5, 1.5, 61), rng.standard_normal(61))
    ax = rng.uniform(0.08, 0.3) * (1 + 0.08 * np.tanh(streak))
    ay = rng.uniform(0.02, 0.06) * (1 + 0.08 * np.tanh(streak))
    n = _normals_from_height(_field(rng, res, 50), rng.uniform(0.2, 1.0))
    # the tangent is the αx axis: across the grooves
    return rho_d, _rgb(rho_s, res), np.stack([ax, ay], -1), n, phi + np.pi / 2


def satin_like(rng, res):
    """Satin cloth: coloured ρd 0.15-0.6 with a soft two-tone motif, ρs 0.5-3, αx 0.15-0.45 across the threads and
    αx / αy 2-6, the thread direction turning by up to 30° across the sample, gentle drape up to 4°."""
    c0, c1 = rng.uniform(0.15, 0.6, 3), rng.uniform(0.15, 0.6, 3)
    motif = 0.5 + 0.5 * np.tanh(2 * _field(rng, res, 25))
    rho_d = c0 + (c1 - c0) * motif[..., None]
    rho_s = rng.uniform(0.5, 3.0) * (1 + 0.06 * _field(rng, res, 20))
    ax = rng.uniform(0.15, 0.45) * (1 + 0.1 * _field(rng, res, 30))
    ay = ax / rng.uniform(2, 6)
    phi = rng.uniform(0, np.pi) + np.radians(rng.uniform(10, 30)) * np.tanh(_field(rng, res, 60))
    n = _normals_from_height(_field(rng, res, 35), rng.uniform(1, 4))
    return rho_d, _rgb(rho_s, res), np.stack([ax, ay], -1), n, phi


def paper_like(rng, res):
    """Bright paper: stock ρd 0.75-0.85 (warm or cool white), a printed motif of darker ink (ρd 0.05-0.4, ~25 % of
    the area, 10-20 mm shapes), a weak rough lobe (ρs 0.1-0.4, α 0.2-0.65, the ink a little glossier), embossing
    that tilts the surface by up to 12° over ~20 mm."""
    stock = rng.uniform(0.75, 0.85) * np.array([1.0, rng.uniform(0.96, 1.0), rng.uniform(0.9, 1.0)])
    ink = rng.uniform(0.05, 0.4, 3)
    f = _field(rng, res, rng.uniform(10, 20))
    printed = 0.5 + 0.5 * np.tanh(6 * (f - np.quantile(f, 0.75)))
    rho_d = stock + (ink - stock) * printed[..., None]
    rho_s = rng.uniform(0.1, 0.25) + rng.uniform(0.0, 0.15) * printed
    a_stock = rng.uniform(0.35, 0.65) * (1 + 0.05 * _field(rng, res, 30))
    a = a_stock + (rng.uniform(0.2, 0.35) - a_stock) * printed
    n = _normals_from_height(_field(rng, res, 20), rng.uniform(6, 12))
    return rho_d, _rgb(rho_s, res), np.stack([a, a], -1), n, np.zeros((res, res))


_KINDS = {"ceramic_like": ceramic_like, "brushed_like": brushed_like, "satin_like": satin_like,
          "paper_like": paper_like}


def unseen_maps(kind: str, seed: int, resolution: int = RESOLUTION, relief: tuple[float, float] | None = None
                ) -> SVBRDFMaps:
    """One composition of `kind` (UNSEEN_KINDS), drawn from np.random.default_rng([seed, index of kind]). `relief`
    (feature mm, largest tilt in degrees) replaces the kind's normals by a relief of that scale, drawn next from the
    same generator: finer than a texel, it is outside the band limit above (docs/accuracy.md, Known limits, "Relief
    finer than a texel"); `resolution` must then resolve it (512 for 2 mm features over 120 mm)."""
    rng = np.random.default_rng([seed, UNSEEN_KINDS.index(kind)])
    rho_d, rho_s, alpha, normal, phi = _KINDS[kind](rng, resolution)
    if relief is not None:
        normal = _normals_from_height(_field(rng, resolution, relief[0]), relief[1])
    return SVBRDFMaps(rho_d=np.clip(rho_d, 0, 1), rho_s=np.clip(rho_s, 0, 20), alpha=alpha, normal=normal,
                      tangent=_tangent(phi, normal), transparency=np.zeros((resolution, resolution)),
                      size_mm=BUILTIN_SIZE_MM, name=f"{kind}@{seed}")


def write_unseen(kind: str, seed: int, directory, **options) -> str:
    """Write `unseen_maps(kind, seed, **options)` as an OpenSVBRDF map folder; returns its path."""
    return str(write_maps(unseen_maps(kind, seed, **options), directory))
