"""A capture design as a file (docs/designer.md): what a pattern designer varies, in one TOML file.

    format = "hemicube-design"
    version = 1
    name = "hadamard-32"           # the design's name in tables and plots (default: the file's stem)
    rig = "mini"                   # a built-in rig or a rig folder (relative paths: from the design file);
                                   # `hemicube design evaluate --rig` overrides it for every design

    [leds]                         # optional layout change: LEDs that are never driven
    off_boards = ["top A"]         # boards removed (names as in the rig)
    stride = 2                     # LED pitch x 2: keep every 2nd row and column of each board
    off = [12, 40]                 # single LEDs off (rig LED indices)

    [cameras.secondary]            # optional: a camera moved, re-aimed at the sample's origin
    centre_mm = [0.0, -250.0, 250.0]

    [patterns]
    family = "learned"             # learned (trained with the network) | hadamard | gradients | lines | olat
                                   # | file (twin.capture.pattern_sets)
    count = 32                     # K signed patterns = 2K photos (+, -) per view; gradients: 4
    file = "patterns.npz"          # family "file": a twin pattern file (twin.capture.patterns) of 2K frames

    [training]                     # the network that scores the design (reconstruction quality)
    distribution = "uniform"       # what it trains on: "uniform" GGX ranges, "suite" (the material suite's
                                   # nine categories: database-like) or "maps:DIR" (folders of OpenSVBRDF maps)
    test_distribution = "suite"    # what it is scored on (default: the training distribution); "suite"
                                   # tests on compositions held back from training (other seeds)
    steps = 300
    batch = 256
    seeds = [0, 1, 2]
    dropout = 0.0                  # the network's dropout (paper §6: 0.3; 0 as the shipped networks, since
                                   # the mini rig's narrow decoder collapses with 0.3: docs/performance.md)

    [capture]
    baud = 2000000                 # the LED controller's link (twin.capture.backends.led_host)
    latency_s = 0.001              # its turnaround per command (docs/led-protocol.md section 7)
    frame_overhead_s = 0.02        # per raw frame beyond its exposure: readout and trigger
    budget_s = 1800                # the capture budget per sample: a design over it is flagged

`load_design(path)` checks every field on load and names the one that is wrong in a one-line DesignError:
an unknown key, an LED index not on the rig, a pattern file of the wrong size or with a level outside the
controller's 8 bits, a camera that no longer sees the whole sample (the rig's own check). Units: millimetres and seconds, the rig's
frames (twin.rig.units).
"""
from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FORMAT_NAME = "hemicube-design"
FORMAT_VERSION = 1
FAMILIES = ("learned", "hadamard", "gradients", "lines", "olat", "file")
DISTRIBUTIONS = ("uniform", "suite", "maps:DIR")
# the material suite's compositions (seeds) a "suite" distribution trains on, and those it is tested on: held
# back from training, as the suite's validation keeps its own held-back seeds (docs/accuracy.md)
SUITE_TRAIN_SEEDS = (0, 1, 2)
SUITE_TEST_SEEDS = (9101, 9102)


