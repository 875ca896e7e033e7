"""The validation report: the report folder and its images. The numbers come from
reconstruction.evaluation.metrics.

    write_report(out, title=..., metrics=..., checks=rows, panels=map_panels(truth_g, recon) + [...],
                 notes=[...])          # -> {"metrics_json", "report_md", "images": {name: path}}
    render_panel(name, photo, latent_render, map_render, path)       # reference §6.4's per-pattern triptych

Report folder (`write_report`): metrics.json ({"title", "passed", "checks", "metrics", "notes"}; NaN is
written as null, ±inf as the strings "inf" / "-inf", so the file is strict JSON), report.md (result,
table, notes, images, every metric), images/<panel>.png. The folder is written as a whole
(twin.atomic.atomic_folder): a reader sees the previous report or the complete new one, never a mix, and a
failed run leaves no temporary file behind.

Panels. `Panel(name, truth, recon, kind)` is one PNG "truth | reconstruction | |error|", one row per
channel for the colour-mapped kinds, with colour bars; NaN pixels are "no data" and drawn grey (e.g.
isotropic texels of a tangent panel). Kinds:
    "rgb"      linear RGB → sRGB (IEC 61966-2-1) after × exposure, clipped to [0, 1]; exposure = the
               panel's, else 1 / (99.5th percentile of the truth), shared by truth and reconstruction so
               that a brightness error shows; error = mean over channels of |Δ| in linear units.
    "normal"   n·0.5 + 0.5 (reference §7.1 encoding); error = angle in degrees.
    "tangent"  the axis orientation atan2(t_y, t_x) mod 180° as a hue (t and −t have the same colour);
               error = axis angle in degrees, in [0, 90] (3-D; map_panels passes the metric's in-plane
               angle instead).
    "alpha"    log10 α (one row per channel, αx and αy), shared colour range; error = |Δ ln α|.
    "scalar"   values (one row per channel), shared colour range; error = |Δ|.
Texture maps are drawn with origin "lower" (row 0 = minimum y at the bottom: the sample seen from above,
+x right, +y up; reference §7.1 orientation), camera images with origin "upper". Error colour bars span
0 to the 99.5th percentile of the error (arrow when larger values are clipped).
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.atomic import atomic_folder, atomic_path, write_bytes_atomic
from twin.materials.samples import SVBRDFMaps, canonical_anisotropy

from reconstruction.evaluation.metrics import (ANISOTROPY_RATIO, _angle_deg, _axis_angle_deg, _check_mask, _fmt_any, _fmt_value,
                      _tangent_error_deg, flatten_metrics, to_jsonable)

__all__ = ["PANEL_KINDS", "FigurePanel", "Panel", "RenderPanel", "map_panels", "render_panel", "write_report"]

DISPLAY_PERCENTILE = 99.5  # display exposure and error colour-bar top: robust to a few hot pixels
PANEL_KINDS = ("rgb", "normal", "tangent", "alpha", "scalar")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


# --- panels -----------------------------------------------------------------------------------------


def _panel_name(name) -> str:
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"panel name {name!r} must be letters, digits, '_', '-', '.' (it names a PNG)")
    return name


def _check_exposure(exposure) -> None:
    if exposure is not None and not (isinstance(exposure, (int, float, np.integer, np.floating))
                                     and math.isfinite(exposure) and exposure > 0):
        raise ValueError(f"exposure must be a positive finite number or None, got {exposure!r}")


@dataclass(frozen=True, eq=False)
class Panel:
    """One PNG "truth | reconstruction | |error|" (module docstring for the kinds). truth and recon are
    (H, W, C) or (H, W) arrays of the same shape; NaN marks "no data". `channels` labels the rows of the
    colour-mapped kinds (default αx, αy for a 2-channel alpha). `error` (H, W), optional, replaces the
    kind's own error image of an rgb / normal / tangent panel (map_panels passes the metric's in-plane
    tangent error, which needs the truth's normal)."""

    name: str
    truth: np.ndarray
    recon: np.ndarray
    kind: str
    exposure: float | None = None
    caption: str = ""
    origin: str = "lower"
    channels: tuple[str, ...] | None = None
    error: np.ndarray | None = None

    def __post_init__(self):
        _panel_name(self.name)
        if self.kind not in PANEL_KINDS:
            raise ValueError(f"panel {self.name}: kind must be one of {PANEL_KINDS}, got {self.kind!r}")
        t = np.asarray(self.truth, dtype=np.float64)
        r = np.asarray(self.recon, dtype=np.float64)
        t = t[..., None] if t.ndim == 2 else t
        r = r[..., None] if r.ndim == 2 else r
        if t.ndim != 3 or t.shape != r.shape or min(t.shape) < 1:
            raise ValueError(f"panel {self.name}: truth {np.shape(self.truth)} and recon {np.shape(self.recon)} "
                             "must both be (H, W, C) or (H, W), of the same shape")
        if self.kind in ("rgb", "normal", "tangent") and t.shape[2] != 3:
            raise ValueError(f"panel {self.name}: kind {self.kind!r} needs 3 channels, got {t.shape[2]}")
        if self.origin not in ("lower", "upper"):
            raise ValueError(f"panel {self.name}: origin must be 'lower' or 'upper', got {self.origin!r}")
        _check_exposure(self.exposure)
        if self.channels is not None and len(self.channels) != t.shape[2]:
            raise ValueError(f"panel {self.name}: {len(self.channels)} channel labels for {t.shape[2]} channels")
        if self.error is not None:
            e = np.asarray(self.error, dtype=np.float64)
            if e.shape != t.shape[:2] or self.kind not in ("rgb", "normal", "tangent"):
                raise ValueError(f"panel {self.name}: error must be (H, W) = {t.shape[:2]} and only replaces the "
                                 f"error of the single-row kinds rgb, normal, tangent; got {e.shape}, {self.kind!r}")
            object.__setattr__(self, "error", e)
        object.__setattr__(self, "truth", t)
        object.__setattr__(self, "recon", r)


