"""The validation report (issue #6 item 6): map errors against the ground truth, image scores against the
held-out photo, thresholds, and the report folder. Pure functions of arrays: no pipeline logic here.

    truth_g = resample_maps(truth, recon.size_mm, recon.resolution)   # truth onto the reconstruction grid
    inside = truth_coverage(truth, recon.size_mm, recon.resolution)   # texel centres on the true sample
    m = map_errors(truth_g, recon, mask=inside)                      # dict, see map_errors
    s = image_scores(photo, render, mask=on_sample)                  # {"ssim", "ssim_all", "psnr_db", ...}
    rows = check({"maps": m, "render": s}, [Threshold("maps.normal_deg.median", "<=", 1.0, "goal, #6")])
    print(format_table(rows))
    write_report(out, title=..., metrics=..., checks=rows, panels=map_panels(truth_g, recon) + [...],
                 notes=[...])          # -> {"metrics_json", "report_md", "images": {name: path}}
    render_panel(name, photo, latent_render, map_render, path)       # reference §6.4's per-pattern triptych

Metric conventions (every statistic is a {"median", "mean", "p90", "count"} dict over the texels used):
* normal_deg: angle between n̂ and n, atan2(|n̂ × n|, n̂ · n) (exact near 0°, where arccos is not).
* tangent_deg: the tangent is an axis (t and −t give the same BRDF), so the angle is taken modulo 180°,
  in [0°, 90°]. Both maps are first put in the export convention αx ≥ αy (reference §5,
  `canonical_anisotropy`), so t is the axis of the larger roughness on both sides. Only texels whose TRUE
  αx/αy ≥ `anisotropy_ratio` (1.5, issue #6) count: on near-isotropic texels the tangent is undefined
  (reference §7.1 expects "discontinuities where the material is near-isotropic"). The angle is measured in
  the truth's tangent plane (t̂ projected onto it), so it is the error of the anisotropy's orientation
  alone; the tilt of the frame is the normal error, reported separately.
* log_alpha_x / log_alpha_y: |ln α̂ − ln α| after the canonical ordering on both sides; alpha_x_pct /
  alpha_y_pct give each statistic s as the relative error 100·(exp(s) − 1) % (exact for the median and
  p90, which commute with the monotone map; for the mean it is the geometric-mean factor).
* rho_d_pct / rho_s_pct: 100·|ρ̂ − ρ| / max(ρ, floor) per channel (pooled, and per channel "r", "g", "b").
  The floor (RHO_FLOOR: 5 % of each map's full range, ρd 1 and ρs 10 = the reference's ps_range, §7.1;
  ours) stops dark texels from dominating: at ρ → 0 any absolute error becomes an unbounded relative one,
  and there the photo's noise floor, not the method, sets the error; below the floor the metric is the
  absolute error in units of the floor.
* transparency_abs: |β̂ − β| (absolute: β = 0, opaque, is the common value, so a relative error is
  meaningless).
* Empty selections (no anisotropic texel, an empty mask) give NaN statistics with count 0; NaN fails
  every threshold.

Image scores (`image_scores`): SSIM is scikit-image's `structural_similarity(channel_axis=-1)` with its
defaults (7 × 7 uniform window, K1 = 0.01, K2 = 0.03), as reference §6.4. Reference §6.4 uses data_range =
255 on photos scaled by 10.2, i.e. a fixed range of 25 photo units tied to its camera's exposure. Ours:
the reference image's own range (max − min over the image, masked pixels zero). SSIM's constants are
(K·L)², so with L proportional to the image's scale SSIM does not change when both images are scaled
together (exposure, units), and a dim pattern is not scored as "nearly black = nearly perfect". Pass
`data_range` for a fixed exposure instead. PSNR = 10 log10(L² / MSE) with the same L, MSE over the mask's
pixels only (so the amount of background in the frame does not inflate it); identical images give
PSNR = inf, which, being non-finite, fails any threshold (it usually means something was compared with
itself). Masked-out pixels are zero in both images (reference §6.4: empty pixels are zero and still enter
the SSIM windows); "ssim" averages the SSIM map over the mask's pixels (ours), "ssim_all" over the whole
image as skimage and reference §6.4 do.

Report folder (`write_report`): metrics.json ({"title", "passed", "checks", "metrics", "notes"}; NaN is
written as null, ±inf as the strings "inf" / "-inf", so the file is strict JSON), report.md (result,
table, notes, images, every metric), images/<panel>.png. Every file is written atomically
(twin.atomic): a reader sees the old file or the complete new one, and no temporary file stays behind.

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

from twin.atomic import atomic_path, write_bytes_atomic
from twin.samples import ALPHA_RANGE, RHO_D_RANGE, RHO_S_RANGE, SVBRDFMaps, canonical_anisotropy

__all__ = [
    "ANISOTROPY_RATIO", "RHO_FLOOR", "PANEL_KINDS", "resample_maps", "truth_coverage", "map_errors",
    "image_scores", "Threshold", "check", "format_table", "flatten_metrics", "Panel", "RenderPanel",
    "map_panels", "render_panel", "write_report", "to_jsonable",
]

ANISOTROPY_RATIO = 1.5  # issue #6: tangent error "where αx/αy ≥ 1.5"
# 5 % of each map's full range (ρd ∈ [0, 1]; ρs ∈ [0, 10], the reference's ps_range, §7.1). Ours.
RHO_FLOOR = (0.05, 0.5)
STAT_PERCENTILE = 90.0
DISPLAY_PERCENTILE = 99.5  # display exposure and error colour-bar top: robust to a few hot pixels
PANEL_KINDS = ("rgb", "normal", "tangent", "alpha", "scalar")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_SNAP = 1e-9  # texel coordinates this close to an integer are that integer (exact identity resampling)


# --- resampling the truth onto the reconstruction grid ---------------------------------------------


def _grid_coords(truth: SVBRDFMaps, size_mm: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous truth (row, col) coordinates (each (resolution,), float64) of the texel centres of a
    square grid of `resolution` texels over `size_mm`, centred on the same origin (twin.samples
    conventions: texel (i, j) centre at −size/2 + (j + 0.5)·size/res; truth texel centre (i, j) = (i, j))."""
    if isinstance(size_mm, bool) or not isinstance(size_mm, (int, float, np.integer, np.floating)) \
            or not math.isfinite(size_mm) or size_mm <= 0:
        raise ValueError(f"size_mm must be a positive finite number of millimetres, got {size_mm!r}")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    x = -0.5 * size_mm + (np.arange(resolution) + 0.5) * (size_mm / resolution)
    h, w = truth.shape
    s = truth.size_mm
    col = (x + 0.5 * s) * (w / s) - 0.5
    row = (x + 0.5 * s) * (h / s) - 0.5
    snap = lambda c: np.where(np.abs(c - np.rint(c)) < _SNAP, np.rint(c), c)  # noqa: E731
    return snap(row), snap(col)


