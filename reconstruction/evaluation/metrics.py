"""Validation metrics (docs/accuracy.md): map errors against the ground truth, image scores against the
held-out photo, and thresholds. Pure functions of arrays: no pipeline logic here (the report folder that shows
them is reconstruction.evaluation.report).

    truth_g = resample_maps(truth, recon.size_mm, recon.resolution)   # truth onto the reconstruction grid
    inside = truth_coverage(truth, recon.size_mm, recon.resolution)   # texel centres on the true sample
    m = map_errors(truth_g, recon, mask=inside)                      # dict, see map_errors
    s = image_scores(photo, render, mask=on_sample)                  # {"ssim", "ssim_all", "psnr_db", ...}
    rows = check({"maps": m, "render": s}, [Threshold("maps.normal_deg.median", "<=", 1.0, "goal")])
    print(format_table(rows))

Metric conventions (every statistic is a {"median", "mean", "p90", "count"} dict over the texels used):
* normal_deg: angle between n̂ and n, atan2(|n̂ × n|, n̂ · n) (exact near 0°, where arccos is not).
* tangent_deg: the tangent is an axis (t and −t give the same BRDF), so the angle is taken modulo 180°,
  in [0°, 90°]. Both maps are first put in the export convention αx ≥ αy (reference §5,
  `canonical_anisotropy`), so t is the axis of the larger roughness on both sides. Only texels whose TRUE
  αx/αy ≥ `anisotropy_ratio` (1.5, docs/accuracy.md) count: on near-isotropic texels the tangent is undefined
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
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.materials.samples import ALPHA_RANGE, RHO_D_RANGE, RHO_S_RANGE, SVBRDFMaps, canonical_anisotropy, grid_coordinates

__all__ = [
    "ANISOTROPY_RATIO", "RHO_FLOOR", "resample_maps", "truth_coverage", "map_errors", "image_scores",
    "Threshold", "check", "format_table", "flatten_metrics", "to_jsonable",
]

ANISOTROPY_RATIO = 1.5  # the tangent's goal holds "where αx/αy ≥ 1.5" (docs/accuracy.md)
# 5 % of each map's full range (ρd ∈ [0, 1]; ρs ∈ [0, 10], the reference's ps_range, §7.1). Ours.
RHO_FLOOR = (0.05, 0.5)
STAT_PERCENTILE = 90.0
_SNAP = 1e-9  # texel coordinates this close to an integer are that integer (exact identity resampling)


# --- resampling the truth onto the reconstruction grid ---------------------------------------------


def _grid_coords(truth: SVBRDFMaps, size_mm: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous truth (row, col) coordinates (each (resolution,), float64) of the texel centres of a
    square grid of `resolution` texels over `size_mm`, centred on the same origin (twin.materials.samples
    conventions: texel (i, j) centre at −size/2 + (j + 0.5)·size/res; truth texel centre (i, j) = (i, j))."""
    if isinstance(size_mm, bool) or not isinstance(size_mm, (int, float, np.integer, np.floating)) \
            or not math.isfinite(size_mm) or size_mm <= 0:
        raise ValueError(f"size_mm must be a positive finite number of millimetres, got {size_mm!r}")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    x, _ = grid_coordinates(size_mm, (resolution, resolution))
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
    `resample_maps`): two twin.materials.samples.SVBRDFMaps of H x W texels over the same size_mm. `mask` (H, W)
    bool selects the texels (default: all). `anisotropy_ratio`: the tangent is scored where the true
    alpha_x >= this times alpha_y. `rho_floor`: an albedo's relative error is |ρ - ρ_true| / max(ρ_true, floor),
    one floor for both albedos or a (ρd, ρs) pair. Returns (module docstring for the definitions; angles in
    degrees, `_pct` in %, log_alpha_x and log_alpha_y as |ln(α / α_true)|, transparency an absolute difference):

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
    # a dotted key to a count of what the metric is taken over (e.g. "maps.tangent_deg.count"): where it is 0
    # the condition does not apply (a sample with no anisotropic texel has no tangent to get wrong)
    applies_if: str | None = None

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
    absent (value None) or not finite (NaN, ±inf) fails, unless the threshold's `applies_if` count is 0
    (then the row passes and says why)."""
    rows = []
    for th in thresholds:
        if not isinstance(th, Threshold):
            raise TypeError(f"expected Threshold, got {type(th).__name__}")
        v = _lookup(metrics, th.metric)
        if th.applies_if is not None and _lookup(metrics, th.applies_if) == 0:
            rows.append({"metric": th.metric, "value": v, "op": th.op, "threshold": th.value, "passed": True,
                         "why": f"not applicable: {th.applies_if} is 0"})
            continue
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