class DesignError(ValueError):
    """A design file that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class Training:
    distribution: str = "uniform"
    test_distribution: str = "uniform"
    steps: int = 300
    batch: int = 256
    seeds: tuple[int, ...] = (0, 1, 2)
    dropout: float = 0.0

    @staticmethod
    def materials(distribution: str, test: bool = False) -> str:
        """The distribution as reconstruction.network.data.SamplingConfig.materials: '' (uniform ranges), 'suite:SEEDS'
        (training or held-back test compositions), 'maps:DIR'."""
        if distribution == "uniform":
            return ""
        if distribution == "suite":
            return "suite:" + ",".join(str(s) for s in (SUITE_TEST_SEEDS if test else SUITE_TRAIN_SEEDS))
        return distribution


@dataclass(frozen=True)
class CaptureCosts:
    baud: int = 2_000_000
    latency_s: float = 0.001
    frame_overhead_s: float = 0.02
    budget_s: float = 1800.0


@dataclass(frozen=True)
class Design:
    name: str
    rig: object                      # twin.rig.model.Rig, with the design's camera moves applied
    led_on: np.ndarray               # (L,) bool: the LEDs the design drives (upper LEDs only)
    family: str
    count: int                       # K signed patterns
    pattern_file: Path | None
    training: Training = field(default_factory=Training)
    capture: CaptureCosts = field(default_factory=CaptureCosts)
    source: Path | None = None

    def signed_patterns(self) -> np.ndarray:
        """(K, L) signed weights in [-1, 1] over all rig LEDs, 0 on the LEDs the design leaves off; None for
        the family "learned" (the network learns them)."""
        from twin.capture import pattern_sets
        from twin.capture.patterns import load_patterns

        if self.family == "learned":
            return None
        make = {"file": lambda: load_patterns(self.pattern_file),
                "hadamard": lambda: pattern_sets.hadamard(self.rig, self.count),
                "gradients": lambda: pattern_sets.gradients(self.rig),
                "lines": lambda: pattern_sets.lines(self.rig, self.count),
                "olat": lambda: pattern_sets.olat(self.rig, self.count, on=self.led_on)}[self.family]
        return np.where(self.led_on[None], pattern_sets.signed_weights(make()), 0.0)


def _err(src, key, msg) -> DesignError:
    return DesignError(f"{src}: {key}: {msg}")


def _table(d, key, src, allowed) -> dict:
    t = d.get(key, {})
    if not isinstance(t, dict):
        raise _err(src, key, f"must be a table, got {type(t).__name__}")
    unknown = sorted(set(t) - set(allowed))
    if unknown:
        raise _err(src, f"{key}.{unknown[0]}", f"unknown key (known: {', '.join(allowed)})")
    return t


def _int(v, key, src, lo=0) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise _err(src, key, f"must be an integer >= {lo}, got {v!r}")
    return v


def _num(v, key, src, positive=True) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise _err(src, key, f"must be a {'positive ' if positive else ''}finite number, got {v!r}")
    return float(v)


def _led_mask(rig, t, src) -> np.ndarray:
    leds = rig.leds
    on = ~np.asarray(rig.is_bottom)
    names = [b.name for b in rig.boards]
    boards = t.get("off_boards", [])
    if not isinstance(boards, list):
        raise _err(src, "leds.off_boards", "must be a list of board names")
    for b in boards:
        if b not in names:
            raise _err(src, "leds.off_boards", f"rig {rig.name!r} has no board {b!r} (it has {names})")
        on &= leds.board != names.index(b)
    stride = _int(t.get("stride", 1), "leds.stride", src, lo=1)
    if stride > 1:
        # every stride-th of the rows and of the columns that carry LEDs on each board, from its first
        keep = np.zeros_like(on)
        for b in range(len(rig.boards)):
            sel = leds.board == b
            if sel.any():
                rows, cols = np.unique(leds.row[sel])[::stride], np.unique(leds.col[sel])[::stride]
                keep |= sel & np.isin(leds.row, rows) & np.isin(leds.col, cols)
        on &= keep
    off = t.get("off", [])
    if not isinstance(off, list):
        raise _err(src, "leds.off", "must be a list of LED indices")
    for i in off:
        if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < rig.num_leds:
            raise _err(src, "leds.off", f"LED index {i!r} is not on rig {rig.name!r} (0..{rig.num_leds - 1})")
        if rig.is_bottom[i]:
            raise _err(src, "leds.off", f"LED {i} is a bottom LED; the patterns drive the upper LEDs only")
        on[i] = False
    if not on.any():
        raise _err(src, "leds", "the design leaves no upper LED on")
    return on


def _moved_cameras(rig, t, src):
    """The rig with each named camera moved; the rig's own check says whether it still sees the whole sample."""
    from twin.rig.camera import Camera
    from twin.rig.model import RigError

    cams = dict(rig.cameras)
    for name, spec in t.items():
        key = f"cameras.{name}"
        if name not in cams:
            raise _err(src, key, f"rig {rig.name!r} has no camera {name!r} (it has {list(cams)})")
        if not isinstance(spec, dict) or set(spec) - {"centre_mm"}:
            raise _err(src, key, "must be a table with the one key centre_mm")
        c = spec.get("centre_mm")
        if not (isinstance(c, list) and len(c) == 3):
            raise _err(src, f"{key}.centre_mm", f"must be three numbers (mm), got {c!r}")
        centre = np.array([_num(v, f"{key}.centre_mm", src, positive=False) for v in c])
        old = cams[name]
        # re-aimed at the sample's origin; image columns keep their direction as far as the new view allows
        up = old.R[0] if abs(float(old.R[0] @ (np.asarray(rig.sample.origin) - centre))) < 0.99 * np.linalg.norm(
            np.asarray(rig.sample.origin) - centre) else old.R[1]
        cams[name] = Camera.look_at(name, centre, rig.sample.origin, up, old.K, old.width, old.height, old.dist,
                                    sensor=old.sensor, assumed=old.assumed, note=f"moved by a design to {c}")
        try:
            rig = dataclasses.replace(rig, cameras=cams)
        except RigError as e:
            raise _err(src, key, str(e)) from None
    return rig


