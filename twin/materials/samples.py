"""SVBRDF texture maps (the OpenSVBRDF map contract, reference §7.1) and built-in synthetic samples.

    SVBRDFMaps(rho_d, rho_s, alpha, normal, tangent, transparency, size_mm, name)   validated, immutable
    texel_positions(maps, sample_plane) -> (H, W, 3) mm      world_to_texel(maps, sample_plane, xyz) -> (..., 2)
    write_maps(maps, directory, overwrite=False)             read_maps(directory, size_mm=None)
    canonical_anisotropy(maps) -> maps with αx ≥ αy (the reference's export convention)
    builtin_sample(name, resolution=128, seed=0, size_mm=120.0)   BUILTIN_SAMPLES = ("ramps", "brushed_metal",
                                          "satin_weave") + the material suite (twin.materials.suite: satin, wood,
                                          paper, metal, leather, ceramic, woven, fabric, wallpaper, quadrants)
    load_sample(name_or_dir, resolution=128) -> SVBRDFMaps      (a name, "NAME@SEED" or a map folder)

Parameters (per texel, all float32)
    rho_d (H, W, 3)        diffuse albedo ρd ∈ [0, 1] (linear RGB)
    rho_s (H, W, 3)        specular albedo ρs ∈ [0, 20] (the reference's ps_range is 10, 20 for paper)
    alpha (H, W, 2)        GGX roughness (αx, αy) ∈ [0.001, 1.5]; αx is along the tangent t
    normal (H, W, 3)       unit shading normal n, world frame (twin.rig.units), n_z > 0
    tangent (H, W, 3)      unit tangent t ⟂ n, world frame: the αx axis; b = n × t is the αy axis
    transparency (H, W)    β ∈ [0, 1], the fraction of bottom light let through (0 = opaque)
    size_mm                side of the square sample (mm); texels are square, so H == W

Orientation (reference §7.1)
    Texel row i ↔ world y increasing, column j ↔ world x increasing, row 0 at the minimum y (so an image
    viewer, row 0 on top, shows the sample from above mirrored in y). The maps are centred on the sample
    plane's origin (rig.sample, (0, 0, −122) mm), columns along `sample_plane.x_axis`, rows along its
    y_axis = normal × x_axis; texel (i, j) has its centre at
        x = −size/2 + (j + 0.5)·size/W,   y = −size/2 + (i + 0.5)·size/H   (in plane coordinates).
    `world_to_texel` uses the texel-centre convention: the centre of texel (i, j) is (row, col) = (i, j).
    Normals and tangents are world-frame vectors, as in the reference's normal/tangent textures.

Folder format (`write_maps` / `read_maps`): the reference's file names, EXR float32 RGB:
    pd_texture.exr (ρd), ps_texture.exr (ρs), ax_ay_texture.exr (αx, αy, 0), normal_texture.exr
    (n·0.5 + 0.5), tangent_texture.exr (t·0.5 + 0.5), and two files of this project:
    transparency_texture.exr (β in R = G = B; optional on read, default 0 = opaque) and sample.toml
    (format = "hemicube-sample", version, name, size_mm; optional on read: the size then comes from the
    `size_mm` argument or defaults to 150 mm, the name from the folder).
"""
from __future__ import annotations

import math
import operator
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tomli_w

from twin.atomic import atomic_folder
from twin.materials.exr import ExrError, check_finite, read_rgb_exr, write_rgb_exr
from twin.materials.fields import grid_uv, streak_noise, unit_rows
from twin.materials.suite import BUILDERS as SUITE_BUILDERS, SUITE_SAMPLES, summary

SAMPLE_FORMAT = "hemicube-sample"
SAMPLE_FORMAT_VERSION = 1
DEFAULT_SIZE_MM = 150.0  # the largest sample of the rig (reference §1.5), used when a folder says nothing
BUILTIN_SIZE_MM = 120.0
MAX_SIZE_MM = 150.0

RHO_D_RANGE = (0.0, 1.0)
RHO_S_RANGE = (0.0, 20.0)
ALPHA_RANGE = (0.001, 1.5)
UNIT_TOL = 1e-3
ORTHO_TOL = 1e-3
# Decoding tolerance on |2e − 1| before renormalising: 8-bit maps are off by ≤ √3/255 ≈ 0.007.
DECODE_UNIT_TOL = 0.05

MAP_FILES = {
    "rho_d": "pd_texture.exr",
    "rho_s": "ps_texture.exr",
    "alpha": "ax_ay_texture.exr",
    "normal": "normal_texture.exr",
    "tangent": "tangent_texture.exr",
    "transparency": "transparency_texture.exr",
}
SAMPLE_TOML = "sample.toml"
_CHANNELS = {"rho_d": 3, "rho_s": 3, "alpha": 2, "normal": 3, "tangent": 3, "transparency": None}


