"""Lighting-pattern files: per-LED 8-bit RGB drive levels with metadata.

The device drives each LED with an 8-bit level per channel (paper §5); a pattern set is K such frames.
File format (`.npz`, opened with allow_pickle=False; written atomically):

    format   "hemicube-patterns"     version  1
    levels   uint8 (K, L, 3)         drive level of LED l in frame k, channel c (0..255)
    names    str (K,)                one name per frame, e.g. "learned_03+", "line_12"
    rig      str                     name of the rig the set was made for
    note     str                     free text (how it was made)

A frame's relative weight is level / 255. Signed patterns (reference §2.4) are stored as two frames,
the positive and negative parts, named "<name>+" and "<name>-".
"""
from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.atomic import write_bytes_atomic

FORMAT_NAME = "hemicube-patterns"
FORMAT_VERSION = 1


class PatternError(ValueError):
    pass


@dataclass(frozen=True)
class PatternSet:
    levels: np.ndarray  # (K, L, 3) uint8
    names: tuple[str, ...]
    rig: str
    note: str = ""

    def __post_init__(self):
        lv = np.asarray(self.levels)
        if lv.ndim != 3 or lv.shape[2] != 3:
            raise PatternError(f"pattern levels must have shape (K, L, 3), got {lv.shape}")
        if lv.dtype != np.uint8:
            raise PatternError(f"pattern levels must be uint8 drive levels, got {lv.dtype}; use "
                               "PatternSet.from_weights to quantise weights in [0, 1]")
        names = tuple(str(n) for n in self.names)
        if len(names) != lv.shape[0]:
            raise PatternError(f"{len(names)} pattern names for {lv.shape[0]} frames")
        if any("\0" in s for s in (*names, str(self.rig), str(self.note))):
            raise PatternError("pattern names, rig and note must not contain NUL characters")
        if len(set(names)) != len(names):
            raise PatternError("pattern names must be unique")
        lv = lv.copy()
        lv.flags.writeable = False
        object.__setattr__(self, "levels", lv)
        object.__setattr__(self, "names", names)

    @property
    def num_patterns(self) -> int:
        return self.levels.shape[0]

    @property
    def num_leds(self) -> int:
        return self.levels.shape[1]

    @property
    def weights(self) -> np.ndarray:
        """(K, L, 3) float32 relative drive in [0, 1]."""
        return self.levels.astype(np.float32) / 255.0

    @classmethod
    def from_weights(cls, weights, names, rig: str, note: str = "") -> "PatternSet":
        """Quantise weights in [0, 1] to 8-bit levels (round to nearest): the device's LED drive."""
        w = np.asarray(weights, dtype=np.float64)
        if w.ndim == 2:
            w = np.repeat(w[..., None], 3, axis=2)
        if not np.all(np.isfinite(w)):
            raise PatternError("pattern weights contain NaN or Inf")
        if w.size and (w.min() < 0 or w.max() > 1):
            raise PatternError(f"pattern weights must lie in [0, 1] (LEDs cannot emit negative light; "
                               f"store signed patterns as +/- pairs), got [{w.min():g}, {w.max():g}]")
        return cls(np.rint(w * 255).astype(np.uint8), tuple(names), rig, note)

    def check_rig(self, rig) -> None:
        if self.num_leds != rig.num_leds:
            raise PatternError(f"pattern set has {self.num_leds} LEDs per frame but rig {rig.name!r} has "
                               f"{rig.num_leds}")

    def to_bytes(self) -> bytes:
        buf = io.BytesIO()
        np.savez_compressed(buf, format=np.str_(FORMAT_NAME), version=np.int32(FORMAT_VERSION),
                            levels=self.levels, names=np.array(self.names, dtype=str),
                            rig=np.str_(self.rig), note=np.str_(self.note))
        return buf.getvalue()


def save_patterns(patterns: PatternSet, path: str | os.PathLike) -> Path:
    return write_bytes_atomic(path, patterns.to_bytes())


def load_patterns(path: str | os.PathLike) -> PatternSet:
    path = Path(path)
    if not path.is_file():
        raise PatternError(f"{path}: no such pattern file")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise PatternError(f"{path}: not a {FORMAT_NAME} file (a single .npy array, not an npz archive)")
        with z:
            if "format" not in z.files or str(z["format"]) != FORMAT_NAME:
                raise PatternError(f"{path}: not a {FORMAT_NAME} file")
            if "version" not in z.files:
                raise PatternError(f"{path}: missing the format version")
            version = z["version"]  # a file's own: any shape or type (int() of an array is a TypeError)
            if version.shape != () or version.dtype.kind not in "iu" or int(version) != FORMAT_VERSION:
                raise PatternError(f"{path}: unknown pattern format version {version.tolist()!r}; this twin reads "
                                   f"version {FORMAT_VERSION}")
            missing = [k for k in ("levels", "names", "rig") if k not in z.files]
            if missing:
                raise PatternError(f"{path}: missing {missing}")
            return PatternSet(z["levels"], tuple(z["names"].tolist()), str(z["rig"]),
                              str(z["note"]) if "note" in z.files else "")
    except PatternError as e:
        raise PatternError(str(e) if str(e).startswith(str(path)) else f"{path}: {e}") from None
    except (ValueError, OSError, EOFError) as e:
        raise PatternError(f"{path}: not a readable pattern file ({e})") from None
