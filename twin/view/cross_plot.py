"""Pictures of per-LED vectors on the unfolded cube (the "cross" image of twin.rig.cross, paper Fig. 5).

`hemicube show pattern` calls `save_pattern_image`. Every picture names the cube's faces on it (face_labels) and has
a scale: the drive level of a pattern's channels, or the colour map of a scalar vector. Images are composed at exact pixel sizes (each cross
pixel becomes a SCALE x SCALE block, nearest neighbour) with matplotlib's Agg canvas, never pyplot, so
they work headless and do not touch global figure state. PNGs are written atomically.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from twin.rig.cross import CROSS_SHAPE, cross_image

BACKGROUND = 0.12  # grey level of canvas pixels outside every board: dark, but not "LED off" black
CMAP = "inferno"
SCALE = 4  # pixels per cross pixel for a single image
GRID_SCALE = 2  # ... and per tile of a grid of several frames
TITLE_PX = 24  # height of the title band above each tile
MARGIN_PX = 8  # around and between tiles
BAR_PX = 90  # the scale bar's column, right of the tiles
DPI = 100
# the scale of a pattern's RGB drive weights, shown as they are: each channel's level, 255 = the LED at full drive
PATTERN_SCALE = (0, 255, "drive level of each channel (255 = full)", "gray")


def normalise(values, num_leds: int) -> tuple[np.ndarray, tuple[float, float]]:
    """Per-LED values as displayable numbers in [0, 1], and the (vmin, vmax) mapped to 0 and 1.

    (L,) scalars are divided by their maximum (so 1 = the brightest LED; a vector with negative entries
    is mapped min..max instead). (L, 3) RGB within [0, 1], such as pattern drive weights, is kept as is
    (a dim pattern stays dim); otherwise it is divided by its maximum."""
    v = np.asarray(values, dtype=np.float64)
    if v.shape not in ((num_leds,), (num_leds, 3)):
        raise ValueError(f"values must have shape ({num_leds},) or ({num_leds}, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("values contain NaN or Inf")
    lo, hi = float(v.min()), float(v.max())
    if v.ndim == 2 and lo >= 0 and hi <= 1:
        return v, (0.0, 1.0)
    if lo < 0:
        return (v - lo) / (hi - lo if hi > lo else 1.0), (lo, hi)
    return v / (hi if hi > 0 else 1.0), (0.0, hi if hi > 0 else 1.0)


def cross_rgb(rig, values) -> np.ndarray:
    """(128, 192, 3) float image in [0, 1] of a per-LED vector on the unfolded cube.

    (L,) scalars go through the "inferno" colormap after `normalise`; (L, 3) values are RGB. Pixels
    outside every board are dark grey (BACKGROUND)."""
    from matplotlib import colormaps

    v, _ = normalise(values, rig.num_leds)
    if v.ndim == 1:
        v = colormaps[CMAP](v)[:, :3]
    img = cross_image(rig, v)  # NaN outside every board
    return np.where(np.isnan(img), BACKGROUND, np.clip(img, 0.0, 1.0))


def _upscale(img: np.ndarray, s: int) -> np.ndarray:
    return np.repeat(np.repeat(img, s, axis=0), s, axis=1)


def face_labels(rig) -> list[tuple[float, float, str]]:
    """(x, y, face) in cross-canvas pixels: each face's name (twin.rig.model.Board.face: "-x", "+x", "-y", "+y", "top",
    "bottom") at the centre of its boards' LEDs, so that a reader of the unfolded cube knows which wall is which."""
    cp = np.asarray(rig.leds.cross_pixel, np.float64)
    return [(*map(float, cp[idx].mean(0)), face) for face, idx in rig.face_leds().items()]