def _pattern_file(path: Path, rig, count, src) -> None:
    """The file's levels must be the controller's 8 bits and its frames 2 * count (+, -) pairs for this rig."""
    from twin.capture.patterns import PatternError, load_patterns

    if not path.is_file():
        raise _err(src, "patterns.file", f"no such file: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            raw = np.asarray(z["levels"]) if "levels" in z.files else None
    except (OSError, ValueError, KeyError) as e:
        raise _err(src, "patterns.file", f"{path} is not a pattern file ({e})") from None
    if raw is not None and raw.dtype.kind in "iuf" and raw.size and (raw.min() < 0 or raw.max() > 255):
        bad = np.argwhere((raw < 0) | (raw > 255))[0]
        raise _err(src, "patterns.file", f"level {raw[tuple(bad)]} at frame {bad[0]}, LED {bad[1]} is outside "
                   "the controller's 8 bits (0-255)")
    try:
        p = load_patterns(path)
        p.check_rig(rig)
    except PatternError as e:
        raise _err(src, "patterns.file", str(e)) from None
    if p.num_patterns != 2 * count:
        raise _err(src, "patterns.file", f"{p.num_patterns} frames, the design's count {count} needs {2 * count} "
                   "(+, -) frames")
    if p.levels[:, np.asarray(rig.is_bottom)].any():
        raise _err(src, "patterns.file", "drives bottom LEDs; learned patterns light the upper LEDs only")


def _distribution(v, key, src) -> str:
    """'uniform', 'suite' or 'maps:DIR' with DIR made absolute from the design file's folder."""
    from twin.materials.samples import SAMPLE_TOML

    if v in ("uniform", "suite"):
        return v
    if isinstance(v, str) and v.startswith("maps:") and len(v) > 5:
        d = (src.parent / v[5:]).resolve()
        if not ((d / SAMPLE_TOML).is_file() or any((p / SAMPLE_TOML).is_file() for p in d.glob("*"))):
            raise _err(src, key, f"{d} holds no folder of OpenSVBRDF maps ({SAMPLE_TOML})")
        return f"maps:{d}"
    raise _err(src, key, f"must be one of {DISTRIBUTIONS}, got {v!r}")


def load_design(path: str | os.PathLike, rig=None) -> Design:
    """Read and check a design file (module docstring). `rig` (a twin.rig.model.Rig, a built-in rig's name or a rig
    folder, relative to the working directory) overrides the file's `rig`: the file's layout changes, camera moves
    and patterns then apply to that rig, and the design keeps its name (`hemicube design evaluate --rig`)."""
    import twin
    from twin.rig.model import Rig, RigError

    src = Path(path)
    try:
        d = tomllib.loads(src.read_text())
    except FileNotFoundError:
        raise DesignError(f"{src}: no such design file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise DesignError(f"{src}: not a readable TOML design ({e})") from None
    top = {"format", "version", "name", "rig", "leds", "cameras", "patterns", "training", "capture"}
    unknown = sorted(set(d) - top)
    if unknown:
        raise _err(src, unknown[0], f"unknown key (known: {', '.join(sorted(top))})")
    if d.get("format") != FORMAT_NAME:
        raise _err(src, "format", f"must be {FORMAT_NAME!r}, got {d.get('format')!r}")
    if d.get("version") != FORMAT_VERSION:
        raise _err(src, "version", f"this reader knows version {FORMAT_VERSION}, got {d.get('version')!r}")
    name = d.get("name", src.stem)
    if not isinstance(name, str) or not name.strip():
        raise _err(src, "name", f"must be a non-empty string, got {name!r}")
    rig_name = d.get("rig")
    if not isinstance(rig_name, str):
        raise _err(src, "rig", f"must be a built-in rig name or a rig folder, got {rig_name!r}")
    if rig is None:  # the file's own rig
        candidate = src.parent / rig_name
        try:
            rig = twin.load_rig(candidate if candidate.is_dir() else rig_name)
        except (RigError, ValueError, OSError) as e:
            raise _err(src, "rig", str(e)) from None
    elif not isinstance(rig, Rig):
        try:
            rig = twin.load_rig(rig)
        except (RigError, ValueError, OSError) as e:
            raise DesignError(f"--rig: {e}") from None
    led_on = _led_mask(rig, _table(d, "leds", src, ("off_boards", "stride", "off")), src)
    cams = d.get("cameras", {})
    if not isinstance(cams, dict):
        raise _err(src, "cameras", "must be a table of camera tables")
    rig = _moved_cameras(rig, cams, src)
    pt = _table(d, "patterns", src, ("family", "count", "file"))
    family = pt.get("family", "learned")
    if family not in FAMILIES:
        raise _err(src, "patterns.family", f"must be one of {FAMILIES}, got {family!r}")
    count = 4 if family == "gradients" else _int(pt.get("count", 32), "patterns.count", src, lo=1)
    if family == "gradients" and "count" in pt and pt["count"] != 4:
        raise _err(src, "patterns.count", f"the gradients family has 4 patterns, got {pt['count']!r}")
    upper_on = int(led_on.sum())
    if family in ("olat", "hadamard") and count > upper_on:
        raise _err(src, "patterns.count", f"{count} {family} patterns need {count} LEDs on, the design has {upper_on}")
    pfile = None
    if family == "file":
        if "file" not in pt:
            raise _err(src, "patterns.file", "family 'file' needs a pattern file")
        pfile = src.parent / str(pt["file"])
        _pattern_file(pfile, rig, count, src)
    elif "file" in pt:
        raise _err(src, "patterns.file", f"only the family 'file' reads a file (family is {family!r})")
    tt = _table(d, "training", src, ("distribution", "test_distribution", "steps", "batch", "seeds", "dropout"))
    dist = _distribution(tt.get("distribution", "uniform"), "training.distribution", src)
    test = _distribution(tt.get("test_distribution", tt.get("distribution", "uniform")), "training.test_distribution",
                         src)
    seeds = tt.get("seeds", [0, 1, 2])
    if not (isinstance(seeds, list) and seeds and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                                                      for s in seeds) and len(set(seeds)) == len(seeds)):
        raise _err(src, "training.seeds", f"must be a list of distinct non-negative integers, got {seeds!r}")
    dropout = _num(tt.get("dropout", 0.0), "training.dropout", src, positive=False)
    if not 0 <= dropout < 1:
        raise _err(src, "training.dropout", f"must lie in [0, 1), got {dropout!r}")
    training = Training(dist, test, _int(tt.get("steps", 300), "training.steps", src, lo=1),
                        _int(tt.get("batch", 256), "training.batch", src, lo=1), tuple(seeds), dropout)
    ct = _table(d, "capture", src, ("baud", "latency_s", "frame_overhead_s", "budget_s"))
    costs = CaptureCosts(_int(ct.get("baud", 2_000_000), "capture.baud", src, lo=1),
                         _num(ct.get("latency_s", 0.001), "capture.latency_s", src, positive=False),
                         _num(ct.get("frame_overhead_s", 0.02), "capture.frame_overhead_s", src, positive=False),
                         _num(ct.get("budget_s", 1800.0), "capture.budget_s", src))
    design = Design(name, rig, led_on, family, count, pfile, training, costs, src)
    if family != "learned":  # a fixed family: each of its patterns must still light an LED of the layout
        try:
            w = design.signed_patterns()
        except ValueError as e:
            raise _err(src, "patterns.count", str(e)) from None
        dark = np.flatnonzero(~(w != 0).any(axis=1))
        if dark.size:
            raise _err(src, "patterns", f"{family} pattern {dark[0]} lights no LED once the design's LEDs are off")
    return design
