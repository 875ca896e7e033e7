"""The material suite: one procedural sample per OpenSVBRDF category, plus `quadrants` (docs/accuracy.md).

    SUITE_SAMPLES                      ("satin", "wood", "paper", "metal", "leather", "ceramic", "woven",
                                        "fabric", "wallpaper", "quadrants"), registered in twin.materials.samples (its SUITE)
    twin.materials.samples.builtin_sample(name, resolution, seed)   the maps (seed varies the composition)
    summary(name)                      its one-line character (`hemicube samples list`, with
                                       twin.materials.samples.parameter_ranges)

Why. `hemicube validate` was tuned on `ramps` alone. OpenSVBRDF's 1,000 samples fall in nine classes (satin
120, wood 300, paper 100, metal 35, leather 180, ceramic 34, woven 30, fabric 105, wallpaper 96; reference
§8) whose parameter statistics differ sharply (the paper's Fig. 12): strong anisotropy in satin, wood and
woven; ρd near zero for metal; a narrow, weak highlight for ceramic; rough, weakly specular paper and
fabric; relief in leather and wallpaper. The reference fits each class with its own roughness and specular
ranges (reference §5 `OBJECT_CONFIG`: axay_range up to 1.0 for wood and woven, ps_range 20 for paper), so
the classes reach α up to ~1 and ρs up to 20. Each builder here reproduces its class's character; together
they span α 0.01-0.6, αx/αy up to 8, ρd 0.01-0.9, ρs up to 18 (paper's foil) and normal tilts up to 25°.

Conventions (twin.materials.samples): row i along +y, column j along +x, `grid_uv`'s u (x) and v (y) in (0, 1); the
tangent is the αx axis. Builders follow the physics of fibres and grooves: a cylinder (fibre, thread,
brush groove) spreads reflected light ACROSS its axis, so the larger roughness is across the fibre; the
tangent is put across the fibre so that αx ≥ αy holds as built (the reference's export convention, §5).

Scale. Sizes are fractions of the sample side, so a builder draws the same sample at every resolution.
The suite is band-limited to what the 48² reconstruction grid (2.2 mm texels on the mini rig) can
represent: relief and colour features are ≥ ~11 mm (≥ 5 grid texels, ≥ 12 map texels at 128²) and
smooth, sharp edges only bound regions ≥ ~8 mm (printed words, finishes), and texel-scale noise (streaks,
pores) is kept to ≤ ±10% on ρs and α. Why: a grid texel measures the average over its footprint (std ~1 mm: the ~1.1 mm pixel, the
bilinear lookup and the extraction's anti-aliasing Gaussian, reconstruction.stages.extraction), while the score
compares with the true maps at the texel centre. Measured on a first draft with 6-8.5 mm leather pebbles:
the TRUE maps rendered at the texel centres matched the held-out photo with SSIM 0.75 (the fitted maps:
0.99) and the normal error was 5.7°; 6 mm fabric ribs gave 2.2°. Sub-grid texture is real (OpenSVBRDF
maps are 1024² over ~10 cm) but no 48² reconstruction can score on it (docs/accuracy.md, "footprint").

Seeds. Every random draw comes from `_rng(name, seed)` (np.random.default_rng([seed, id, 0 or 1])); the seed
picks the composition within the class (layout, directions, colours, finishes), so other seeds give
held-back variants of the same character (tests/test_material_suite.py).
"""
from __future__ import annotations

import re

import numpy as np
from scipy.ndimage import gaussian_filter

from twin.materials.fields import grid_uv, streak_noise, unit_rows

SUITE_SAMPLES = ("satin", "wood", "paper", "metal", "leather", "ceramic", "woven", "fabric", "wallpaper",
                 "quadrants")
_ID = {name: 100 + k for k, name in enumerate(SUITE_SAMPLES)}  # rng stream of each builder
_Z = np.array([0.0, 0.0, 1.0])


# Band limit (module docstring, "Scale"): a normal that turns by κ rad/mm broadens the lobe measured over the
# ~1 mm footprint by ~κ rad, so relief is kept to κ ≲ α / 4 along the roughness it turns across (e.g. ceramic:
# α ≥ 0.01, relief ≤ 2° over ≥ 40 mm features; woven: the 6° cross-section turns across αx ≈ 0.38).


