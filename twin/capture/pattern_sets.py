"""The lighting patterns of the capture plan (paper §5, reference §2.4 and §6.3), as 8-bit PatternSets.

learned patterns
    Signed patterns are captured as two physical frames, the positive and the negative part
    (reference §2.4: the released network consumes B(W+) - B(W-)); `signed_pairs` splits them, naming the
    frames "<name>+" and "<name>-". Until the acquisition network exists, `placeholder_learned` gives a
    seeded random signed set (uniform in [-1, 1] per LED and channel, upper LEDs only): valid patterns,
    not optimised ones.
linear lights (64)
    Each linear light is one straight line of LEDs: a full row of one upper board (a row runs across the
    board's 64 columns: a horizontal bar on a wall, a bar along y on the top). The 64 lines are shared
    out as evenly as possible over the six upper boards (11, 11, 11, 11, 10, 10 in board order); on each
    board the rows are evenly spaced among the rows it has. A rig whose board has fewer rows than its
    share (the mini rig: 6 rows per board) takes the rest of that board's share as columns, evenly spaced.
uniform
    Every upper LED at full drive: the alignment photos (reference §6.1 uses uniform-light photos).
bottom
    Every bottom LED at full drive: the transparency photo (reference §6.3, image 128).
"""
from __future__ import annotations

import numpy as np

from twin.capture.patterns import PatternSet

NUM_LINEAR_LIGHTS = 64


def signed_pairs(weights: np.ndarray, names, rig_name: str, note: str = "") -> PatternSet:
    """(K, L, 3) signed weights in [-1, 1] -> 2K non-negative frames (+, -) in plan order."""
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 3 or w.shape[2] != 3:
        raise ValueError(f"signed patterns must have shape (K, L, 3), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.abs(w).max(initial=0) > 1:
        raise ValueError("signed patterns must be finite and lie in [-1, 1]")
    frames = np.empty((2 * len(w),) + w.shape[1:])
    frames[0::2] = np.clip(w, 0, None)
    frames[1::2] = np.clip(-w, 0, None)
    pair_names = [f"{n}{s}" for n in names for s in "+-"]
    return PatternSet.from_weights(frames, pair_names, rig_name, note)


def placeholder_learned(rig, count: int = 32, seed: int = 0) -> PatternSet:
    rng = np.random.default_rng(seed)
    w = rng.uniform(-1, 1, (count, rig.num_leds, 3))
    w[:, rig.is_bottom] = 0.0
    return signed_pairs(w, [f"learned_{k:02d}" for k in range(count)], rig.name,
                        note=f"placeholder learned patterns: seeded random signed set (seed {seed}), not optimised")


def linear_light_lines(rig, count: int = NUM_LINEAR_LIGHTS) -> list[np.ndarray]:
    """The LED indices of each linear light (see module docstring for the rule)."""
    leds = rig.leds
    boards = [b for b in range(len(rig.boards)) if np.any((leds.board == b) & ~leds.is_bottom)]
    share = [count // len(boards) + (1 if i < count % len(boards) else 0) for i in range(len(boards))]
    lines = []
    for b, n in zip(boards, share):
        sel = (leds.board == b) & ~leds.is_bottom
        rows, cols = np.unique(leds.row[sel]), np.unique(leds.col[sel])
        take_rows = rows[_spread(len(rows), min(n, len(rows)))]
        lines += [np.flatnonzero(sel & (leds.row == r)) for r in take_rows]
        if n > len(rows):
            take_cols = cols[_spread(len(cols), n - len(rows))]
            lines += [np.flatnonzero(sel & (leds.col == c)) for c in take_cols]
    return lines


def _spread(n: int, k: int) -> np.ndarray:
    """k indices evenly spread over range(n) (centred bins)."""
    return np.floor((np.arange(k) + 0.5) * n / k).astype(int)


def linear_lights(rig, count: int = NUM_LINEAR_LIGHTS) -> PatternSet:
    lines = linear_light_lines(rig, count)
    w = np.zeros((len(lines), rig.num_leds))
    for k, idx in enumerate(lines):
        w[k, idx] = 1.0
    return PatternSet.from_weights(w, [f"line_{k:02d}" for k in range(len(lines))], rig.name,
                                   note="linear lights: one board row (or column) each, twin.capture.pattern_sets")


def uniform(rig) -> PatternSet:
    return PatternSet.from_weights((~rig.is_bottom)[None].astype(float), ["uniform"], rig.name)


def bottom_only(rig) -> PatternSet:
    if not rig.is_bottom.any():
        raise ValueError(f"rig {rig.name!r} has no bottom LEDs")
    return PatternSet.from_weights(rig.is_bottom[None].astype(float), ["bottom"], rig.name)


def concatenate(sets: list[PatternSet], rig_name: str, note: str = "") -> PatternSet:
    return PatternSet(np.concatenate([s.levels for s in sets]), tuple(n for s in sets for n in s.names), rig_name,
                      note)