def tiles_figure(tiles: list[tuple[np.ndarray, str]], scale: int, colorbar: tuple | None = None,
                 labels: list[tuple[float, float, str]] | None = None):
    """The matplotlib Figure of save_tiles (its docstring)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    H, W = CROSS_SHAPE
    th, tw = H * scale, W * scale
    k = len(tiles)
    ncols = math.ceil(math.sqrt(k))
    nrows = math.ceil(k / ncols)
    bar_px = BAR_PX if colorbar is not None else 0
    width = ncols * tw + (ncols + 1) * MARGIN_PX + bar_px
    height = nrows * (th + TITLE_PX) + (nrows + 1) * MARGIN_PX
    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI, facecolor="white")
    FigureCanvasAgg(fig)
    font = 10 if scale >= SCALE else 8
    for i, (img, title) in enumerate(tiles):
        r, c = divmod(i, ncols)
        x = MARGIN_PX + c * (tw + MARGIN_PX)
        top = MARGIN_PX + r * (th + TITLE_PX + MARGIN_PX)  # from the top of the figure
        y = height - top - TITLE_PX - th  # matplotlib axes origin is at the bottom
        ax = fig.add_axes((x / width, y / height, tw / width, th / height))
        ax.imshow(_upscale(img, scale), interpolation="none", aspect="auto")
        ax.set_axis_off()
        ax.text(0.0, 1.0, title, transform=ax.transAxes, va="bottom", ha="left", fontsize=font,
                clip_on=False)
        for lx, ly, text in labels or ():  # on a dark box: readable over any LED colour
            ax.text((lx + 0.5) * scale, (ly + 0.5) * scale, text, ha="center", va="center", fontsize=font - 1,
                    color="white", bbox={"facecolor": "black", "alpha": 0.55, "pad": 1.0, "edgecolor": "none"})
    if colorbar is not None:
        from matplotlib import colormaps
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        vmin, vmax, *rest = colorbar
        label, cmap = (list(rest) + ["", CMAP])[:2] if rest else ("", CMAP)
        cax = fig.add_axes(((width - bar_px + 10) / width, MARGIN_PX / height, 14 / width,
                            (height - 2 * MARGIN_PX - TITLE_PX) / height))
        bar = fig.colorbar(ScalarMappable(Normalize(vmin, vmax), colormaps[cmap]), cax=cax)
        cax.tick_params(labelsize=8)
        if label:
            bar.set_label(label, fontsize=8)
    return fig


def save_tiles(tiles: list[tuple[np.ndarray, str]], output, scale: int, colorbar: tuple | None = None,
               labels: list[tuple[float, float, str]] | None = None) -> Path:
    """Lay out (image, title) tiles on a grid and write a PNG of exactly computed size:
    ncols = ceil(sqrt(K)) tiles per row; each tile is (128*scale + TITLE_PX) x (192*scale) pixels,
    with MARGIN_PX around and between tiles. `colorbar` (vmin, vmax[, label[, colour map]]) adds a scale bar (the
    colour map CMAP unless named); `labels` (x, y, text) in cross-canvas pixels are drawn on every tile (face_labels)."""
    from twin.atomic import atomic_path

    fig = tiles_figure(tiles, scale, colorbar, labels)
    output = Path(output)
    with atomic_path(output, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=DPI, facecolor="white")
    return output


def save_pattern_image(patterns, rig, output, index: int | None = None) -> Path:
    """A PNG of frame `index` of a PatternSet, or of all its frames on a grid, each labelled with its
    name. Drive weights are shown as RGB as they are (level 255 = full brightness)."""
    patterns.check_rig(rig)
    k = patterns.num_patterns
    if index is not None:
        if not isinstance(index, (int, np.integer)) or not 0 <= index < k:
            raise ValueError(f"pattern index {index} out of range: the set has {k} frame(s), 0..{k - 1}")
        frames = [int(index)]
    else:
        if k == 0:
            raise ValueError("the pattern set has no frames")
        frames = list(range(k))
    w = patterns.weights
    tiles = [(cross_rgb(rig, w[i]), f"{i}: {patterns.names[i]}") for i in frames]
    return save_tiles(tiles, output, SCALE if len(tiles) == 1 else GRID_SCALE, colorbar=PATTERN_SCALE,
                      labels=face_labels(rig))


def save_cross_image(rig, values, output, title: str | None = None) -> Path:
    """A PNG of any per-LED vector (a lumitexel, a pattern frame) on the unfolded cube; scalar vectors
    get a colour bar."""
    values = np.asarray(values)
    _, span = normalise(values, rig.num_leds)
    bar = span if values.ndim == 1 else PATTERN_SCALE if span == (0.0, 1.0) else None
    return save_tiles([(cross_rgb(rig, values), title or "")], output, SCALE, colorbar=bar, labels=face_labels(rig))