@dataclass(frozen=True, eq=False)
class RenderPanel:
    """Reference §6.4's per-pattern picture: "photo | latent render | texture render" on top and
    |latent − photo|, |texture − photo| below (shared error scale). Images (H, W, 3), linear, camera
    pixel grid (origin "upper"); one exposure from the photo for all three."""

    name: str
    photo: np.ndarray
    latent_render: np.ndarray
    map_render: np.ndarray
    exposure: float | None = None
    caption: str = ""
    origin: str = "upper"

    def __post_init__(self):
        _panel_name(self.name)
        arrs = [np.asarray(getattr(self, k), dtype=np.float64) for k in ("photo", "latent_render", "map_render")]
        if arrs[0].ndim != 3 or arrs[0].shape[2] != 3 or any(a.shape != arrs[0].shape for a in arrs):
            raise ValueError(f"panel {self.name}: photo, latent_render and map_render must all be (H, W, 3) of "
                             f"one shape, got {[a.shape for a in arrs]}")
        if self.origin not in ("lower", "upper"):
            raise ValueError(f"panel {self.name}: origin must be 'lower' or 'upper', got {self.origin!r}")
        _check_exposure(self.exposure)
        for k, a in zip(("photo", "latent_render", "map_render"), arrs):
            object.__setattr__(self, k, a)