class SampleError(ValueError):
    """SVBRDF maps are invalid or cannot be read. `field` names the offending map when there is one."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=np.float32)  # always a copy: the maps own their arrays
    a.flags.writeable = False
    return a


def _texel(mask: np.ndarray) -> tuple[int, int]:
    i, j = np.argwhere(mask)[0][:2]
    return int(i), int(j)


def _fmt(v) -> str:
    v = np.atleast_1d(np.asarray(v, dtype=np.float64))
    return "(" + ", ".join(f"{x:.6g}" for x in v) + ")" if v.size > 1 else f"{v[0]:.6g}"


@dataclass(frozen=True, eq=False)
class SVBRDFMaps:
    """Validated, immutable per-texel SVBRDF parameters (see the module docstring for every convention).
    Arrays are stored as read-only float32 copies; `dataclasses.replace` re-validates."""

    rho_d: np.ndarray
    rho_s: np.ndarray
    alpha: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    transparency: np.ndarray
    size_mm: float
    name: str = "sample"

    ARRAYS = ("rho_d", "rho_s", "alpha", "normal", "tangent", "transparency")

    def __post_init__(self):
        for k in self.ARRAYS:
            try:
                object.__setattr__(self, k, _frozen(getattr(self, k)))
            except (TypeError, ValueError) as e:
                raise SampleError(f"{k}: not a numeric array ({e})", k) from None
        _validate(self)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) in texels."""
        return self.rho_d.shape[:2]

    @property
    def resolution(self) -> int:
        return self.rho_d.shape[0]

    @property
    def texel_mm(self) -> float:
        """Side of one (square) texel in mm."""
        return self.size_mm / self.rho_d.shape[1]

    @property
    def alpha_x(self) -> np.ndarray:
        return self.alpha[..., 0]

    @property
    def alpha_y(self) -> np.ndarray:
        return self.alpha[..., 1]

    @property
    def bitangent(self) -> np.ndarray:
        """b = n × t, the αy axis (H, W, 3) float32."""
        return np.cross(self.normal, self.tangent).astype(np.float32)


def _validate(m: SVBRDFMaps) -> None:
    rd = m.rho_d
    if rd.ndim != 3 or rd.shape[2] != 3 or rd.shape[0] < 1 or rd.shape[1] < 1:
        raise SampleError(f"rho_d: expected shape (H, W, 3), got {rd.shape}", "rho_d")
    h, w = rd.shape[:2]
    if h != w:
        raise SampleError(f"rho_d: the sample is square with square texels, so H must equal W; got "
                          f"{h} x {w}", "rho_d")
    for k, c in _CHANNELS.items():
        a = getattr(m, k)
        want = (h, w) if c is None else (h, w, c)
        if a.shape != want:
            raise SampleError(f"{k}: expected shape {want} (like rho_d), got {a.shape}", k)
    def reject(k, bad, message):
        """Raise for the first texel where `bad` (per texel or per channel) holds."""
        bad = bad.any(axis=2) if bad.ndim == 3 else bad
        if bad.any():
            i, j = _texel(bad)
            raise SampleError(message(getattr(m, k)[i, j], i, j, int(bad.sum())), k)

    for k in m.ARRAYS:
        reject(k, ~np.isfinite(getattr(m, k)), lambda v, i, j, n, k=k:
               f"{k}: non-finite value {_fmt(v)} at texel (row {i}, col {j}) ({n} bad texels)")
    for k, (lo, hi) in (("rho_d", RHO_D_RANGE), ("rho_s", RHO_S_RANGE), ("alpha", ALPHA_RANGE),
                        ("transparency", (0.0, 1.0))):
        a = getattr(m, k)
        reject(k, (a < lo) | (a > hi), lambda v, i, j, n, k=k, lo=lo, hi=hi:
               f"{k}: value {_fmt(v)} at texel (row {i}, col {j}) is outside [{lo:g}, {hi:g}] "
               f"({n} texels out of range)")
    for k in ("normal", "tangent"):
        a = getattr(m, k)
        norm = np.linalg.norm(a.astype(np.float64), axis=2)
        bad = np.abs(norm - 1.0) > UNIT_TOL
        if bad.any():
            i, j = _texel(bad)
            raise SampleError(f"{k}: not a unit vector at texel (row {i}, col {j}): {_fmt(a[i, j])}, "
                              f"length {norm[i, j]:.6g} (tolerance ±{UNIT_TOL:g})", k)
    bad = m.normal[..., 2] <= 0.0
    if bad.any():
        i, j = _texel(bad)
        raise SampleError(f"normal: {_fmt(m.normal[i, j])} at texel (row {i}, col {j}) is not in the upper "
                          "hemisphere (n_z must be > 0)", "normal")
    dot = np.einsum("ijk,ijk->ij", m.normal.astype(np.float64), m.tangent.astype(np.float64))
    bad = np.abs(dot) >= ORTHO_TOL
    if bad.any():
        i, j = _texel(bad)
        raise SampleError(f"tangent: not perpendicular to the normal at texel (row {i}, col {j}): "
                          f"t·n = {dot[i, j]:.6g} (|t·n| must be < {ORTHO_TOL:g})", "tangent")
    s = m.size_mm
    if isinstance(s, bool) or not isinstance(s, (int, float, np.integer, np.floating)):
        raise SampleError(f"size_mm: expected a number of millimetres, got {s!r}", "size_mm")
    s = float(s)
    if not (math.isfinite(s) and 0.0 < s <= MAX_SIZE_MM):
        raise SampleError(f"size_mm: {s:g} mm is outside (0, {MAX_SIZE_MM:g}] (the rig takes samples up to "
                          f"{MAX_SIZE_MM:g} mm square)", "size_mm")
    object.__setattr__(m, "size_mm", s)
    if not isinstance(m.name, str) or not m.name.strip():
        raise SampleError(f"name: expected a non-empty string, got {m.name!r}", "name")


