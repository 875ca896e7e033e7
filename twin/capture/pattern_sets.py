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

Fixed signed families, baselines for a pattern designer (docs/designer.md), each captured as (+, -) pairs through
`signed_pairs` over the upper LEDs (bottom LEDs 0, the three channels equal), frames "<family>_{k:02d}+/-":
hadamard
    Rows 1..count of the Sylvester Hadamard matrix of order n = the next power of two >= the number of
    upper LEDs, truncated to the upper LEDs in rig order: the +/-1 Hadamard code (Harwit & Sloane,
    "Hadamard Transform Optics", 1979), each row's +1 LEDs in the + frame and its -1 LEDs in the - frame.
    Row 0 (all ones) is skipped: it is the uniform light. Entry (i, j) is (-1)^popcount(i AND j), so the
    rows are made without the whole n x n matrix (16,384^2 for the paper rig).
gradients
    The four spherical-gradient patterns of Ma et al. 2007 ("Rapid acquisition of specular and diffuse
    normal maps from polarized spherical gradient illumination", EGSR): per upper LED the components
    d_x, d_y, d_z of its unit direction from the sample origin (rig world frame) and a constant 1 (whose
    - frame is dark).
lines
    `count` linear lights by `linear_light_lines`' rule (one board row or column each, the plan's own kind
    of light), each a + frame whose - frame is dark.
olat
    One LED at a time: `count` upper LEDs evenly spread over the upper LEDs in rig order (`_spread`), or
    over those of a given mask.
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


def signed_weights(patterns: PatternSet) -> np.ndarray:
    """The inverse of `signed_pairs` in grey: (K, L) float64 weights (+ frame minus - frame, the mean over the
    channels) of a set of 2K frames in (+, -) order."""
    if patterns.num_patterns % 2:
        raise ValueError(f"signed patterns come as (+, -) pairs: an even number of frames, got {patterns.num_patterns}")
    grey = patterns.weights.astype(np.float64).mean(axis=2)
    return grey[0::2] - grey[1::2]


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


def _check_count(count, most: int) -> int:
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 1 <= count <= most:
        raise ValueError(f"count must be an integer in [1, {most}], got {count!r}")
    return int(count)


def _upper_signed(rig, values: np.ndarray, family: str, note: str) -> PatternSet:
    """(K, L_upper) signed values on the upper LEDs -> the (+, -) PatternSet, bottom LEDs 0, channels equal."""
    w = np.zeros((len(values), rig.num_leds, 3))
    w[:, ~rig.is_bottom] = values[..., None]
    return signed_pairs(w, [f"{family}_{k:02d}" for k in range(len(values))], rig.name, note)


def hadamard(rig, count: int) -> PatternSet:
    """Rows 1..count of the Sylvester Hadamard matrix (module docstring): the +/-1 Hadamard code captured as
    (+, -) pairs, levels 255 in the frame of each LED's sign."""
    n_up = int((~rig.is_bottom).sum())
    order = 1 << max(n_up - 1, 0).bit_length()  # next power of two >= n_up
    count = _check_count(count, order - 1)
    bits = np.arange(1, count + 1)[:, None] & np.arange(n_up)[None, :]
    parity = np.zeros(bits.shape, dtype=np.int64)
    while bits.any():  # parity of popcount(i AND j), one bit at a time
        parity ^= bits & 1
        bits >>= 1
    rows = 1.0 - 2.0 * parity
    return _upper_signed(rig, rows, "hadamard",
                         f"hadamard: rows 1..{count} of the Sylvester Hadamard matrix of order {order}, truncated "
                         f"to the {n_up} upper LEDs, as (+, -) pairs")


def gradients(rig) -> PatternSet:
    """The 4 spherical-gradient patterns of Ma et al. 2007 (module docstring): x, y, z, constant."""
    d = rig.leds.positions[~rig.is_bottom] - np.asarray(rig.sample.origin)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    values = np.concatenate([d.T, np.ones((1, len(d)))])
    return _upper_signed(rig, values, "gradients",
                         "spherical gradients (Ma et al. 2007): LED direction x, y, z from the sample origin, "
                         "then constant")


def lines(rig, count: int) -> PatternSet:
    """`count` linear lights (module docstring) as (+, -) pairs with dark - frames."""
    count = _check_count(count, NUM_LINEAR_LIGHTS)
    values = linear_lights(rig, count).weights[..., 0][:, ~rig.is_bottom]
    return _upper_signed(rig, values, "lines", f"linear lights: {count} board rows or columns, - frames dark")


def olat(rig, count: int, on=None) -> PatternSet:
    """`count` one-LED-at-a-time patterns, the LEDs evenly spread over the upper LEDs in rig order (module
    docstring); `on` ((L,) bool over all rig LEDs) restricts the choice to the upper LEDs it marks."""
    up = ~rig.is_bottom
    if on is not None:
        on = np.asarray(on)
        if on.dtype != bool or on.shape != (rig.num_leds,):
            raise ValueError(f"on must be a ({rig.num_leds},) bool mask over the rig's LEDs, got {on.dtype} "
                             f"{on.shape}")
    pool = np.flatnonzero(up if on is None else up & on)  # candidate LEDs
    count = _check_count(count, len(pool))
    values = np.zeros((count, rig.num_leds))
    values[np.arange(count), pool[_spread(len(pool), count)]] = 1.0
    return _upper_signed(rig, values[:, up], "olat",
                         f"one LED at a time: {count} of {len(pool)} upper LEDs, evenly spread")


def bottom_only(rig) -> PatternSet:
    if not rig.is_bottom.any():
        raise ValueError(f"rig {rig.name!r} has no bottom LEDs")
    return PatternSet.from_weights(rig.is_bottom[None].astype(float), ["bottom"], rig.name)


def concatenate(sets: list[PatternSet], rig_name: str, note: str = "") -> PatternSet:
    return PatternSet(np.concatenate([s.levels for s in sets]), tuple(n for s in sets for n in s.names), rig_name,
                      note)