def truth_coverage(truth: SVBRDFMaps, size_mm: float, resolution: int) -> np.ndarray:
    """(resolution, resolution) bool: which texel centres of the reconstruction grid lie on the true
    sample (outside it `resample_maps` repeats the edge texels, which are not ground truth)."""
    row, col = _grid_coords(truth, size_mm, resolution)
    h, w = truth.shape
    in_r = (row >= -0.5) & (row <= h - 0.5)
    in_c = (col >= -0.5) & (col <= w - 0.5)
    return in_r[:, None] & in_c[None, :]


def _bilinear(img: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Separable bilinear interpolation of img (H, W, ...) at the grid rows × cols (float64), clamped
    to the edge texels."""
    def axis(c, n):
        c = np.clip(c, 0.0, n - 1.0)
        i0 = np.clip(np.floor(c).astype(np.int64), 0, max(n - 2, 0))
        i1 = np.minimum(i0 + 1, n - 1)
        return i0, i1, c - i0

    r0, r1, fr = axis(row, img.shape[0])
    c0, c1, fc = axis(col, img.shape[1])
    a = img.astype(np.float64)
    extra = (1,) * (a.ndim - 2)
    fr = fr.reshape((-1, 1) + extra)
    fc = fc.reshape((1, -1) + extra)
    rows = a[r0] * (1.0 - fr) + a[r1] * fr
    return rows[:, c0] * (1.0 - fc) + rows[:, c1] * fc


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def resample_maps(truth: SVBRDFMaps, size_mm: float, resolution: int) -> SVBRDFMaps:
    """The truth on the reconstruction's grid (square, `resolution` texels over `size_mm`, same centre).

    Bilinear at the new texel centres (edge texels repeated outside the truth: use `truth_coverage` to
    mask them) for ρd, ρs, β and the normal (then renormalised); α in log space (geometric interpolation,
    the space of the |log α| metric, and exact on the log-linear ramps). The tangent comes from the
    NEAREST truth texel, because it is an axis (t ≡ −t) and near-isotropic texels carry arbitrary
    tangents: averaging t with a neighbour's −t would cancel it. It is then re-orthogonalised against the
    interpolated normal (Gram-Schmidt), falling back to (0, 1, 0) × n if it was parallel to n. Values
    are clipped to the maps' ranges only to absorb float rounding."""
    if not isinstance(truth, SVBRDFMaps):
        raise TypeError(f"truth must be SVBRDFMaps, got {type(truth).__name__}")
    row, col = _grid_coords(truth, size_mm, resolution)
    rho_d = np.clip(_bilinear(truth.rho_d, row, col), *RHO_D_RANGE)
    rho_s = np.clip(_bilinear(truth.rho_s, row, col), *RHO_S_RANGE)
    beta = np.clip(_bilinear(truth.transparency, row, col), 0.0, 1.0)
    alpha = np.clip(np.exp(_bilinear(np.log(truth.alpha.astype(np.float64)), row, col)), *ALPHA_RANGE)
    n = _unit(_bilinear(truth.normal, row, col))
    h, w = truth.shape
    ri = np.clip(np.rint(row), 0, h - 1).astype(np.int64)
    ci = np.clip(np.rint(col), 0, w - 1).astype(np.int64)
    t = truth.tangent.astype(np.float64)[ri][:, ci]
    t = t - np.sum(t * n, axis=-1, keepdims=True) * n
    norm = np.linalg.norm(t, axis=-1, keepdims=True)
    fallback = np.cross(np.array([0.0, 1.0, 0.0]), n)
    t = np.where(norm > 1e-6, t / np.maximum(norm, 1e-300), _unit(fallback))
    return SVBRDFMaps(rho_d, rho_s, alpha, n, t, beta, float(size_mm), truth.name)


# --- map errors -------------------------------------------------------------------------------------


def _stats(values: np.ndarray) -> dict:
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        return {"median": math.nan, "mean": math.nan, "p90": math.nan, "count": 0}
    return {"median": float(np.median(v)), "mean": float(np.mean(v)),
            "p90": float(np.percentile(v, STAT_PERCENTILE)), "count": int(v.size)}


def _pct_of_log(stats: dict) -> dict:
    """A |log| statistic as the relative error 100·(exp(s) − 1) %."""
    return {k: (100.0 * math.expm1(v) if k != "count" else v) for k, v in stats.items()}


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors (..., 3), atan2(|a × b|, a · b) in degrees (accurate at small angles)."""
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


def _axis_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between the axes of a and b (t ≡ −t), in [0°, 90°]."""
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.abs(np.sum(a * b, axis=-1))))


