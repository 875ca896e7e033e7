"""Novel views and lights: a reconstruction against the truth under 560 pairs of view and light direction that the
capture never used (the paper's validation beyond the capture's photos, §10.2 and Fig. 14).

    vset = validation_set(rig)                                   # 20 views x 28 lights, fixed for every rig
    scores = novel_view_scores(vset, truth_maps, recon_maps)     # truth's radiance box-filtered onto recon's grid
    images = render(vset, maps)                                  # (20, 28, R, C, 3) linear radiance

The validation set
* **Views**: 20 directions, **lights**: 28 directions over the upper hemisphere with zenith <= 60 deg, each set spread
  evenly in solid angle (a Fibonacci spiral on the cap: z uniform in [cos 60 deg, 1], azimuth by the golden angle).
* **A view** is a virtual camera with the primary camera's intrinsics at the primary camera's distance from the
  sample's centre, aimed at it (+x of the image along the world's +x made orthogonal, OpenCV convention).
* **A light** is a point source at the centre of the 8 x 8 group of upper LEDs nearest its direction (the paper's
  Fig. 14: each light is the centre of such a group), with the group's summed intensity, the LEDs' profile Psi and
  the board's normal; a rig whose boards hold no whole 8 x 8 group (the mini rig) uses its nearest LED. Nearest: the
  largest cosine between the direction and the source seen from the sample's centre.

Image formation (the same for the truth and the reconstruction): each texel of the reconstruction's grid seen from
the view's camera centre under one light at a time, by the forward model's physical convention (twin.lumitexels:
inverse-square fall-off, Psi, the GGX of twin.optics.ggx), linear HDR, no sensor noise, no holder frame (its shadow
would fall alike on both). The image is the texel grid itself: both maps live on it, so a camera's resampling would
blur both alike. The truth's radiance is box-filtered onto the reconstruction's grid (truth_images): rendered at
sub-texel points and averaged over each texel, which is what a camera resolving the grid sees of it.

Scores per pair, on the texels whose SSIM window lies inside the sample (the mask eroded by the window's radius):
* SSIM (Wang et al. 2004: Gaussian window sigma 1.5 truncated at 11 px, K1 0.01, K2 0.03, population covariance) on
  luminance (Rec. 709) after a fixed tone map: the truth's 99th percentile -> 1, sRGB encoding, clipped to [0, 1];
* PSNR (dB) of the same tone-mapped luminance (peak 1);
* the relative RMSE of the linear HDR RGB, sqrt(sum (r - t)^2 / sum t^2).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

VIEWS = 20
LIGHTS = 28
MAX_ZENITH_DEG = 60.0
GROUP = 8  # LEDs a side of a light's group (the paper's Fig. 14)
SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # skimage's Gaussian window: truncate 3.5 sigma -> radius int(3.5 * 1.5 + 0.5) = 5, 11 px
TONE_PERCENTILE = 99.0
# points per truth texel across a grid texel when the truth's radiance is box-filtered (truth_images): 1.5 to 3 moves
# the suite's SSIM by at most 0.004 (docs/accuracy.md)
SUPERSAMPLE = 1.5
REC709_Y = np.array([0.2126, 0.7152, 0.0722])


def fibonacci_cap(n: int, max_zenith_deg: float = MAX_ZENITH_DEG) -> np.ndarray:
    """(n, 3) unit directions spread evenly in solid angle over the cap zenith <= max_zenith_deg (+z up): equal
    area bands in z (z_k = 1 - (k + 1/2) (1 - cos max) / n, Archimedes), azimuth k times the golden angle."""
    k = np.arange(n) + 0.5
    z = 1.0 - k * (1.0 - math.cos(math.radians(max_zenith_deg))) / n
    phi = np.arange(n) * math.pi * (3.0 - math.sqrt(5.0))
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], 1)


@dataclass(frozen=True)
class ValidationSet:
    """The fixed views and lights of one rig (module docstring). `lights_rig` holds one LED per distinct source
    and one camera per view (named view00 ...); light k is LED `source[k]` of it."""

    rig: object
    lights_rig: object
    views: np.ndarray      # (VIEWS, 3) the view directions
    lights: np.ndarray     # (LIGHTS, 3) the light directions asked for
    source: np.ndarray     # (LIGHTS,) index of each light's source in lights_rig
    light_leds: tuple      # (LIGHTS,) the rig's LEDs summed into each light (64, or 1 on a rig without whole groups)
    view_leds: tuple       # (VIEWS,) the rig's LEDs nearest each view's direction (a group, or one LED)

    @property
    def view_names(self) -> list[str]:
        return list(self.lights_rig.cameras)

    def source_directions(self) -> np.ndarray:
        """(LIGHTS, 3) the directions of the lights' sources from the sample's centre."""
        d = self.lights_rig.leds.positions[self.source] - np.asarray(self.rig.sample.origin)
        return d / np.linalg.norm(d, axis=1, keepdims=True)


def _sources(rig) -> list[np.ndarray]:
    """The candidate light sources: the index arrays of the whole 8 x 8 groups of upper LEDs on each board, or every
    upper LED alone where no board holds a whole group."""
    leds = rig.leds
    upper = np.flatnonzero(~np.asarray(leds.is_bottom))
    key = (leds.board[upper].astype(np.int64) * 1_000_000 + (leds.row[upper] // GROUP) * 1000
           + leds.col[upper] // GROUP)
    groups = [upper[key == k] for k in np.unique(key)]
    whole = [g for g in groups if len(g) == GROUP * GROUP]
    return whole or [np.array([i]) for i in upper]


def validation_set(rig) -> ValidationSet:
    """The rig's validation set (module docstring): views (VIEWS, 3) = (20, 3) and lights (LIGHTS, 3) = (28, 3), unit
    directions in the rig's world frame within MAX_ZENITH_DEG = 60 degrees of +z; each view a virtual camera
    with the primary camera's intrinsics (pixels) at its distance (mm) from the sample's centre, each light the
    nearest 8 x 8 group of upper LEDs (or LED) of `rig` (a twin Rig)."""
    from twin.rig.camera import Camera
    from twin.rig.model import Rig

    origin = np.asarray(rig.sample.origin, np.float64)
    groups = _sources(rig)
    leds = rig.leds
    centres = np.stack([leds.positions[g].mean(0) for g in groups])
    to = centres - origin
    to /= np.linalg.norm(to, axis=1, keepdims=True)
    lights = fibonacci_cap(LIGHTS)
    nearest = np.argmax(lights @ to.T, axis=1)
    views = fibonacci_cap(VIEWS)
    used, source = np.unique(nearest, return_inverse=True)
    first = np.array([groups[u][0] for u in used])
    normals = np.stack([leds.normals[groups[u]].sum(0) for u in used])
    src = replace(leds.subset(first), positions=centres[used],
                  normals=normals / np.linalg.norm(normals, axis=1, keepdims=True),
                  intensity=np.stack([leds.intensity[groups[u]].sum(0) for u in used]))
    primary = rig.primary
    dist = float(np.linalg.norm(primary.centre - origin))
    cams = {}
    for v, d in enumerate(views):
        up = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        cams[f"view{v:02d}"] = Camera.look_at(f"view{v:02d}", origin + dist * d, origin, up, primary.K,
                                              primary.width, primary.height)
    lights_rig = Rig(f"{rig.name} validation lights", src, rig.boards, cams, sample=rig.sample, frame=None,
                     bottom=None, led_profile=rig.led_profile)
    return ValidationSet(rig, lights_rig, views, lights, source, tuple(groups[u] for u in nearest),
                         tuple(groups[i] for i in np.argmax(views @ to.T, axis=1)))


def render(vset: ValidationSet, maps, device: str = "cpu", block: int = 1) -> np.ndarray:
    """(VIEWS, LIGHTS, H / block, W / block, 3) float64 linear radiance (W m^-2 sr^-1 per unit drive) of `maps` (on
    their own grid, centred on the sample plane) under each pair (module docstring), each block x block of texels
    averaged into one (the box filter of the truth's radiance onto a coarser grid)."""
    import twin
    from twin.materials.samples import grid_positions

    h, w = maps.shape
    if h % block or w % block:
        raise ValueError(f"a {h} x {w} grid does not divide into blocks of {block} x {block} texels")
    pos = grid_positions(maps.size_mm, maps.shape, vset.rig.sample).reshape(-1, 3).astype(np.float32)
    # twin.lumitexels' keywords, as reconstruction.evaluation.validation.map_parameters (which imports this module)
    params = dict(normal=maps.normal.reshape(-1, 3), tangent=maps.tangent.reshape(-1, 3),
                  rho_d=maps.rho_d.reshape(-1, 3), rho_s=maps.rho_s.reshape(-1, 3),
                  alpha_x=maps.alpha[..., 0].reshape(-1), alpha_y=maps.alpha[..., 1].reshape(-1),
                  transparency=maps.transparency.reshape(-1))
    out = np.empty((VIEWS, LIGHTS, h // block, w // block, 3))
    for v, name in enumerate(vset.view_names):
        m = twin.lumitexels(vset.lights_rig, pos, camera=name, convention="physical", visibility=False,
                            device=device, **params)[:, vset.source]
        m = m.reshape(h // block, block, w // block, block, LIGHTS, 3).mean((1, 3), dtype=np.float64)
        out[v] = m.transpose(2, 0, 1, 3)
    return out


def truth_images(vset: ValidationSet, truth, size_mm: float, resolution: int, device: str = "cpu") -> np.ndarray:
    """The truth's images on a square grid of `resolution` texels over `size_mm` (same centre): its radiance
    box-filtered onto that grid, i.e. rendered at s x s points per texel (the truth bilinear there, alpha in log space,
    reconstruction.evaluation.metrics.resample_maps; s = SUPERSAMPLE per truth texel across a grid texel, at least 2)
    and averaged: what a camera resolving the grid sees of the sample. Maps already on that grid are rendered as they
    are. (Rendering the truth's maps box-filtered instead is no reference where the structure is finer than a texel:
    on the woven suite sample those maps render the radiance's box filter at SSIM 0.66 in the worst pair.)"""
    from reconstruction.evaluation.metrics import resample_maps

    if truth.shape == (resolution, resolution) and truth.size_mm == size_mm:
        return render(vset, truth, device)
    per = max(truth.shape) * size_mm / (truth.size_mm * resolution)  # truth texels across one grid texel
    s = max(2, math.ceil(SUPERSAMPLE * per))
    return render(vset, resample_maps(truth, size_mm, resolution * s), device, block=s)


def _tone(y: np.ndarray, scale: float) -> np.ndarray:
    """The fixed tone map: y * scale, sRGB-encoded (IEC 61966-2-1), clipped to [0, 1]."""
    x = np.clip(y * scale, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def scored_texels(mask: np.ndarray) -> np.ndarray:
    """The texels whose whole SSIM window (11 x 11) lies inside `mask`."""
    from scipy.ndimage import binary_erosion

    return binary_erosion(mask, np.ones((2 * SSIM_RADIUS + 1,) * 2, bool), border_value=0)


def pair_scores(truth: np.ndarray, test: np.ndarray, scored: np.ndarray) -> dict:
    """SSIM, PSNR and relative RMSE (module docstring) of one pair's images (H, W, 3), linear, on `scored`."""
    from skimage.metrics import structural_similarity

    yt, yr = truth @ REC709_Y, test @ REC709_Y
    p = float(np.percentile(yt[scored], TONE_PERCENTILE))
    scale = 1.0 / p if p > 0 else 1.0
    a, b = _tone(yt, scale), _tone(yr, scale)
    _, smap = structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=SSIM_SIGMA,
                                    use_sample_covariance=False, full=True)
    mse = float(np.mean((a[scored] - b[scored]) ** 2))
    den = float(np.sum(truth[scored] ** 2))
    num = float(np.sum((test[scored] - truth[scored]) ** 2))
    return {"ssim": float(smap[scored].mean()), "psnr_db": math.inf if mse == 0 else -10.0 * math.log10(mse),
            "rel_rmse": math.sqrt(num / den) if den > 0 else (0.0 if num == 0 else math.inf)}


def _angles(d: np.ndarray) -> dict:
    return {"zenith_deg": round(math.degrees(math.acos(min(1.0, d[2]))), 2),
            "azimuth_deg": round(math.degrees(math.atan2(d[1], d[0])) % 360.0, 2)}


def novel_view_scores(vset: ValidationSet, truth, recon, mask=None, device: str = "cpu",
                      images: bool = False) -> dict:
    """Every pair's scores of `recon` (maps on the reconstruction's grid) against `truth` (any map folder's maps, its
    radiance box-filtered onto that grid: truth_images), and their summary: {"ssim": {"mean", "p5", "worst"},
    "psnr_db": {"mean", "worst"}, "rel_rmse": {"mean", "worst"}, "worst": the pair of the lowest SSIM with its view
    and light, "pairs": every pair (view and light directions, the light's source, the scores), "texels": how many
    are scored}. SSIM in [0, 1], PSNR in dB, rel_rmse a fraction; "worst" gives the view's and the light's zenith_deg
    and azimuth_deg (degrees). `vset`: validation_set(rig); truth, recon: twin.materials.samples.SVBRDFMaps, recon
    square (H == W texels) over recon.size_mm mm. mask (H, W) bool: the texels on the true sample (default all).
    images=True adds "worst_images": (truth, recon) of the worst pair, each (H, W, 3) linear radiance."""
    h, w = recon.shape
    if h != w:
        raise ValueError(f"the reconstruction's grid must be square, got {h} x {w}")
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    scored = scored_texels(mask)
    if not scored.any():
        raise ValueError(f"no texel of the {h} x {w} grid has its {2 * SSIM_RADIUS + 1}-texel SSIM window inside "
                         "the sample: the grid is too small to score novel views")
    t_img, r_img = truth_images(vset, truth, recon.size_mm, h, device), render(vset, recon, device)
    src = vset.source_directions()
    pairs = []
    for v in range(VIEWS):
        for k in range(LIGHTS):
            s = pair_scores(t_img[v, k], r_img[v, k], scored)
            pairs.append({"view": v, "light": k, "view_dir": vset.views[v].round(6).tolist(),
                          "light_dir": vset.lights[k].round(6).tolist(), "source_dir": src[k].round(6).tolist(),
                          "source_leds": len(vset.light_leds[k]), **s})
    ssim = np.array([p["ssim"] for p in pairs])
    psnr = np.array([p["psnr_db"] for p in pairs])
    rmse = np.array([p["rel_rmse"] for p in pairs])
    worst = pairs[int(np.argmin(ssim))]
    out = {"ssim": {"mean": float(ssim.mean()), "p5": float(np.percentile(ssim, 5)), "worst": float(ssim.min())},
           "psnr_db": {"mean": float(np.mean(np.minimum(psnr, 1e3))), "worst": float(psnr.min())},
           "rel_rmse": {"mean": float(rmse.mean()), "worst": float(rmse.max())},
           "worst": {"view": worst["view"], "light": worst["light"], "ssim": worst["ssim"],
                     "view_angles": _angles(vset.views[worst["view"]]), "light_angles": _angles(src[worst["light"]])},
           "pairs": pairs, "texels": int(scored.sum())}
    if images:
        out["worst_images"] = (t_img[worst["view"], worst["light"]], r_img[worst["view"], worst["light"]])
    return out


def summary_line(scores: dict) -> str:
    """One line of novel_view_scores' summary: the mean, the 5th percentile and the worst pair with its view and
    light (zenith / azimuth)."""
    w, s = scores["worst"], scores["ssim"]
    return (f"novel views: SSIM mean {s['mean']:.4f}, 5th percentile {s['p5']:.4f}, worst {s['worst']:.4f} "
            f"(view {w['view']} at zenith {w['view_angles']['zenith_deg']:.0f}° azimuth "
            f"{w['view_angles']['azimuth_deg']:.0f}°, light {w['light']} at {w['light_angles']['zenith_deg']:.0f}° / "
            f"{w['light_angles']['azimuth_deg']:.0f}°) over {len(scores['pairs'])} pairs")


def directions_figure(vset: ValidationSet, ssim: np.ndarray, path):
    """The paper's Fig. 14 picture of SSIM over view and light directions: one unfolded cube (twin.rig.cross) per
    view, each light's LEDs in the colour of its pair's SSIM (inferno, from min(worst, 0.9) to 1), the LEDs
    nearest the view's direction in cyan, the other upper LEDs grey. ssim (VIEWS, LIGHTS)."""
    from matplotlib import colormaps

    from twin.view.cross_plot import BACKGROUND, CMAP, GRID_SCALE, save_tiles
    from twin.rig.cross import cross_image

    rig = vset.rig
    lo = min(0.9, float(np.min(ssim)))
    tiles = []
    for v in range(VIEWS):
        rgb = np.where(np.asarray(rig.leds.is_bottom)[:, None], np.nan, 0.45) * np.ones((rig.num_leds, 3))
        for k in range(LIGHTS):
            rgb[vset.light_leds[k]] = colormaps[CMAP]((ssim[v, k] - lo) / (1.0 - lo) if lo < 1 else 1.0)[:3]
        rgb[vset.view_leds[v]] = (0.0, 1.0, 1.0)
        img = cross_image(rig, rgb)
        a = _angles(vset.views[v])
        tiles.append((np.where(np.isnan(img), BACKGROUND, img),
                      f"view {v}: {a['zenith_deg']:.0f}° / {a['azimuth_deg']:.0f}°, worst {ssim[v].min():.3f}"))
    return save_tiles(tiles, path, GRID_SCALE, colorbar=(lo, 1.0))