def _srgb(v: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1)."""
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1.0 / 2.4) - 0.055)


_GREY = 0.5  # "no data"


def _auto_exposure(img: np.ndarray) -> float:
    v = img[np.isfinite(img)]
    top = float(np.percentile(v, DISPLAY_PERCENTILE)) if v.size else 0.0
    return 1.0 / top if top > 0 else 1.0


def _rgb_display(img: np.ndarray, exposure: float) -> np.ndarray:
    bad = ~np.all(np.isfinite(img), axis=-1, keepdims=True)
    return np.where(bad, _GREY, _srgb(np.where(bad, 0.0, img) * exposure))


@dataclass(frozen=True, eq=False)
class FigurePanel:
    """A picture drawn by its own function: draw(path) writes the PNG at `path` (atomically) and returns it
    (e.g. reconstruction.evaluation.novel_views.directions_figure)."""

    name: str
    draw: object
    caption: str = ""

    def __post_init__(self):
        _panel_name(self.name)
        if not callable(self.draw):
            raise TypeError(f"panel {self.name}: draw must be a function of the PNG's path")


def _tangent_display(t: np.ndarray) -> np.ndarray:
    from matplotlib.colors import hsv_to_rgb

    bad = ~np.all(np.isfinite(t), axis=-1, keepdims=True)
    phi = np.mod(np.arctan2(t[..., 1], t[..., 0]), np.pi)  # axis orientation: t and −t alike
    hsv = np.stack([np.nan_to_num(phi / np.pi) % 1.0, np.ones_like(phi), np.ones_like(phi)], axis=-1)
    return np.where(bad, _GREY, hsv_to_rgb(hsv))


@dataclass
class _Tile:
    data: np.ndarray  # (H, W, 3) display RGB, or (H, W) values for a colour map
    title: str
    cmap: str | None = None
    vmin: float = 0.0
    vmax: float = 1.0
    label: str = ""
    extend: str = "neither"


def _error_tile(err: np.ndarray, title: str, label: str, vmax: float | None = None) -> _Tile:
    top, extend = _error_range(err) if vmax is None else (vmax, "max" if _finite_max(err) > vmax * (1.0 + 1e-6)
                                                          else "neither")
    return _Tile(err, title, "inferno", 0.0, top, label, extend)


def _finite_max(a: np.ndarray) -> float:
    v = a[np.isfinite(a)]
    return float(v.max()) if v.size else 0.0


def _error_range(*errs: np.ndarray) -> tuple[float, str]:
    """Colour-bar top for error images: the 99.5th percentile of the finite errors (1 if all zero)."""
    v = np.concatenate([e[np.isfinite(e)].ravel() for e in errs])
    if v.size == 0:
        return 1.0, "neither"
    top = float(np.percentile(v, DISPLAY_PERCENTILE))
    top = top if top > 0 else (float(v.max()) if v.max() > 0 else 1.0)
    return top, "max" if v.max() > top * (1.0 + 1e-6) else "neither"


def _value_range(*arrs: np.ndarray) -> tuple[float, float]:
    v = np.concatenate([a[np.isfinite(a)].ravel() for a in arrs])
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    return (lo, hi) if hi > lo else (lo - 0.5, hi + 0.5)


def _panel_tiles(p: Panel) -> list[list[_Tile | None]]:
    t, r = p.truth, p.recon
    if p.kind == "rgb":
        e = p.exposure if p.exposure is not None else _auto_exposure(t)
        err = np.mean(np.abs(r - t), axis=-1) if p.error is None else p.error
        return [[_Tile(_rgb_display(t, e), f"truth (sRGB, ×{e:.3g})"),
                 _Tile(_rgb_display(r, e), f"reconstruction (×{e:.3g})"),
                 _error_tile(err, "|error|, mean over RGB", "linear units")]]
    if p.kind == "normal":
        disp = lambda n: np.where(np.isfinite(n), np.clip(n * 0.5 + 0.5, 0.0, 1.0), _GREY)  # noqa: E731
        return [[_Tile(disp(t), "truth (n·0.5+0.5)"), _Tile(disp(r), "reconstruction"),
                 _error_tile(_angle_deg(r, t) if p.error is None else p.error, "angular error", "degrees")]]
    if p.kind == "tangent":
        return [[_Tile(_tangent_display(t), "truth (axis angle as hue)"),
                 _Tile(_tangent_display(r), "reconstruction"),
                 _error_tile(_axis_angle_deg(r, t) if p.error is None else p.error, "axis error (mod 180°)",
                             "degrees")]]
    c = t.shape[2]
    labels = p.channels or (("αx", "αy") if p.kind == "alpha" and c == 2 else tuple(f"ch {i}" for i in range(c)))
    rows = []
    for i in range(c):
        ti, ri = t[..., i], r[..., i]
        if p.kind == "alpha":
            with np.errstate(divide="ignore", invalid="ignore"):
                lt = np.where(ti > 0, np.log10(np.where(ti > 0, ti, 1.0)), np.nan)
                lr = np.where(ri > 0, np.log10(np.where(ri > 0, ri, 1.0)), np.nan)
            lo, hi = _value_range(lt, lr)
            err = np.abs(lr - lt) * math.log(10.0)
            rows.append([_Tile(lt, f"truth {labels[i]}", "viridis", lo, hi, "log10 α"),
                         _Tile(lr, f"reconstruction {labels[i]}", "viridis", lo, hi, "log10 α"),
                         _error_tile(err, f"|Δ ln {labels[i]}|", "|Δ ln α|")])
        else:
            lo, hi = _value_range(ti, ri)
            rows.append([_Tile(ti, f"truth {labels[i]}", "viridis", lo, hi),
                         _Tile(ri, f"reconstruction {labels[i]}", "viridis", lo, hi),
                         _error_tile(np.abs(ri - ti), f"|error| {labels[i]}", "")])
    return rows


def _render_tiles(p: RenderPanel) -> list[list[_Tile | None]]:
    e = p.exposure if p.exposure is not None else _auto_exposure(p.photo)
    el = np.mean(np.abs(p.latent_render - p.photo), axis=-1)
    em = np.mean(np.abs(p.map_render - p.photo), axis=-1)
    top, _ = _error_range(el, em)
    return [[_Tile(_rgb_display(p.photo, e), f"photo (sRGB, ×{e:.3g})"),
             _Tile(_rgb_display(p.latent_render, e), "latent render"),
             _Tile(_rgb_display(p.map_render, e), "texture render")],
            [None, _error_tile(el, "|latent − photo|", "linear units", top),
             _error_tile(em, "|texture − photo|", "linear units", top)]]


def _save_panel(p: Panel | RenderPanel, path) -> Path:
    """Draw a panel's tile grid with matplotlib's Agg canvas (never pyplot: headless, no global state)
    and write the PNG atomically."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure

    rows = _panel_tiles(p) if isinstance(p, Panel) else _render_tiles(p)
    h, w = (p.truth if isinstance(p, Panel) else p.photo).shape[:2]
    aspect = h / w
    ncols = 3
    fig = Figure(figsize=(ncols * 3.6, len(rows) * 3.0 * aspect + 0.7 + 0.25 * len(rows)), dpi=100,
                 layout="constrained", facecolor="white")
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(rows), ncols, squeeze=False)
    # a column with a colour bar anywhere reserves its space in every row (kept invisible where there is
    # no bar), so the images of one column stay aligned
    barred = [any(r[c] is not None and r[c].cmap is not None for r in rows) for c in range(ncols)]
    for ax_row, tiles in zip(axes, rows):
        for c, (ax, tile) in enumerate(zip(ax_row, tiles)):
            ax.set_axis_off()
            if tile is None:
                continue
            ax.set_title(tile.title, fontsize=9)
            if tile.cmap is None:
                ax.imshow(tile.data, origin=p.origin, interpolation="antialiased")
                if barred[c]:
                    fig.colorbar(ScalarMappable(), ax=ax, fraction=0.046, pad=0.02).ax.set_visible(False)
            else:
                cmap = colormaps[tile.cmap].with_extremes(bad=(_GREY, _GREY, _GREY))
                im = ax.imshow(np.ma.masked_invalid(tile.data), cmap=cmap, vmin=tile.vmin, vmax=tile.vmax,
                               origin=p.origin, interpolation="antialiased")
                cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, extend=tile.extend)
                cb.ax.tick_params(labelsize=7)
                if tile.label:
                    cb.set_label(tile.label, fontsize=8)
    fig.suptitle(p.name + (f": {p.caption}" if p.caption else ""), fontsize=10)
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=100, facecolor="white")
    return path