# --- fields ----------------------------------------------------------------------------------------------
def _smooth_noise(rng: np.random.Generator, res: int, cells: float) -> np.ndarray:
    """Value noise in [-1, 1] with features ~1/cells of the sample side: a random lattice of ceil(cells) + 3
    knots per side, interpolated with the C1 smoothstep (separable), normalised to its largest value."""
    n = int(np.ceil(cells)) + 3
    knots = rng.uniform(-1.0, 1.0, (n, n))
    c = (np.arange(res) + 0.5) / res * cells + 1.0
    i = np.floor(c).astype(np.int64)
    f = c - i
    w = f * f * (3.0 - 2.0 * f)
    rows = knots[i] * (1.0 - w)[:, None] + knots[i + 1] * w[:, None]  # (res, n): interpolated along y
    out = rows[:, i] * (1.0 - w) + rows[:, i + 1] * w  # (res, res): then along x
    return out / max(float(np.abs(out).max()), 1e-12)


def _fbm(rng: np.random.Generator, res: int, cells: float, octaves: int) -> np.ndarray:
    """Octaves of _smooth_noise (cells, 2 cells, ...; amplitudes 1, 1/2, ...), normalised to [-1, 1]."""
    out = sum(0.5 ** k * _smooth_noise(rng, res, cells * 2 ** k) for k in range(octaves))
    return out / max(float(np.abs(out).max()), 1e-12)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _cells(rng: np.random.Generator, res: int, per_side: int):
    """Worley cells of a jittered grid (per_side² sites, one per grid cell, so cell sizes stay even):
    (index of the nearest site (H, W), distance to it, distance to the second nearest), distances in units
    of the sample side."""
    u, v = grid_uv(res)
    g = (np.arange(per_side) + 0.5) / per_side
    sx, sy = np.meshgrid(g, g, indexing="xy")
    jitter = rng.uniform(-0.35, 0.35, (2, per_side, per_side)) / per_side
    sites = np.stack([(sx + jitter[0]).ravel(), (sy + jitter[1]).ravel()], -1)
    d = np.hypot(u[..., None] - sites[:, 0], v[..., None] - sites[:, 1])  # (res, res, sites)
    order = np.argsort(d, axis=-1)[..., :2]
    d1 = np.take_along_axis(d, order[..., :1], -1)[..., 0]
    d2 = np.take_along_axis(d, order[..., 1:2], -1)[..., 0]
    return order[..., 0], d1, d2


def _slopes(height: np.ndarray, max_tilt_deg: float) -> np.ndarray:
    """(H, W, 2) surface slopes (∂h/∂x, ∂h/∂y) of a height field in any unit, scaled so that its steepest
    texel is tilted by max_tilt_deg (x along columns, y along rows)."""
    gy, gx = np.gradient(height.astype(np.float64))
    k = np.tan(np.radians(max_tilt_deg)) / max(float(np.hypot(gx, gy).max()), 1e-12)
    return k * np.stack([gx, gy], -1)


def _normals(slopes: np.ndarray) -> np.ndarray:
    """Unit normals n = normalise(−∂h/∂x, −∂h/∂y, 1) of surface slopes (H, W, 2)."""
    return unit_rows(np.concatenate([-slopes, np.ones(slopes.shape[:2] + (1,))], -1))