def _tangent_error_deg(n: np.ndarray, t: np.ndarray, t_hat: np.ndarray) -> np.ndarray:
    """Axis angle (degrees, [0, 90]) between t̂ and the true tangent t, in the truth's tangent plane
    (normal n): from the components of t̂ along t and along b = n × t. A t̂ parallel to n has no
    orientation in that plane and scores the worst, 90°."""
    n, t, t_hat = (a.astype(np.float64) for a in (n, t, t_hat))
    along = np.sum(t_hat * t, axis=-1)
    across = np.sum(t_hat * np.cross(n, t), axis=-1)
    ang = np.degrees(np.arctan2(np.abs(across), np.abs(along)))
    return np.where(along ** 2 + across ** 2 > 1e-12, ang, 90.0)


def _check_mask(mask, shape: tuple[int, int]) -> np.ndarray:
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.dtype != bool:
        raise ValueError(f"mask must be a boolean array, got dtype {m.dtype}")
    if m.shape != tuple(shape):
        raise ValueError(f"mask must have shape {tuple(shape)} (H, W), got {m.shape}")
    return m


def _floors(rho_floor) -> tuple[float, float]:
    f = (rho_floor, rho_floor) if np.isscalar(rho_floor) else tuple(rho_floor)
    if len(f) != 2 or not all(isinstance(x, (int, float, np.integer, np.floating)) and math.isfinite(x)
                              and x > 0 for x in f):
        raise ValueError(f"rho_floor must be a positive number or a (rho_d, rho_s) pair of them, got "
                         f"{rho_floor!r}")
    return float(f[0]), float(f[1])