def render_panel(name: str, photo, latent_render, map_render, path, *, exposure: float | None = None,
                 caption: str = "") -> Path:
    """Write reference §6.4's per-pattern PNG (RenderPanel) to `path`."""
    return _save_panel(RenderPanel(name, photo, latent_render, map_render, exposure, caption), path)


def map_panels(truth: SVBRDFMaps, recon: SVBRDFMaps, mask=None,
               anisotropy_ratio: float = ANISOTROPY_RATIO) -> list[Panel]:
    """The standard map panels (both maps on one grid, in the αx ≥ αy convention): ρd (exposure 1: an
    albedo is shown as is), ρs (automatic exposure: ρs goes up to 10), normal, tangent (only where the
    truth's αx/αy ≥ anisotropy_ratio, as the metric), α, transparency. Texels outside `mask` are no data."""
    if truth.shape != recon.shape:
        raise ValueError(f"truth {truth.shape} and recon {recon.shape} are on different grids (resample_maps)")
    sel = _check_mask(mask, truth.shape)
    t = canonical_anisotropy(truth)
    r = canonical_anisotropy(recon)

    def only(a, keep):
        a = a.astype(np.float64)
        return np.where(keep[..., None] if a.ndim == 3 else keep, a, np.nan)

    aniso = sel & (t.alpha_x >= anisotropy_ratio * t.alpha_y)
    return [
        Panel("rho_d", only(t.rho_d, sel), only(r.rho_d, sel), "rgb", exposure=1.0, caption="diffuse albedo ρd"),
        Panel("rho_s", only(t.rho_s, sel), only(r.rho_s, sel), "rgb", caption="specular albedo ρs"),
        Panel("normal", only(t.normal, sel), only(r.normal, sel), "normal", caption="shading normal"),
        Panel("tangent", only(t.tangent, aniso), only(r.tangent, aniso), "tangent",
              caption=f"tangent where true αx/αy ≥ {anisotropy_ratio:g}; error in the true tangent plane",
              error=np.where(aniso, _tangent_error_deg(t.normal, t.tangent, r.tangent), np.nan)),
        Panel("alpha", only(t.alpha, sel), only(r.alpha, sel), "alpha", caption="GGX roughness, αx ≥ αy"),
        Panel("transparency", only(t.transparency, sel), only(r.transparency, sel), "scalar",
              caption="transparency β", channels=("β",)),
    ]