# --- geometry --------------------------------------------------------------------------------------


def _plane_axes(sample_plane):
    o = np.asarray(sample_plane.origin, dtype=np.float64)
    x = np.asarray(sample_plane.x_axis, dtype=np.float64)
    y = np.asarray(sample_plane.y_axis, dtype=np.float64)
    return o, x, y


def _check_fits(maps: SVBRDFMaps, sample_plane) -> None:
    max_size = getattr(sample_plane, "max_size", None)
    if max_size is not None and maps.size_mm > max_size + 1e-9:
        raise SampleError(f"sample {maps.name!r} is {maps.size_mm:g} mm wide; the rig's sample plane takes "
                          f"at most {max_size:g} mm", "size_mm")


def grid_coordinates(size_mm: float, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Plane coordinates (mm, float64) of the centres of a square size_mm grid of shape (H, W) centred on the
    plane origin: x (W,) along columns and y (H,) along rows (the maps' convention, module docstring)."""
    h, w = shape
    x = -0.5 * size_mm + (np.arange(w) + 0.5) * (size_mm / w)
    y = -0.5 * size_mm + (np.arange(h) + 0.5) * (size_mm / h)
    return x, y


def grid_positions(size_mm: float, shape: tuple[int, int], sample_plane) -> np.ndarray:
    """World positions (mm, float64) of that grid's centres, (H, W, 3): origin + x·x_axis + y·y_axis. The
    reconstruction's texture grid (reconstruction.stages.extraction) uses the same convention as the maps."""
    o, ax, ay = _plane_axes(sample_plane)
    x, y = grid_coordinates(size_mm, shape)
    return o + x[None, :, None] * ax + y[:, None, None] * ay


def texel_positions(maps: SVBRDFMaps, sample_plane) -> np.ndarray:
    """World positions (mm, float64) of the texel centres, (H, W, 3)."""
    _check_fits(maps, sample_plane)
    return grid_positions(maps.size_mm, maps.shape, sample_plane)


def world_to_texel(maps: SVBRDFMaps, sample_plane, xyz) -> np.ndarray:
    """Continuous (row, col) (float64, shape (..., 2)) of world points (..., 3), projected along the plane
    normal; the centre of texel (i, j) is (i, j), the sample's edges are at −0.5 and H − 0.5 / W − 0.5."""
    p = np.asarray(xyz, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"xyz must have shape (..., 3), got {p.shape}")
    o, ax, ay = _plane_axes(sample_plane)
    h, w = maps.shape
    s = maps.size_mm
    d = p - o
    col = (d @ ax + 0.5 * s) * (w / s) - 0.5
    row = (d @ ay + 0.5 * s) * (h / s) - 0.5
    return np.stack([row, col], axis=-1)


def canonical_anisotropy(maps: SVBRDFMaps) -> SVBRDFMaps:
    """The reference's export convention (§5): where αx < αy, swap them and replace t by n × t, so that
    αx ≥ αy everywhere and t is the axis of the larger roughness. The BRDF is unchanged (D and the Smith
    G1 only see (h·t)²/αx² + (h·b)²/αy² and the analogous sum, and the new b is −t)."""
    swap = maps.alpha[..., 0] < maps.alpha[..., 1]
    if not swap.any():
        return maps
    alpha = np.where(swap[..., None], maps.alpha[..., ::-1], maps.alpha)
    nt = np.cross(maps.normal.astype(np.float64), maps.tangent.astype(np.float64))
    nt /= np.linalg.norm(nt, axis=2, keepdims=True)
    tangent = np.where(swap[..., None], nt, maps.tangent)
    return SVBRDFMaps(maps.rho_d, maps.rho_s, alpha, maps.normal, tangent, maps.transparency,
                      maps.size_mm, maps.name)


# --- folder I/O ------------------------------------------------------------------------------------


def write_maps(maps: SVBRDFMaps, directory: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write `maps` as a map folder (module docstring). The folder is assembled under a temporary name
    beside `directory` and renamed into place, so a reader sees the old folder or the complete new one."""
    if not isinstance(maps, SVBRDFMaps):
        raise TypeError(f"expected SVBRDFMaps, got {type(maps).__name__}")
    with atomic_folder(directory, overwrite) as tmp:
        attrs = {"hemicube_sample": maps.name, "size_mm": maps.size_mm}
        zero = np.zeros(maps.shape + (1,), np.float32)
        images = {
            "rho_d": maps.rho_d,
            "rho_s": maps.rho_s,
            "alpha": np.concatenate([maps.alpha, zero], axis=2),
            "normal": maps.normal * np.float32(0.5) + np.float32(0.5),
            "tangent": maps.tangent * np.float32(0.5) + np.float32(0.5),
            "transparency": np.repeat(maps.transparency[..., None], 3, axis=2),
        }
        for k, img in images.items():
            write_rgb_exr(tmp / MAP_FILES[k], img, attributes=attrs)
        doc = {"format": SAMPLE_FORMAT, "version": SAMPLE_FORMAT_VERSION, "name": maps.name,
               "size_mm": maps.size_mm, "resolution": list(maps.shape)}
        (tmp / SAMPLE_TOML).write_text(tomli_w.dumps(doc))
    return Path(directory)


def _read_image(path: Path, shape) -> np.ndarray:
    try:
        img = read_rgb_exr(path, shape=shape)
        check_finite(str(path), img)
    except ExrError as e:
        raise SampleError(str(e)) from None
    return img.astype(np.float64)


def _decode_unit(path: Path, enc: np.ndarray, what: str) -> np.ndarray:
    v = enc * 2.0 - 1.0
    norm = np.linalg.norm(v, axis=2)
    bad = np.abs(norm - 1.0) > DECODE_UNIT_TOL
    if bad.any():
        i, j = _texel(bad)
        raise SampleError(f"{path}: texel (row {i}, col {j}) decodes to {_fmt(v[i, j])}, length {norm[i, j]:.4g}, "
                          f"not a unit {what} (expected {what}·0.5 + 0.5 encoding; {int(bad.sum())} such texels)")
    return v / norm[..., None]


def _read_toml(path: Path) -> dict:
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SampleError(f"{path}: not valid TOML ({e})") from None
    if doc.get("format", SAMPLE_FORMAT) != SAMPLE_FORMAT:
        raise SampleError(f"{path}: format must be {SAMPLE_FORMAT!r}, got {doc.get('format')!r}")
    ver = doc.get("version", SAMPLE_FORMAT_VERSION)
    if not isinstance(ver, int) or ver > SAMPLE_FORMAT_VERSION:
        raise SampleError(f"{path}: version {ver!r} is not supported (this reader knows up to "
                          f"{SAMPLE_FORMAT_VERSION})")
    if "size_mm" in doc and (isinstance(doc["size_mm"], bool) or not isinstance(doc["size_mm"], (int, float))):
        raise SampleError(f"{path}: size_mm must be a number, got {doc['size_mm']!r}")
    if "name" in doc and not isinstance(doc["name"], str):
        raise SampleError(f"{path}: name must be a string, got {doc['name']!r}")
    return doc


def read_maps(directory: str | os.PathLike, size_mm: float | None = None) -> SVBRDFMaps:
    """Read a map folder (ours or the reference's texture_maps/). size_mm, when given, overrides
    sample.toml; without either the sample is taken as 150 mm wide. Normals and tangents are decoded,
    renormalised (8/16-bit rounding in third-party maps) and t is re-orthogonalised against n before the
    maps are validated. Any problem gives a SampleError naming the file."""
    d = Path(directory)
    if not d.is_dir():
        raise SampleError(f"{d}: not a map folder (no such directory)")
    missing = [MAP_FILES[k] for k in ("rho_d", "rho_s", "alpha", "normal", "tangent")
               if not (d / MAP_FILES[k]).is_file()]
    if missing:
        raise SampleError(f"{d}: not a map folder: missing {', '.join(missing)}")
    doc = _read_toml(d / SAMPLE_TOML) if (d / SAMPLE_TOML).is_file() else {}
    size = size_mm if size_mm is not None else doc.get("size_mm", DEFAULT_SIZE_MM)
    name = doc.get("name") or d.resolve().name or "sample"

    path = {k: d / f for k, f in MAP_FILES.items()}
    rho_d = _read_image(path["rho_d"], None)
    shape = rho_d.shape[:2]
    rho_s = _read_image(path["rho_s"], shape)
    alpha = _read_image(path["alpha"], shape)[..., :2]
    normal = _decode_unit(path["normal"], _read_image(path["normal"], shape), "normal")
    tangent = _decode_unit(path["tangent"], _read_image(path["tangent"], shape), "tangent")
    tangent = tangent - np.einsum("ijk,ijk->ij", tangent, normal)[..., None] * normal
    tn = np.linalg.norm(tangent, axis=2)
    bad = tn < 1e-3
    if bad.any():
        i, j = _texel(bad)
        raise SampleError(f"{path['tangent']}: the tangent at texel (row {i}, col {j}) is parallel to the normal "
                          f"of {MAP_FILES['normal']}")
    tangent /= tn[..., None]
    if path["transparency"].is_file():
        transparency = _read_image(path["transparency"], shape).mean(axis=2)
    else:
        transparency = np.zeros(shape)
    try:
        return SVBRDFMaps(rho_d, rho_s, alpha, normal, tangent, transparency, size, name)
    except SampleError as e:
        where = path.get(e.field, d / SAMPLE_TOML if e.field in ("size_mm", "name") else d)
        raise SampleError(f"{where}: {e}", e.field) from None


# --- built-in samples ------------------------------------------------------------------------------

BUILTIN_SAMPLES = ("ramps", "brushed_metal", "satin_weave")
SUITE = SUITE_SAMPLES  # `hemicube validate --suite`: the samples every threshold must hold on
MIN_RESOLUTION = 16
MAX_RESOLUTION = 8192

# ramps: reference values everywhere outside the ramp (borders and the held parameters)
RAMPS_REFERENCE = {"rho_d": 0.3, "rho_s": 2.0, "alpha": (0.1, 0.1), "normal": (0.0, 0.0, 1.0),
                   "tangent": (1.0, 0.0, 0.0), "transparency": 0.0}
RAMPS_COLOUR = (1.0, 0.55, 0.2)
# name: (region row (along +y, 0 = min y), region column (along +x), what varies with s = 0 → 1 along +x)
RAMPS_LAYOUT = {
    "rho_d_grey": (0, 0, "rho_d = s·(1, 1, 1)"),
    "rho_d_colour": (0, 1, f"rho_d = s·{RAMPS_COLOUR}"),
    "rho_s": (1, 0, "rho_s = 10·s (grey)"),
    "alpha_iso": (1, 1, "alpha_x = alpha_y = 0.006·(0.5/0.006)^s (log-linear 0.006 → 0.5)"),
    "anisotropy": (2, 0, "alpha_x = 0.3, alpha_y = 0.3·(0.02/0.3)^s (log-linear 0.3 → 0.02)"),
    "normal_tilt": (2, 1, "n = +z rotated about t = +x by 40°·s: (0, −sin, cos)"),
    "tangent_rotation": (3, 0, "t = (cos 180°·s, sin 180°·s, 0), alpha = (0.3, 0.05)"),
    "transparency": (3, 1, "transparency = s"),
}
RAMPS_GRID = (4, 2)  # region rows x region columns


def ramp_border(resolution: int) -> int:
    return max(1, resolution // 64)


def ramp_regions(resolution: int) -> dict[str, tuple[slice, slice]]:
    """Interior (row slice, column slice) of each `ramps` region (RAMPS_LAYOUT) at `resolution`; the
    ramp parameter s goes linearly from exactly 0 at the first interior column to exactly 1 at the last."""
    res = _check_resolution(resolution)
    b = ramp_border(res)
    nr, nc = RAMPS_GRID
    re = [round(k * res / nr) for k in range(nr + 1)]
    ce = [round(k * res / nc) for k in range(nc + 1)]
    return {k: (slice(re[r] + b, re[r + 1] - b), slice(ce[c] + b, ce[c + 1] - b))
            for k, (r, c, _) in RAMPS_LAYOUT.items()}


def _ramps(res: int, seed: int, size_mm: float) -> dict:
    """ramps (cf. the paper's Fig. 13): a 4 x 2 grid of regions, each varying ONE parameter linearly with
    s ∈ [0, 1] along +x (columns) while all others keep RAMPS_REFERENCE; rows of the grid go along +y:

        region row 3 (max y) | tangent_rotation (α = (0.3, 0.05))  | transparency 0 → 1
        region row 2         | anisotropy αx = 0.3, αy 0.3 → 0.02  | normal_tilt 0 → 40° about t = +x
        region row 1         | rho_s 0 → 10                         | alpha_iso 0.006 → 0.5 (log)
        region row 0 (min y) | rho_d_grey 0 → 1                     | rho_d_colour s·(1, 0.55, 0.2)
                               region column 0 (min x)                region column 1 (max x)

    Each region has a frame of `ramp_border(res)` texels (= max(1, res // 64)) with plain reference
    values, i.e. thin borders between regions. `ramp_regions(res)` gives the interior slices. The seed
    is ignored (nothing is random)."""
    ref = RAMPS_REFERENCE
    rho_d = np.full((res, res, 3), ref["rho_d"])
    rho_s = np.full((res, res, 3), ref["rho_s"])
    alpha = np.broadcast_to(np.array(ref["alpha"]), (res, res, 2)).copy()
    normal = np.broadcast_to(np.array(ref["normal"]), (res, res, 3)).copy()
    tangent = np.broadcast_to(np.array(ref["tangent"]), (res, res, 3)).copy()
    beta = np.full((res, res), ref["transparency"])
    for k, (rs, cs) in ramp_regions(res).items():
        s = np.linspace(0.0, 1.0, cs.stop - cs.start)[None, :]  # (1, n), broadcast over the region's rows
        one = np.ones((rs.stop - rs.start, 1))
        s2 = s * one
        if k == "rho_d_grey":
            rho_d[rs, cs] = s2[..., None]
        elif k == "rho_d_colour":
            rho_d[rs, cs] = s2[..., None] * np.array(RAMPS_COLOUR)
        elif k == "rho_s":
            rho_s[rs, cs] = 10.0 * s2[..., None]
        elif k == "alpha_iso":
            a = 0.006 * (0.5 / 0.006) ** s2
            alpha[rs, cs] = np.stack([a, a], -1)
        elif k == "anisotropy":
            alpha[rs, cs] = np.stack([0.3 * one * np.ones_like(s), 0.3 * (0.02 / 0.3) ** s2], -1)
        elif k == "normal_tilt":
            th = np.radians(40.0) * s2
            normal[rs, cs] = np.stack([np.zeros_like(th), -np.sin(th), np.cos(th)], -1)
        elif k == "tangent_rotation":
            ph = np.pi * s2
            tangent[rs, cs] = np.stack([np.cos(ph), np.sin(ph), np.zeros_like(ph)], -1)
            alpha[rs, cs] = (0.3, 0.05)
        elif k == "transparency":
            beta[rs, cs] = s2
    return dict(rho_d=rho_d, rho_s=rho_s, alpha=alpha, normal=normal, tangent=tangent, transparency=beta)


def _brushed_metal(res: int, seed: int, size_mm: float) -> dict:
    """brushed_metal: grey steel with a slowly curving brushing direction (seeded global angle and two
    sine undulations of the brush lines, ≤ ~25° of bend). The tangent (αx axis, the larger roughness) is
    ACROSS the brushing: the grooves run along it, so their facets spread reflected light across it.
    ρd = 0.02 ± 0.005; ρs = 5 ± 0.7 streak noise (minus (0, 0.08, 0.2): slightly warm), i.e. in [4, 5.7];
    αx = 0.30 ± 0.05 across the brushing, αy = 0.03 ± 0.01 along it (αx/αy ≥ 6.25 everywhere); the normal is
    tilted across the streaks by < 2.5° (streak noise). All noise is constant along the brush lines
    (streaks) and varies at the texel scale across them."""
    rng = np.random.default_rng([seed, 1])
    u, v = grid_uv(res)
    phi0 = rng.uniform(0.0, np.pi)
    (a1, a2), (f1, f2) = (0.04, 0.015), (1.0, 2.3)
    p1, p2 = rng.uniform(0.0, 2 * np.pi, 2)
    c, s = np.cos(phi0), np.sin(phi0)
    x, y = u - 0.5, v - 0.5
    xr, yr = c * x + s * y, -s * x + c * y  # coordinates in the frame of the global brushing direction
    k1, k2 = 2 * np.pi * f1, 2 * np.pi * f2
    psi = yr - a1 * np.sin(k1 * xr + p1) - a2 * np.sin(k2 * xr + p2)  # constant along a brush line
    slope = a1 * k1 * np.cos(k1 * xr + p1) + a2 * k2 * np.cos(k2 * xr + p2)  # dyr/dxr along the line
    dr = unit_rows(np.stack([np.ones_like(slope), slope], -1))
    d = np.stack([c * dr[..., 0] - s * dr[..., 1], s * dr[..., 0] + c * dr[..., 1], np.zeros_like(slope)], -1)
    g_rs, g_ax, g_ay, g_n, g_d = (streak_noise(rng, res, psi) for _ in range(5))
    rho_d = (0.02 + 0.005 * g_d)[..., None] * np.ones(3)
    rho_s = (5.0 + 0.7 * g_rs)[..., None] - np.array([0.0, 0.08, 0.2])
    alpha = np.stack([0.30 + 0.05 * g_ax, 0.03 + 0.01 * g_ay], -1)
    across = np.cross([0.0, 0.0, 1.0], d)  # in-plane, perpendicular to the brushing
    normal = unit_rows(np.array([0.0, 0.0, 1.0]) + np.tan(np.radians(2.5)) * g_n[..., None] * across)
    tangent = unit_rows(across - np.einsum("ijk,ijk->ij", across, normal)[..., None] * normal)
    return dict(rho_d=rho_d, rho_s=rho_s, alpha=alpha, normal=normal, tangent=tangent,
                transparency=np.zeros((res, res)))


def satin_thread_texels(res: int) -> int:
    """Thread width (texels) of `satin_weave` at `res`: res/20 rounded, clipped to [4, 8]."""
    return int(min(8, max(4, round(res / 20))))


def satin_warp_on_top(res: int) -> np.ndarray:
    """(H, W) bool: True where the warp thread (along y) is on top, False where the weft (along x) is."""
    p = satin_thread_texels(res)
    ci, cj = np.meshgrid(np.arange(res) // p, np.arange(res) // p, indexing="ij")
    return (cj + 2 * ci) % 5 != 0


def _satin_weave(res: int, seed: int, size_mm: float) -> dict:
    """satin_weave: a 5-harness warp-faced satin. Threads are p = satin_thread_texels(res) texels wide
    (4-8); warp threads run along y (crimson), weft threads along x (gold); in cell (ci, cj) = (i // p,
    j // p) the weft is on top where (cj + 2 ci) mod 5 == 0, the warp elsewhere (satin_warp_on_top).
    The tangent follows the top thread (±y for warp, ±x for weft, re-orthogonalised against n), so the
    tangents form two orthogonal families; α = (0.15 along the thread, 0.4 across) ± 10% per thread
    (so αx < αy here: canonical_anisotropy swaps it). Each cell is a dome-shaped bump (tilt up to 15°,
    largest across the thread), giving bumps at every thread crossing. Transparency: 0.25-0.45 at the
    corner texel of each cell (the small gap where neither thread covers), 0 elsewhere; gap texels are
    darker (shadowed) and texels on a cell's edge slightly darker. Per-thread colour, gloss and
    roughness variations and fine fibre noise along the threads are seeded."""
    rng = np.random.default_rng([seed, 2])
    p = satin_thread_texels(res)
    ii, jj = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    warp = satin_warp_on_top(res)
    n_threads = res // p + 1
    var_warp = rng.uniform(-1, 1, (n_threads, 3))  # per warp thread (index cj): colour, gloss, roughness
    var_weft = rng.uniform(-1, 1, (n_threads, 3))  # per weft thread (index ci)
    var = np.where(warp[..., None], var_warp[jj // p], var_weft[ii // p])
    fibre = np.where(warp, rng.uniform(-1, 1, (res, res)), rng.uniform(-1, 1, (res, res)))
    colour = np.where(warp[..., None], np.array([0.50, 0.06, 0.10]), np.array([0.55, 0.42, 0.10]))
    rho_d = colour * (1.0 + 0.08 * var[..., :1] + 0.03 * fibre[..., None])
    rho_s = np.where(warp, 1.2, 0.8)[..., None] * (1.0 + 0.1 * var[..., 1:2]) * np.ones(3)
    ax = 0.15 * (1.0 + 0.1 * var[..., 2])
    alpha = np.stack([ax, 0.4 * (1.0 + 0.1 * var[..., 2])], -1)
    # local coordinates in the cell, (−1, 1): a_x across x, a_y across y
    a_x = ((jj % p) + 0.5) / p * 2.0 - 1.0
    a_y = ((ii % p) + 0.5) / p * 2.0 - 1.0
    across = np.where(warp, a_x, a_y)   # across the top thread
    along = np.where(warp, a_y, a_x)    # along it
    ex, ey = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    dir_across = np.where(warp[..., None], ex, ey)
    dir_along = np.where(warp[..., None], ey, ex)
    slope = across[..., None] * dir_across + 0.6 * along[..., None] * dir_along
    slope /= np.maximum(1.0, np.linalg.norm(slope, axis=-1, keepdims=True))
    normal = unit_rows(np.array([0.0, 0.0, 1.0]) + np.tan(np.radians(15.0)) * slope)
    tangent = unit_rows(dir_along - np.einsum("ijk,ijk->ij", dir_along, normal)[..., None] * normal)
    edge_i, edge_j = (ii % p) == p - 1, (jj % p) == p - 1
    gap = edge_i & edge_j
    beta = np.where(gap, 0.35 + 0.1 * rng.uniform(-1, 1, (res, res)), 0.0)
    shade = np.where(gap, 0.3, np.where(edge_i | edge_j, 0.8, 1.0))[..., None]
    return dict(rho_d=np.clip(rho_d * shade, 0.0, 1.0), rho_s=rho_s * shade, alpha=alpha, normal=normal,
                tangent=tangent, transparency=beta)


_BUILDERS = {"ramps": _ramps, "brushed_metal": _brushed_metal, "satin_weave": _satin_weave}
# the material suite (docs/accuracy.md): one sample per OpenSVBRDF category and `quadrants` (twin.materials.suite)
_BUILDERS.update(SUITE_BUILDERS)
BUILTIN_SAMPLES = BUILTIN_SAMPLES + SUITE_SAMPLES
# one line per built-in sample for `hemicube samples list` (the builders' docstrings say the rest)
CHARACTER = {"ramps": "one parameter ramped per region (cf. Fig. 13)",
             "brushed_metal": "dark steel, brushed: strong anisotropy along curving streaks",
             "satin_weave": "5-harness satin: two orthogonal thread families, bumps, gaps",
             **{name: summary(name) for name in SUITE_SAMPLES}}


def _integer(value, what: str) -> int:
    """An integer argument (int or numpy integer, not bool), else a SampleError saying `what` it must be."""
    if isinstance(value, bool):
        raise SampleError(f"{what}, got {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise SampleError(f"{what}, got {value!r}") from None


def _check_resolution(resolution) -> int:
    res = _integer(resolution, f"resolution must be an integer >= {MIN_RESOLUTION}")
    if not MIN_RESOLUTION <= res <= MAX_RESOLUTION:
        raise SampleError(f"resolution must be in [{MIN_RESOLUTION}, {MAX_RESOLUTION}], got {res}")
    return res


def builtin_sample(name: str, resolution: int = 128, seed: int = 0,
                   size_mm: float = BUILTIN_SIZE_MM) -> SVBRDFMaps:
    """A procedural, exactly known sample (BUILTIN_SAMPLES; see each builder's docstring: `ramps`,
    `brushed_metal`, `satin_weave`), resolution x resolution texels, `size_mm` wide (120 mm by default).
    Deterministic: the same (name, resolution, seed, size) gives bit-identical maps."""
    if name not in _BUILDERS:
        raise SampleError(f"unknown built-in sample {name!r}; expected one of {', '.join(BUILTIN_SAMPLES)}")
    res = _check_resolution(resolution)
    seed = _integer(seed, "seed must be a non-negative integer")
    if seed < 0:
        raise SampleError(f"seed must be a non-negative integer, got {seed}")
    maps = _BUILDERS[name](res, seed, size_mm)
    return SVBRDFMaps(**maps, size_mm=size_mm, name=name)


builtin_sample.__doc__ += "\n\n" + "\n\n".join(f"{k}: {_BUILDERS[k].__doc__}" for k in BUILTIN_SAMPLES)


def parameter_ranges(maps: SVBRDFMaps) -> dict:
    """What the maps span: (min, max) of ρd and ρs (over texels and channels), αx and αy and αx/αy (in the
    export convention αx ≥ αy, canonical_anisotropy), the normal's tilt from +z (degrees) and the transparency."""
    m = canonical_anisotropy(maps)
    ax, ay = m.alpha[..., 0].astype(np.float64), m.alpha[..., 1].astype(np.float64)
    tilt = np.degrees(np.arccos(np.clip(m.normal[..., 2].astype(np.float64), -1.0, 1.0)))

    def span(a):
        return (float(np.min(a)), float(np.max(a)))

    return {"rho_d": span(m.rho_d), "rho_s": span(m.rho_s), "alpha_x": span(ax), "alpha_y": span(ay),
            "anisotropy": span(ax / ay), "tilt_deg": span(tilt), "transparency": span(m.transparency)}


def sample_ranges(name: str, resolution: int = 64, seed: int = 0) -> dict:
    """What `hemicube samples list` shows of a built-in sample: parameter_ranges at `resolution` and `seed`
    (rounded) and a one-line character."""
    r = parameter_ranges(builtin_sample(name, resolution, seed))
    return {**{k: [round(v[0], 4), round(v[1], 4)] for k, v in r.items()}, "description": CHARACTER[name]}


def _builtin_name(name_or_dir) -> tuple[str, int] | None:
    """(name, seed) of a built-in sample's name or "NAME@SEED", else None."""
    if isinstance(name_or_dir, str) and name_or_dir in BUILTIN_SAMPLES:
        return name_or_dir, 0
    if isinstance(name_or_dir, str) and "@" in name_or_dir:
        name, _, seed = name_or_dir.partition("@")
        if name in BUILTIN_SAMPLES and seed.isdigit():
            return name, int(seed)
    return None


def check_sample(name_or_dir) -> None:
    """A SampleError unless `name_or_dir` is what load_sample reads (a built-in name, NAME@SEED or an existing
    folder), found without building or reading any maps: a run of many samples checks every name before any work."""
    if _builtin_name(name_or_dir) is None and not Path(name_or_dir).is_dir():
        raise SampleError(f"{str(name_or_dir)!r} is neither a built-in sample ({', '.join(BUILTIN_SAMPLES)}) "
                          "nor an existing map folder")


def load_sample(name_or_dir, resolution: int = 128) -> SVBRDFMaps:
    """A built-in sample by name (BUILTIN_SAMPLES, at `resolution`, seed 0), or "NAME@SEED" for another seed
    (another composition of the same sample: the held-back variants of the material suite), or a map folder
    (read_maps; `resolution` is then ignored: the folder's maps are used as they are)."""
    check_sample(name_or_dir)
    builtin = _builtin_name(name_or_dir)
    return builtin_sample(builtin[0], resolution, builtin[1]) if builtin else read_maps(Path(name_or_dir))