def map_errors(truth: SVBRDFMaps, recon: SVBRDFMaps, mask=None, anisotropy_ratio: float = ANISOTROPY_RATIO,
               rho_floor=RHO_FLOOR) -> dict:
    """Errors of reconstructed maps against the truth ON THE SAME GRID (resample the truth first:
    `resample_maps`). `mask` (H, W) bool selects the texels (default: all). `rho_floor`: one floor for
    both albedos or a (ρd, ρs) pair. Returns (module docstring for the definitions):

        {"texels": N, "normal_deg": S, "tangent_deg": S, "log_alpha_x": S, "log_alpha_y": S,
         "alpha_x_pct": S, "alpha_y_pct": S, "rho_d_pct": S + {"r": S, "g": S, "b": S},
         "rho_s_pct": (same), "transparency_abs": S,
         "settings": {"anisotropy_ratio", "rho_d_floor", "rho_s_floor"}}

    with S = {"median", "mean", "p90", "count"}."""
    for k, m in (("truth", truth), ("recon", recon)):
        if not isinstance(m, SVBRDFMaps):
            raise TypeError(f"{k} must be SVBRDFMaps, got {type(m).__name__}")
    if truth.shape != recon.shape or not math.isclose(truth.size_mm, recon.size_mm, rel_tol=1e-6):
        raise ValueError(f"truth ({truth.shape[0]}² texels over {truth.size_mm:g} mm) and reconstruction "
                         f"({recon.shape[0]}² over {recon.size_mm:g} mm) are on different grids; resample the "
                         "truth onto the reconstruction grid first (resample_maps)")
    if not (isinstance(anisotropy_ratio, (int, float, np.integer, np.floating))
            and math.isfinite(anisotropy_ratio) and anisotropy_ratio >= 1.0):
        raise ValueError(f"anisotropy_ratio must be a finite number >= 1, got {anisotropy_ratio!r}")
    fd, fs = _floors(rho_floor)
    sel = _check_mask(mask, truth.shape)
    t = canonical_anisotropy(truth)
    r = canonical_anisotropy(recon)
    out = {"texels": int(sel.sum())}
    out["normal_deg"] = _stats(_angle_deg(r.normal[sel], t.normal[sel]))

    aniso = sel & (t.alpha_x >= anisotropy_ratio * t.alpha_y)
    out["tangent_deg"] = _stats(_tangent_error_deg(t.normal[aniso], t.tangent[aniso], r.tangent[aniso]))

    for c, name in ((0, "x"), (1, "y")):
        err = np.abs(np.log(r.alpha[..., c][sel].astype(np.float64)) - np.log(t.alpha[..., c][sel].astype(
            np.float64)))
        s = _stats(err)
        out[f"log_alpha_{name}"] = s
        out[f"alpha_{name}_pct"] = _pct_of_log(s)

    for key, floor in (("rho_d", fd), ("rho_s", fs)):
        true = getattr(t, key)[sel].astype(np.float64)
        rel = 100.0 * np.abs(getattr(r, key)[sel].astype(np.float64) - true) / np.maximum(true, floor)
        s = _stats(rel)
        s.update({ch: _stats(rel[:, i]) for i, ch in enumerate("rgb")})
        out[f"{key}_pct"] = s
    out["transparency_abs"] = _stats(np.abs(r.transparency[sel].astype(np.float64)
                                            - t.transparency[sel].astype(np.float64)))
    out["settings"] = {"anisotropy_ratio": float(anisotropy_ratio), "rho_d_floor": fd, "rho_s_floor": fs}
    return out


