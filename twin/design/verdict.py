"""Whether one capture design beats another: a verdict that says "real" only when the numbers allow it.

Two designs are compared by their networks' test losses (paper Eq. 3, one network a training seed). The difference
is called **real** only when all of these hold, and **not resolved** otherwise, with every reason that failed:

- each design has at least MIN_SEEDS networks (seeds), so that a spread can be measured;
- Welch's t-test (Welch 1947: two means, unequal variances) on the two sets of losses gives p < P_REAL;
- every network uses its measurements: its test loss is at most 1 / BLIND_RATIO of the loss of the best predictor
  that ignores them (the per-LED mean: `blind_eq3`), so a comparison of two networks that learned nothing of the
  photos is never read as a comparison of the designs;
- every network has finished learning: its held-out loss changed by less than FLAT_CHANGE (relative) over the last
  FLAT_TAIL of its training steps, so the order is not that of two runs caught at different points of their curves.

The thresholds are the goals a study states before it runs (the conventional 5 % level; the 2x and 1 % bars of the
designer's acceptance), never values fitted to a result. Rows are the dicts `hemicube design evaluate` writes to
designs.json (heldout_eq3_per_seed, blind_eq3, heldout_curve_per_seed).
"""
from __future__ import annotations

import math

import numpy as np

P_REAL = 0.05  # two-sided significance level of Welch's test
MIN_SEEDS = 3  # networks (training seeds) a design needs for a verdict
BLIND_RATIO = 2.0  # a network's test loss must be at most the blind predictor's / BLIND_RATIO
FLAT_TAIL = 0.2  # the last share of the training steps over which the held-out curve must be flat
FLAT_CHANGE = 0.01  # ... changing by less than this, relative
REAL, NOT_RESOLVED = "real", "not resolved"


def welch_t_test(a, b) -> tuple[float, float, float]:
    """Welch's unequal-variances t-test (Welch 1947, Biometrika 34): (t, degrees of freedom by the
    Welch-Satterthwaite equation, two-sided p) for the means of samples `a` and `b` (each >= 2 values). Equal
    samples with no spread give t = 0 and p = 1."""
    from scipy import stats

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.size < 2 or b.size < 2:
        raise ValueError(f"Welch's test needs at least 2 values a sample, got {a.size} and {b.size}")
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    diff = a.mean() - b.mean()
    if va + vb == 0:
        return (0.0, float(a.size + b.size - 2), 1.0) if diff == 0 else (math.copysign(math.inf, diff), math.nan, 0.0)
    t = diff / math.sqrt(va + vb)
    dof = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
    return float(t), float(dof), float(2 * stats.t.sf(abs(t), dof))


def tail_change(curve) -> float | None:
    """Relative change of a held-out curve ([(step, loss), ...], in step order) over its last FLAT_TAIL of steps:
    |loss at the end - loss at the last evaluation at or before (1 - FLAT_TAIL) x the steps| / the latter. None when
    no evaluation lies at or before that point (the curve is too coarse to tell)."""
    pts = sorted((int(s), float(v)) for s, v in curve)
    if len(pts) < 2:
        return None
    end_step, end = pts[-1]
    start = [v for s, v in pts if s <= (1 - FLAT_TAIL) * end_step]
    if not start or start[-1] == 0:
        return None
    return abs(end - start[-1]) / abs(start[-1])


def tail_change_max(curves) -> float | None:
    """The largest tail_change of several seeds' curves; None when there are none or one is too coarse to tell."""
    changes = [tail_change(c) for c in curves]
    return None if not changes or any(c is None for c in changes) else max(changes)


def network_bar(row: dict) -> list[str]:
    """Why a design's networks cannot be compared (empty when they can): too few seeds, a network within
    BLIND_RATIO of the blind predictor, a held-out curve not flat over its last FLAT_TAIL of steps."""
    name, losses, blind = row["design"], list(row["heldout_eq3_per_seed"]), float(row["blind_eq3"])
    why = []
    if len(losses) < MIN_SEEDS:
        why.append(f"{name} has {len(losses)} seed(s), a verdict needs {MIN_SEEDS}")
    worst = max(losses) if losses else math.nan
    if not worst * BLIND_RATIO <= blind:
        why.append(f"{name}'s worst network scores {worst:.4g}, not {BLIND_RATIO:g}x below the measurement-blind "
                   f"predictor's {blind:.4g} ({blind / worst:.2f}x): it has not learned to use its measurements")
    curves = row.get("heldout_curve_per_seed") or []
    change = tail_change_max(curves)
    if len(curves) < len(losses) or change is None:
        why.append(f"{name}'s held-out curves are too coarse to tell whether training had flattened")
    elif change >= FLAT_CHANGE:
        why.append(f"{name}'s held-out loss still moved {100 * change:.1f} % over the last "
                   f"{100 * FLAT_TAIL:.0f} % of its steps (a flat curve moves < {100 * FLAT_CHANGE:g} %): train longer")
    return why


def compare(a: dict, b: dict) -> dict:
    """The verdict on designs `a` and `b` (rows of designs.json): which has the lower mean test loss, the ratio of the
    means (worse / better), Welch's p, "real" or "not resolved", every reason it is not resolved, and `text`, the
    sentence a report prints."""
    la, lb = np.asarray(a["heldout_eq3_per_seed"], float), np.asarray(b["heldout_eq3_per_seed"], float)
    better, worse = (a, b) if la.mean() <= lb.mean() else (b, a)
    ratio = float(np.mean(worse["heldout_eq3_per_seed"]) / np.mean(better["heldout_eq3_per_seed"]))
    why = network_bar(better) + network_bar(worse)
    p = welch_t_test(la, lb)[2] if la.size >= 2 and lb.size >= 2 else math.nan
    if not p < P_REAL:
        why.append(f"Welch's t-test gives p = {p:.3g} (a real difference needs p < {P_REAL:g})")
    verdict = NOT_RESOLVED if why else REAL
    head = (f"{better['design']} vs {worse['design']}: test loss {np.mean(better['heldout_eq3_per_seed']):.4g} vs "
            f"{np.mean(worse['heldout_eq3_per_seed']):.4g} (x{ratio:.3g}, Welch p = {p:.3g}): {verdict}")
    return {"better": better["design"], "worse": worse["design"], "ratio": ratio, "p": p, "verdict": verdict,
            "why": why, "text": head + ("" if not why else " — " + "; ".join(why))}


def compare_all(rows: list[dict]) -> list[dict]:
    """`compare` on every pair of designs, in the rows' order."""
    return [compare(rows[i], rows[j]) for i in range(len(rows)) for j in range(i + 1, len(rows))]