def _in_plane(phi: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    """Linear RGB of hue h ∈ [0, 1), saturation s, value v (the HSV hexcone)."""
    rgb = np.clip(np.abs(((h * 6.0 + np.array([0.0, 4.0, 2.0])) % 6.0) - 3.0) - 1.0, 0.0, 1.0)
    return v * (1.0 - s + s * rgb)


def _maps(res, rho_d, rho_s, alpha_x, alpha_y, normal, tangent_phi) -> dict:
    """The builder's dict (twin.materials.samples `_BUILDERS` contract): ρ broadcast to RGB, the tangent (cos φ, sin φ, 0)
    made orthogonal to the normal (the αx axis), αx ≥ αy (asserted by construction), opaque."""
    d = _in_plane(tangent_phi)
    t = unit_rows(d - np.sum(d * normal, -1, keepdims=True) * normal)
    rho_d = np.broadcast_to(np.asarray(rho_d)[..., None] if np.ndim(rho_d) == 2 else rho_d, (res, res, 3))
    rho_s = np.broadcast_to(np.asarray(rho_s)[..., None] if np.ndim(rho_s) == 2 else rho_s, (res, res, 3))
    return dict(rho_d=np.clip(rho_d, 0.0, 1.0), rho_s=np.clip(rho_s, 0.0, 20.0),
                alpha=np.stack(np.broadcast_arrays(alpha_x, alpha_y), -1), normal=normal, tangent=t,
                transparency=np.zeros((res, res)))


def _rng(name: str, seed: int, fine: bool = False) -> np.random.Generator:
    """The builder's generator; `fine`: a second one for texel-scale noise (_streak_noise draws a number of
    knots that grows with the resolution, so it must not shift the composition's draws)."""
    return np.random.default_rng([seed, _ID[name], int(fine)])


# --- the categories --------------------------------------------------------------------------------------
def _satin(res: int, seed: int, size_mm: float) -> dict:
    """satin: a damask satin, strongly anisotropic (Fig. 12: satin's αx/αy is the largest of the classes).
    Long floats of a smooth filament yarn run along the warp direction φ0 (seeded) with a gentle drape
    (±14°, ~50 mm waves); a damask motif (seeded fBm, ~30% of the area) is weft-faced, its floats turned
    by 90°, so the tangent field has two families with sharp motif edges. Across the floats αx 0.30-0.38,
    along them αy 0.045-0.07 (αx/αy 5-8; reference §5 gives satin axay_range 0.8); ρd a saturated colour,
    the weft a second one (value 0.25-0.6); ρs 1.6-2.8, glossier on the warp face; texel-scale streaks
    along the floats in ρs (±8%) and α (±5%); drape relief up to 6°."""
    rng = _rng("satin", seed)
    u, v = grid_uv(res)
    phi0 = rng.uniform(0.0, np.pi)
    motif = _fbm(rng, res, 3.0, 2)
    weft = motif > np.quantile(motif, rng.uniform(0.6, 0.75))
    fibre = phi0 + 0.25 * _smooth_noise(rng, res, 2.5) + np.where(weft, 0.5 * np.pi, 0.0)
    streak = streak_noise(_rng("satin", seed, fine=True), res, -np.sin(fibre) * u + np.cos(fibre) * v)  # along floats
    var = _smooth_noise(rng, res, 6.0)
    warp_c = _hsv(rng.uniform(), rng.uniform(0.5, 0.9), rng.uniform(0.35, 0.6))
    weft_c = _hsv(rng.uniform(), rng.uniform(0.3, 0.8), rng.uniform(0.25, 0.5))
    rho_d = np.where(weft[..., None], weft_c, warp_c) * (1.0 + 0.015 * var[..., None])
    rho_s = np.where(weft, 1.9, 2.5) * (1.0 + 0.08 * streak)
    alpha_y = np.where(weft, 0.065, 0.05) * (1.0 + 0.05 * streak) * (1.0 + 0.08 * var)
    alpha_x = 0.34 * (1.0 + 0.05 * streak) * (1.0 - 0.08 * var)
    relief = _smooth_noise(rng, res, 2.5) + 0.3 * _smooth_noise(rng, res, 5.0)
    return _maps(res, rho_d, rho_s, alpha_x, alpha_y, _normals(_slopes(relief, 6.0)), fibre + 0.5 * np.pi)


def _wood(res: int, seed: int, size_mm: float) -> dict:
    """wood: a flat-sawn board (Fig. 12: wood is anisotropic along the grain). The log's axis runs at a
    seeded angle near x or y; growth rings are the level sets of the distance to the pith (off the board,
    seeded), stretched along the axis into cathedral arches and wavy (fBm), 18-26 mm apart. Each ring goes
    smoothly from earlywood to a darker latewood (ρd x 0.6-0.75; a sharp latewood edge is below the 48²
    grid's band limit). Fibres follow the axis (±5° waves): αx (across) 0.30-0.42, αy (along) 0.07-0.1
    (αx/αy 4.4; reference §5: wood axay_range 1.0). Finish (seeded): oiled (ρs 0.4-0.7) or lacquered (ρs
    1.5-2.5, smoother); latewood is denser and glossier (ρs x 1.2, α x 0.85). Pores: streaks along the
    fibres in ρs (±8%) and α (±5%). Latewood ridges raise the surface: relief up to 3°, across the rings."""
    rng = _rng("wood", seed)
    u, v = grid_uv(res)
    axis = rng.uniform(-0.3, 0.3) + 0.5 * np.pi * rng.integers(2)
    x, y = u - 0.5, v - 0.5
    along = np.cos(axis) * x + np.sin(axis) * y
    across = -np.sin(axis) * x + np.cos(axis) * y
    pith = rng.choice([-1.0, 1.0]) * rng.uniform(0.7, 1.3)
    stretch = rng.uniform(0.15, 0.35)
    r = np.hypot(across - pith + 0.04 * _fbm(rng, res, 2.0, 2), stretch * along)
    late = (0.5 + 0.5 * np.sin(2 * np.pi * r / rng.uniform(0.15, 0.22))) ** 2  # rings 18-26 mm apart
    fibre = axis + 0.08 * _smooth_noise(rng, res, 3.0)
    streak = streak_noise(_rng("wood", seed, fine=True), res, -np.sin(fibre) * u + np.cos(fibre) * v)
    early_c = rng.uniform(0.35, 0.75) * np.array([1.0, 0.68, 0.40]) * (1 + 0.1 * rng.uniform(-1, 1, 3))
    late_c = early_c * rng.uniform(0.6, 0.75)
    rho_d = early_c + (late_c - early_c) * late[..., None]
    lacquer = bool(rng.integers(2))
    gloss = rng.uniform(1.5, 2.5) if lacquer else rng.uniform(0.4, 0.7)
    rho_s = gloss * (1.0 + 0.2 * late) * (1.0 + 0.08 * streak)
    smooth = (0.85 if lacquer else 1.0) * (1.0 - 0.15 * late)
    alpha_x = 0.42 * smooth * (1.0 + 0.05 * streak)
    alpha_y = 0.095 * smooth * (1.0 + 0.05 * streak)
    return _maps(res, rho_d, rho_s, alpha_x, alpha_y, _normals(_slopes(late, 3.0)), fibre + 0.5 * np.pi)


def _text_mask(rng: np.random.Generator, res: int, box: tuple) -> np.ndarray:
    """A block of printed 'words': lines 8 mm high every 16 mm inside box (u0, v0, u1, v1), words 8-30 mm
    long separated by 4-6 mm (fractions of a 120 mm side); (H, W) float in {0, 1}."""
    u, v = grid_uv(res)
    u0, v0, u1, v1 = box
    mask = np.zeros((res, res))
    pitch, height = 16.0 / 120.0, 8.0 / 120.0
    for top in np.arange(v0, v1 - height, pitch):
        row = (v >= top) & (v < top + height)
        x = u0
        while x < u1:
            w = rng.uniform(8.0, 30.0) / 120.0
            mask[row & (u >= x) & (u < min(x + w, u1))] = 1.0
            x += w + rng.uniform(4.0, 6.0) / 120.0
    return mask


def _paper(res: int, seed: int, size_mm: float) -> dict:
    """paper: a printed sheet with a foil stamp (Fig. 12: paper is rough and weakly specular; reference §5
    gives paper ps_range 20, the only class above 10, for coated and foiled stock). Base stock (seeded white,
    cream or coloured, ρd 0.6-0.9 ±1.5% flocs of ~5 mm): ρs 0.1-0.3, α 0.40-0.60 (rough), a slight
    machine-direction anisotropy (αx/αy 1.15). A block of printed 'words' (seeded layout, dark or coloured
    ink ρd 0.03-0.2, glossier: ρs 0.5-0.9, α 0.15-0.25; lines 8 mm high) on one half; on the other a
    hot-foil disc (gold or silver, ρd 0.02-0.04, ρs 11-18, α 0.04-0.08) pressed in: its rim is tilted up to
    15°. Cockle relief up to 2°."""
    rng = _rng("paper", seed)
    u, v = grid_uv(res)
    kind = rng.integers(3)
    stock = (np.array([0.88, 0.88, 0.85]), np.array([0.88, 0.80, 0.62]),
             _hsv(rng.uniform(), rng.uniform(0.2, 0.45), rng.uniform(0.6, 0.8)))[kind]
    rho_d = stock * (1.0 + 0.015 * _smooth_noise(rng, res, 24.0)[..., None])
    rho_s = rng.uniform(0.1, 0.3) * (1.0 + 0.1 * _smooth_noise(rng, res, 4.0))
    a = rng.uniform(0.45, 0.52) * (1.0 + 0.12 * _smooth_noise(rng, res, 3.0))
    alpha_x, alpha_y = a * 1.07, a / 1.07
    left = bool(rng.integers(2))  # text on the left half, foil on the right, or the other way round
    box = (0.06, 0.08, 0.48, 0.92) if left else (0.52, 0.08, 0.94, 0.92)
    ink = _text_mask(rng, res, box)
    ink_c = rng.uniform(0.03, 0.08) * np.ones(3) if rng.integers(2) else _hsv(rng.uniform(), 0.8, 0.2)
    rho_d = rho_d + (ink_c - rho_d) * ink[..., None]
    rho_s = rho_s + (rng.uniform(0.5, 0.9) - rho_s) * ink
    ink_a = rng.uniform(0.15, 0.25)
    alpha_x, alpha_y = alpha_x + (ink_a - alpha_x) * ink, alpha_y + (ink_a - alpha_y) * ink
    cx = rng.uniform(0.68, 0.78) if left else rng.uniform(0.22, 0.32)
    cy, radius = rng.uniform(0.35, 0.65), rng.uniform(0.13, 0.17)
    r = np.hypot(u - cx, v - cy)
    foil = (r < radius).astype(np.float64)
    metal = np.array([1.0, 0.78, 0.42]) if rng.integers(2) else np.array([1.0, 1.0, 1.0])
    rho_d = rho_d + (rng.uniform(0.02, 0.04) * metal - rho_d) * foil[..., None]
    rho_s = rho_s[..., None] + (rng.uniform(11.0, 18.0) * metal - rho_s[..., None]) * foil[..., None]
    fa = rng.uniform(0.04, 0.08)
    alpha_x, alpha_y = alpha_x + (fa - alpha_x) * foil, alpha_y + (fa - alpha_y) * foil
    press = _smoothstep(radius - 0.02, radius + 0.01, r)  # the die's bevel: 3.6 mm wide
    slopes = _slopes(press, 15.0) + _slopes(_fbm(rng, res, 2.0, 2), 2.0)
    return _maps(res, rho_d, rho_s, alpha_x, alpha_y, _normals(slopes), np.full((res, res), 0.5 * np.pi))


# metal colours: the tint of ρs (reference §5 fits coloured ρs; F0 is grey, so the tint lives in ρs)
METALS = {"steel": (1.0, 0.97, 0.93), "gold": (1.0, 0.78, 0.38), "copper": (1.0, 0.62, 0.48),
          "aluminium": (1.0, 1.0, 1.0)}


def _metal(res: int, seed: int, size_mm: float) -> dict:
    """metal: a plate in four finishes (Fig. 12: ρd near zero for metal). A jittered 2 x 2 Voronoi layout
    (seeded) holds one patch each of polished (α 0.02-0.03), brushed (αx 0.22-0.28 across the brushing,
    αy 0.03-0.04 along it, αx/αy ~7, a seeded direction, texel-scale streaks), bead-blasted (α 0.25-0.31)
    and hammered (α 0.08-0.1, concave dimples ~20 mm wide, tilted up to 8°), in a seeded order. ρd 0.01-0.04
    (smooth), ρs 5-9 tinted steel, gold, copper or aluminium (seeded), ±5%."""
    rng = _rng("metal", seed)
    u, v = grid_uv(res)
    label, _, _ = _cells(rng, res, 2)
    finish = rng.permutation(4)[label]  # 0 polished, 1 brushed, 2 blasted, 3 hammered
    tint = np.array(list(METALS.values())[rng.integers(len(METALS))])
    rho_s = rng.uniform(5.0, 9.0) * tint * (1.0 + 0.05 * _smooth_noise(rng, res, 4.0)[..., None])
    rho_d = (0.025 + 0.015 * _smooth_noise(rng, res, 3.0))[..., None] * np.ones(3)
    brush = rng.uniform(0.0, np.pi)
    streak = streak_noise(_rng("metal", seed, fine=True), res, -np.sin(brush) * u + np.cos(brush) * v)
    n_iso = _smooth_noise(rng, res, 4.0)
    iso = np.select([finish == 0, finish == 2], [0.025, 0.28], 0.09) * (1.0 + 0.1 * n_iso)
    alpha_x = np.where(finish == 1, 0.25 * (1.0 + 0.1 * streak), iso)
    alpha_y = np.where(finish == 1, 0.035 * (1.0 + 0.1 * streak), iso)
    _, d1, _ = _cells(rng, res, 6)
    dimples = _slopes(d1 ** 2, 8.0) * (finish == 3)[..., None]
    rho_s = rho_s * np.where(finish == 1, 1.0 + 0.08 * streak, 1.0)[..., None]
    return _maps(res, rho_d, rho_s, alpha_x, alpha_y, _normals(dimples), np.full((res, res), brush + 0.5 * np.pi))


def _leather(res: int, seed: int, size_mm: float) -> dict:
    """leather: a hide embossed with a coarse pebble (reptile-like) grain (Fig. 12: leather is isotropic with
    strong relief). Worley pebbles 20-24 mm across (5-6 per side, seeded), flat-topped (quartic) domes
    falling into rounded creases, tilted up to 25° there, plus slow wrinkles (≤ 4°). Colour (seeded: tan,
    brown, oxblood, black) darkens towards the creases (x 0.6) and varies smoothly pebble to pebble (±8%):
    ρd 0.02-0.39. The tops are worn glossy: ρs 0.5-1.2 on tops, half that in the creases; α 0.18 on tops to
    0.40 in the creases (correlated with relief: a 'bumpy leather'). Finer grain, or creases
    sharper than ~2 mm, would be below the 48² grid's band limit (module docstring)."""
    rng = _rng("leather", seed)
    cells = int(rng.integers(5, 7))
    _, d1, _ = _cells(rng, res, cells)
    per = _smooth_noise(rng, res, float(cells))  # pebble-to-pebble variation, continuous across the creases
    # paraboloid pebbles meeting in V creases, the creases rounded (a Gaussian of 2 mm on a 120 mm side: a
    # V narrower than the grid's footprint is not ground truth a 48² grid can score, module docstring)
    dome = gaussian_filter(-(d1 * cells) ** 4, 2.0 / 120.0 * res, mode="nearest")
    crease = (dome.max() - dome) / (dome.max() - dome.min())  # 0 on the highest top, 1 in the deepest crease
    colour = (np.array([0.36, 0.20, 0.09]), np.array([0.20, 0.10, 0.05]), np.array([0.24, 0.05, 0.05]),
              np.array([0.045, 0.04, 0.04]))[rng.integers(4)]
    rho_d = colour * ((1.0 - 0.4 * crease) * (1.0 + 0.08 * per))[..., None]
    rho_s = rng.uniform(0.5, 1.2) * (1.0 - 0.5 * crease)
    a = (0.18 + 0.22 * crease) * (1.0 + 0.05 * per)
    slopes = _slopes(dome, 25.0) + _slopes(_smooth_noise(rng, res, 3.0), 4.0)
    return _maps(res, rho_d, rho_s, a, a, _normals(slopes), np.zeros((res, res)))


def _ceramic(res: int, seed: int, size_mm: float) -> dict:
    """ceramic: a glazed tile with a painted decoration (Fig. 12: ceramic has a narrow, weak highlight).
    Glaze (seeded white, cream or celadon, ρd 0.55-0.88) with brushed decoration (seeded cobalt, iron red or
    black; soft brush edges over ~4 mm, ~35% of the area). The glaze is a thin smooth film: α 0.01-0.035
    with slow thickness changes (~40 mm), ρs 0.3-0.7 (weak); the paint roughens it (α x 1.3). Glaze
    undulation up to 2° over ~40 mm."""
    rng = _rng("ceramic", seed)
    glaze = (np.array([0.86, 0.86, 0.84]), np.array([0.84, 0.78, 0.62]), np.array([0.55, 0.70, 0.60]))[rng.integers(3)]
    deco = (np.array([0.05, 0.09, 0.45]), np.array([0.45, 0.10, 0.05]), np.array([0.04, 0.04, 0.04]))[rng.integers(3)]
    f = _fbm(rng, res, 4.0, 2)
    paint = _smoothstep(*np.quantile(f, [0.58, 0.72]), f)
    rho_d = glaze + (deco - glaze) * paint[..., None]
    rho_s = rng.uniform(0.3, 0.7) * (1.0 + 0.05 * _smooth_noise(rng, res, 3.0))
    a = np.exp(np.log(0.01) + np.log(3.5) * (0.5 + 0.5 * _smooth_noise(rng, res, 3.0))) * (1.0 + 0.3 * paint)
    slopes = _slopes(_smooth_noise(rng, res, 3.0), 2.0)
    return _maps(res, rho_d, rho_s, a, a, _normals(slopes), np.zeros((res, res)))


def _woven(res: int, seed: int, size_mm: float) -> dict:
    """woven: a coarse weave of flat ribbon yarn (Fig. 12: woven is strongly anisotropic). Threads 18-24 mm
    wide in a seeded weave (plain, 2/2 twill or 2 x 2 basket) at a seeded angle: the tangent is across the
    top thread, so two orthogonal families alternate cell by cell. αx (across) 0.34-0.42, αy (along)
    0.05-0.065 (αx/αy 6.5; reference §5: woven axay_range 1.0), per-thread ±8%. Each thread is curved
    across (tilt up to 6° at its edges; the lobe is wide that way) and flat along. Warp and weft colours
    seeded (value 0.3-0.6), thread edges shaded (x 0.85); ρs 0.8-1.4."""
    rng = _rng("woven", seed)
    u, v = grid_uv(res)
    width = rng.uniform(18.0, 24.0) / 120.0
    theta = rng.uniform(0.0, np.pi)
    x, y = u - 0.5, v - 0.5
    a = (np.cos(theta) * x + np.sin(theta) * y) / width
    b = (-np.sin(theta) * x + np.cos(theta) * y) / width
    cj, ci = np.floor(a).astype(np.int64), np.floor(b).astype(np.int64)
    kind = rng.integers(3)
    warp = ((ci + cj) % 2 == 0, (cj - ci) % 4 < 2, ((ci // 2) + (cj // 2)) % 2 == 0)[kind]
    fa, fb = 2.0 * (a - cj) - 1.0, 2.0 * (b - ci) - 1.0  # (-1, 1) across the warp / the weft thread
    across = np.where(warp, fa, fb)
    thread_dir = np.where(warp, theta + 0.5 * np.pi, theta)  # warp threads run along b, weft along a
    cj, ci = cj - cj.min(), ci - ci.min()  # thread indices from 0
    var = np.where(warp, rng.uniform(-1, 1, cj.max() + 1)[cj], rng.uniform(-1, 1, ci.max() + 1)[ci])  # per thread
    warp_c = _hsv(rng.uniform(), rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.6))
    weft_c = _hsv(rng.uniform(), rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.6))
    shade = 1.0 - 0.15 * _smoothstep(0.4, 1.0, np.abs(across))
    rho_d = np.where(warp[..., None], warp_c, weft_c) * shade[..., None]
    rho_s = rng.uniform(0.8, 1.4) * shade
    alpha_x = 0.38 * (1.0 + 0.08 * var)
    alpha_y = 0.058 * (1.0 + 0.08 * var)
    tilt = np.tan(np.radians(6.0)) * across  # the thread's cross-section, cylinder-like
    normal = unit_rows(_Z + tilt[..., None] * _in_plane(thread_dir + 0.5 * np.pi))
    return _maps(res, rho_d, rho_s, alpha_x, alpha_y, normal, thread_dir + 0.5 * np.pi)


def _fabric(res: int, seed: int, size_mm: float) -> dict:
    """fabric: a cotton or wool cloth with a printed or yarn-dyed pattern (Fig. 12: fabric is rough,
    weakly specular and mildly anisotropic). Seeded pattern: stripes or a gingham check, 20-30 mm period,
    soft edges; light ground (value 0.55-0.8) and a darker colour (value 0.25-0.45): ρd 0.1-0.8. Rough:
    αx 0.5-0.6 across the warp, αy 0.3-0.37 along it (αx/αy ~1.6); ρs 0.15-0.35. Soft folds (~40 mm) tilt
    it up to 6° (a knit's or twill's millimetre relief is below the 48² grid's band limit)."""
    rng = _rng("fabric", seed)
    u, v = grid_uv(res)
    theta = rng.uniform(0.0, np.pi)
    x, y = u - 0.5, v - 0.5
    a = np.cos(theta) * x + np.sin(theta) * y
    b = -np.sin(theta) * x + np.cos(theta) * y
    period = rng.uniform(20.0, 30.0) / 120.0
    band = lambda c: _smoothstep(0.05, 0.45, np.abs(((c / period) % 1.0) - 0.5))  # noqa: E731  0 inside a stripe
    # gingham: where both stripe sets cross the colour is full, where one crosses it is half; else stripes
    mix = 0.5 * (2.0 - band(a) - band(b)) if rng.integers(2) else 1.0 - band(a)
    ground = _hsv(rng.uniform(), rng.uniform(0.0, 0.3), rng.uniform(0.55, 0.8))
    colour = _hsv(rng.uniform(), rng.uniform(0.5, 0.9), rng.uniform(0.25, 0.45))
    rho_d = ground + (colour - ground) * mix[..., None]
    n = _smooth_noise(rng, res, 5.0)
    rho_s = rng.uniform(0.18, 0.3) * (1.0 + 0.15 * n)
    alpha_x = 0.55 * (1.0 + 0.1 * n)
    alpha_y = 0.34 * (1.0 + 0.1 * n)
    folds = _smooth_noise(rng, res, 3.0)  # soft folds of the cloth
    return _maps(res, rho_d, rho_s, alpha_x, alpha_y, _normals(_slopes(folds, 6.0)), np.full((res, res), theta))


def _wallpaper(res: int, seed: int, size_mm: float) -> dict:
    """wallpaper: embossed vinyl with a metallic-ink ornament (Fig. 12: wallpaper is mostly isotropic, with
    relief and glossy inks). A seeded damask-like repeat (two cosine lattices, 40-60 mm period, rotated)
    with soft edges; ink: ρd 0.08-0.2 tinted, ρs 2-5 gold, silver or pearl, α 0.1-0.15; ground: matte (ρd
    value 0.4-0.8, ρs 0.2-0.4, α 0.35-0.45). The ornament is embossed (tilt up to 6° at its edges) on a
    vinyl grain (≤ 2°, ~10 mm)."""
    rng = _rng("wallpaper", seed)
    u, v = grid_uv(res)
    k = rng.integers(2, 4)
    rot = rng.uniform(0.0, 0.5 * np.pi)
    a = np.cos(rot) * u + np.sin(rot) * v + rng.uniform()
    b = -np.sin(rot) * u + np.cos(rot) * v + rng.uniform()
    f = np.cos(2 * np.pi * k * a) * np.cos(2 * np.pi * k * b) + 0.5 * np.cos(2 * np.pi * (k * (a + b) + rng.uniform()))
    ink = _smoothstep(-0.2, 1.0, f)
    tint = (np.array([1.0, 0.8, 0.45]), np.array([1.0, 1.0, 1.0]), np.array([0.95, 0.9, 1.0]))[rng.integers(3)]
    ground = _hsv(rng.uniform(), rng.uniform(0.2, 0.6), rng.uniform(0.4, 0.8))
    rho_d = ground + (rng.uniform(0.08, 0.2) * tint - ground) * ink[..., None]
    gloss = rng.uniform(0.2, 0.4)
    rho_s = gloss + (rng.uniform(2.0, 5.0) * tint - gloss) * ink[..., None]
    a_ground, a_ink = rng.uniform(0.35, 0.45), rng.uniform(0.10, 0.15)
    a_ = a_ground + (a_ink - a_ground) * ink
    slopes = _slopes(ink, 6.0) + _slopes(_smooth_noise(rng, res, 12.0), 2.0)
    return _maps(res, rho_d, rho_s, a_, a_, _normals(slopes), np.zeros((res, res)))


QUADRANT_RATIOS = (1.0, 2.0, 4.0, 8.0)


def _quadrants(res: int, seed: int, size_mm: float) -> dict:
    """quadrants (the suite's unseen sample): four quadrants of anisotropy αx/αy = 1, 2, 4, 8 (seeded
    order). In each, the roughness sqrt(αx αy) ramps log-linearly 0.02 -> 0.3 along +x (αx = that · sqrt(r),
    αy = that / sqrt(r), then αx ≤ 0.6 and αy ≥ 0.01, which lowers r at the ends of the r = 8 ramp), the
    normal tilts 0 -> 20° along +y towards a seeded azimuth, and the tangent turns by 90° from a seeded
    angle along the diagonal. ρd (value 0.1-0.6, seeded colour) and ρs (1-5) are constant per quadrant."""
    rng = _rng("quadrants", seed)
    u, v = grid_uv(res)
    q = 2 * (v >= 0.5) + (u >= 0.5)
    s, t = (u % 0.5) / 0.5, (v % 0.5) / 0.5  # in (0, 1) inside each quadrant
    ratio = np.array(QUADRANT_RATIOS)[rng.permutation(4)][q]
    rough = 0.02 * (0.3 / 0.02) ** s
    alpha_x = np.minimum(rough * np.sqrt(ratio), 0.6)
    alpha_y = np.maximum(rough / np.sqrt(ratio), 0.01)
    azimuth = rng.uniform(0.0, 2 * np.pi, 4)[q]
    tilt = np.radians(20.0) * t
    normal = np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)], -1)
    phi = rng.uniform(0.0, np.pi, 4)[q] + 0.25 * np.pi * (s + t)
    rho_d = np.stack([_hsv(rng.uniform(), rng.uniform(0.0, 0.6), rng.uniform(0.1, 0.6)) for _ in range(4)])[q]
    rho_s = rng.uniform(1.0, 5.0, 4)[q]
    return _maps(res, rho_d, rho_s, alpha_x, alpha_y, normal, phi)


BUILDERS = {"satin": _satin, "wood": _wood, "paper": _paper, "metal": _metal, "leather": _leather,
            "ceramic": _ceramic, "woven": _woven, "fabric": _fabric, "wallpaper": _wallpaper,
            "quadrants": _quadrants}
def summary(name: str) -> str:
    """A suite sample's one-line character: its builder's docstring, first sentence after the name."""
    doc = re.sub(r"\s*\(Fig\. [^)]*\)", "", " ".join(BUILDERS[name].__doc__.split()))  # the paper's figure
    return doc.split(": ", 1)[1].split(". ")[0]