# --- image scores -----------------------------------------------------------------------------------


def _image(a, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"{what} must have shape (H, W, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise ValueError(f"{what} has non-finite values (first at row {bad[0]}, col {bad[1]})")
    return a


def image_scores(reference, test, mask=None, data_range: float | None = None) -> dict:
    """SSIM and PSNR of `test` against `reference` (both (H, W, 3), linear); pixels outside `mask` (H, W)
    bool are zero in both. data_range: default the reference's range (module docstring). Returns
    {"ssim", "ssim_all", "psnr_db", "data_range", "pixels"}."""
    from skimage.metrics import structural_similarity

    ref = _image(reference, "reference")
    tst = _image(test, "test")
    if ref.shape != tst.shape:
        raise ValueError(f"reference {ref.shape} and test {tst.shape} differ in shape")
    h, w = ref.shape[:2]
    win = 7  # skimage's default window (reference §6.4)
    if min(h, w) < win:
        raise ValueError(f"images must be at least {win} x {win} pixels for SSIM's window, got {h} x {w}")
    sel = _check_mask(mask, (h, w))
    ref = np.where(sel[..., None], ref, 0.0)
    tst = np.where(sel[..., None], tst, 0.0)
    if data_range is None:
        data_range = float(ref.max() - ref.min())
        if not data_range > 0:
            raise ValueError("the reference image is constant over the mask; pass data_range explicitly")
    elif not (math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"data_range must be positive and finite, got {data_range!r}")
    ssim_all, smap = structural_similarity(ref, tst, channel_axis=-1, data_range=data_range, full=True)
    pad = (win - 1) // 2  # skimage averages inside this border; so do we
    inner = np.zeros((h, w), dtype=bool)
    inner[pad:h - pad, pad:w - pad] = True
    use = sel & inner
    ssim = float(smap[use].mean()) if use.any() else math.nan
    n = int(sel.sum())
    mse = float(np.mean((ref[sel] - tst[sel]) ** 2)) if n else math.nan
    psnr = math.inf if mse == 0 else 10.0 * math.log10(data_range ** 2 / mse)
    return {"ssim": ssim, "ssim_all": float(ssim_all), "psnr_db": psnr, "data_range": float(data_range),
            "pixels": n}


# --- thresholds -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Threshold:
    """A pass condition on one metric: `metric` is a dotted key into the metrics dict (e.g.
    "maps.normal_deg.median"), op "<=" or ">=", and `why` says where the number comes from."""

    metric: str
    op: str
    value: float
    why: str

    def __post_init__(self):
        if not isinstance(self.metric, str) or not self.metric.strip():
            raise ValueError(f"metric must be a non-empty dotted key, got {self.metric!r}")
        if self.op not in ("<=", ">="):
            raise ValueError(f"op must be '<=' or '>=', got {self.op!r}")
        if isinstance(self.value, bool) or not isinstance(self.value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(self.value):
            raise ValueError(f"threshold value for {self.metric} must be a finite number, got {self.value!r}")
        if not isinstance(self.why, str) or not self.why.strip():
            raise ValueError(f"threshold for {self.metric}: say why (where the number comes from)")
        object.__setattr__(self, "value", float(self.value))


def _lookup(metrics: dict, key: str):
    """The value at a dotted key, as a float (None when absent; JSON's null and "nan"/"inf" strings
    read back as NaN / inf, so a loaded metrics.json can be checked again)."""
    node = metrics
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    if node is None:
        return math.nan
    if isinstance(node, str) and node in ("nan", "inf", "-inf"):
        return float(node)
    if isinstance(node, bool) or not isinstance(node, (int, float, np.integer, np.floating)):
        raise ValueError(f"metric {key!r} is not a number but {type(node).__name__}"
                         + (f" (keys: {', '.join(node)})" if isinstance(node, dict) else ""))
    return float(node)


def check(metrics: dict, thresholds) -> list[dict]:
    """One row per threshold: {"metric", "value", "op", "threshold", "passed", "why"}. A metric that is
    absent (value None) or not finite (NaN, ±inf) fails."""
    rows = []
    for th in thresholds:
        if not isinstance(th, Threshold):
            raise TypeError(f"expected Threshold, got {type(th).__name__}")
        v = _lookup(metrics, th.metric)
        ok = v is not None and math.isfinite(v) and (v <= th.value if th.op == "<=" else v >= th.value)
        rows.append({"metric": th.metric, "value": v, "op": th.op, "threshold": th.value, "passed": bool(ok),
                     "why": th.why})
    return rows


def _fmt_value(v) -> str:
    if v is None:
        return "missing"
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return str(int(v))
    v = float(v)
    return str(v) if not math.isfinite(v) else f"{v:.4g}"  # "nan", "inf", "-inf"


def _fmt_any(v) -> str:
    numeric = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
    return _fmt_value(v) if numeric or v is None else str(v)


def format_table(rows: list[dict]) -> str:
    """A fixed-width table for the terminal: metric, value, threshold, PASS/FAIL."""
    head = ("metric", "value", "threshold", "result")
    body = [(r["metric"], _fmt_value(r["value"]), f"{r['op']} {r['threshold']:g}",
             "PASS" if r["passed"] else "FAIL") for r in rows]
    widths = [max(len(x[i]) for x in [head] + body) for i in range(4)]
    line = lambda x: "  ".join((c.ljust if i != 1 else c.rjust)(widths[i]) for i, c in enumerate(x))  # noqa: E731
    rule = "  ".join("-" * w for w in widths)
    return "\n".join(x.rstrip() for x in [line(head), rule] + [line(x) for x in body])


def flatten_metrics(metrics: dict, prefix: str = "") -> dict:
    """{"a": {"b": 1}} -> {"a.b": 1}: the dotted keys `Threshold.metric` names."""
    out = {}
    for k, v in metrics.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_metrics(v, key + "."))
        else:
            out[key] = v
    return out


# --- JSON -------------------------------------------------------------------------------------------


def to_jsonable(obj):
    """Plain JSON types: numpy scalars and arrays converted, NaN -> None (null), ±inf -> "inf" / "-inf"."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if obj is None or isinstance(obj, (bool, np.bool_)):
        return None if obj is None else bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else (None if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(obj, (str, Path)):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to metrics.json")


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


def _md_cell(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def write_report(out_dir, *, title: str, metrics: dict, checks: list[dict], panels=(), notes=()) -> dict:
    """Write out_dir/images/<panel>.png, out_dir/metrics.json and out_dir/report.md (module docstring),
    each atomically, images first and report.md last. Returns {"metrics_json": path, "report_md": path,
    "images": {name: path}}."""
    if not isinstance(title, str) or not title.strip():
        raise ValueError("title must be a non-empty string")
    if not isinstance(metrics, dict):
        raise TypeError(f"metrics must be a dict, got {type(metrics).__name__}")
    panels = list(panels)
    notes = [str(n) for n in notes]
    for p in panels:
        if not isinstance(p, (Panel, RenderPanel)):
            raise TypeError(f"panels must be Panel or RenderPanel, got {type(p).__name__}")
    names = [p.name for p in panels]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"panel names must be unique (they name the PNGs); repeated: {', '.join(dup)}")
    out = Path(out_dir)
    passed = all(c["passed"] for c in checks) if checks else None
    doc = to_jsonable({"title": title, "passed": passed, "checks": checks, "metrics": metrics, "notes": notes})
    blob = (json.dumps(doc, indent=2, allow_nan=False) + "\n").encode()  # fails before any file is written

    images = {p.name: _save_panel(p, out / "images" / f"{p.name}.png") for p in panels}
    metrics_json = write_bytes_atomic(out / "metrics.json", blob)

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
    md += [f"{k} = {_fmt_any(v)}" for k, v in flatten_metrics(metrics).items()]
    md += ["```", "", "metrics.json holds the same numbers (NaN as null, ±inf as \"inf\" / \"-inf\").", ""]
    text = re.sub(r"\n{3,}", "\n\n", "\n".join(md))  # one blank line between blocks
    report_md = write_bytes_atomic(out / "report.md", text.encode())
    return {"metrics_json": metrics_json, "report_md": report_md, "images": images}