# --- the report folder ------------------------------------------------------------------------------


def _is_table(v) -> bool:
    """A list of rows (dicts), e.g. the novel views' 560 pairs: in metrics.json, counted in report.md."""
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _md_cell(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def write_report(out_dir, *, title: str, metrics: dict, checks: list[dict], panels=(), notes=()) -> dict:
    """Write out_dir/images/<panel>.png, out_dir/metrics.json and out_dir/report.md
    as one folder (module docstring). Returns {"metrics_json": path, "report_md": path,
    "images": {name: path}}."""
    if not isinstance(title, str) or not title.strip():
        raise ValueError("title must be a non-empty string")
    if not isinstance(metrics, dict):
        raise TypeError(f"metrics must be a dict, got {type(metrics).__name__}")
    panels = list(panels)
    notes = [str(n) for n in notes]
    for p in panels:
        if not isinstance(p, (Panel, RenderPanel, FigurePanel)):
            raise TypeError(f"panels must be Panel, RenderPanel or FigurePanel, got {type(p).__name__}")
    names = [p.name for p in panels]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"panel names must be unique (they name the PNGs); repeated: {', '.join(dup)}")
    out = Path(out_dir)
    passed = all(c["passed"] for c in checks) if checks else None
    doc = to_jsonable({"title": title, "passed": passed, "checks": checks, "metrics": metrics, "notes": notes})
    blob = (json.dumps(doc, indent=2, allow_nan=False) + "\n").encode()  # fails before any file is written

    md = [f"# {title}", ""]
    if passed is None:
        md.append("**Result: no thresholds checked.**")
    else:
        n_ok = sum(c["passed"] for c in checks)
        md.append(f"**Result: {'PASS' if passed else 'FAIL'}** ({n_ok} of {len(checks)} thresholds met).")
    if checks:
        md += ["", "| metric | value | threshold | result | why |", "|---|---:|---|---|---|"]
        md += [f"| `{_md_cell(c['metric'])}` | {_fmt_value(c['value'])} | {c['op']} {c['threshold']:g} | "
               f"{'PASS' if c['passed'] else '**FAIL**'} | {_md_cell(c.get('why', ''))} |" for c in checks]
    if notes:
        md += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    if panels:
        md += ["", "## Images", ""]
        for p in panels:
            md += [f"### {p.name}", ""] + ([p.caption, ""] if p.caption else [])
            md += [f"![{p.name}](images/{p.name}.png)", ""]
    md += ["", "## All metrics", "", "```text"]
    md += [f"{k} = {len(v)} rows (metrics.json)" if _is_table(v) else f"{k} = {_fmt_any(v)}"
           for k, v in flatten_metrics(metrics).items()]
    md += ["```", "", "metrics.json holds the same numbers (NaN as null, ±inf as \"inf\" / \"-inf\").", ""]
    text = re.sub(r"\n{3,}", "\n\n", "\n".join(md))  # one blank line between blocks
    # the whole folder at once: a failed or killed run leaves the previous report (or none), never a mix
    with atomic_folder(out, overwrite=True) as tmp:
        for p in panels:
            png = tmp / "images" / f"{p.name}.png"
            if isinstance(p, FigurePanel):
                p.draw(png)
            else:
                _save_panel(p, png)
        write_bytes_atomic(tmp / "metrics.json", blob)
        write_bytes_atomic(tmp / "report.md", text.encode())
    return {"metrics_json": out / "metrics.json", "report_md": out / "report.md",
            "images": {p.name: out / "images" / f"{p.name}.png" for p in panels}}
