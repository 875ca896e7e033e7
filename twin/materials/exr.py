"""OpenEXR input/output with clear errors (OpenEXR ≥ 3.3, the `OpenEXR.File` API).

    write_exr(path, {"R": a, "G": b, ...}, half=False, compression="zip", attributes=None) -> Path
    write_rgb_exr(path, rgb (H, W, 3), **kw) -> Path                  channels "R", "G", "B"
    rgb_exr_bytes(height, width) -> int                                the file size, float32, uncompressed
    read_exr(path, channels=None, shape=None) -> {name: float32 (H, W)}
    read_rgb_exr(path, shape=None) -> float32 (H, W, 3)                in R, G, B order
    read_exr_attributes(path) -> {name: value}                         custom header attributes only
    check_finite(name, array)                                          ExrError naming the first bad pixel

Conventions
    * Arrays are indexed [row, column]; row 0 is the first scanline of the file (the top of the image
      in a viewer). Channels are addressed by name only, never by position, so there is no BGR
      confusion: `read_rgb_exr(...)[..., 0]` is the channel named "R" (OpenCV's `imread` would return
      B first; the reference pipeline converts BGR → RGB after reading, reference §6.3).
    * The file stores channels sorted by name; `read_exr` returns them with R, G, B, A first (in that
      order) and the others in natural order (L_0, L_1, …, L_10, not L_0, L_1, L_10).
    * Pixels are written as FLOAT (float32) or, with half=True, HALF (float16; relative rounding error
      ≤ 2⁻¹¹ ≈ 4.9e-4, values beyond ±65504 become ±Inf, which is refused). Float32 round trips are
      bit-exact with the lossless compressions ("none", "zip" (default), "zips", "piz", "rle"); "pxr24",
      "b44", "b44a", "dwaa" and "dwab" are lossy. Reading always returns float32 (HALF widened exactly);
      UINT channels are refused.
    * Custom attributes: str, int, float (stored as a 32-bit float by OpenEXR: ~7 significant digits),
      lists of floats. Standard header names (channels, compression, dataWindow, …) cannot be used.
    * Writing is atomic (`twin.atomic.atomic_path`): a failed write leaves the old file (if any) and no
      temporary file behind.
    * The reader allows NaN/Inf (a map may legitimately carry them; callers validate with
      `check_finite`). Everything else that is wrong gives `ExrError` (a ValueError) naming the file:
      missing file, not an EXR, truncated/corrupt, missing channels, unexpected size, subsampled or
      integer channels, channels of different sizes.
"""
from __future__ import annotations

import functools
import os
import re
import tempfile
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from twin.atomic import atomic_path

EXR_MAGIC = b"\x76\x2f\x31\x01"
RGB = ("R", "G", "B")
COMPRESSIONS = ("none", "zip", "zips", "piz", "rle", "pxr24", "b44", "b44a", "dwaa", "dwab")
# Header keys that OpenEXR itself owns (or that the writer sets); not allowed as custom attributes.
STANDARD_ATTRIBUTES = frozenset({
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
    "screenWindowCenter", "screenWindowWidth", "type", "tiles", "name", "version", "chunkCount",
    "maxSamplesPerPixel", "view", "multiView",
})
_HALF_MAX = 65504.0
_NAME_RE = re.compile(r"^[^\x00-\x1f]{1,255}$")


class ExrError(ValueError):
    """An EXR file cannot be written or read as asked. The message names the file and the problem."""


def _openexr():
    import OpenEXR  # imported lazily: a heavy-ish extension module

    return OpenEXR


def _compression(name: str):
    OpenEXR = _openexr()
    key = str(name).lower()
    if key not in COMPRESSIONS:
        raise ExrError(f"unknown EXR compression {name!r}; expected one of {', '.join(COMPRESSIONS)}")
    return getattr(OpenEXR, "NO_COMPRESSION" if key == "none" else f"{key.upper()}_COMPRESSION")


def _natural_key(name: str):
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def _channel_order(names: Iterable[str]) -> list[str]:
    names = list(names)
    first = [c for c in ("R", "G", "B", "A") if c in names]
    return first + sorted((n for n in names if n not in first), key=_natural_key)


def _first_bad(a: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])


def check_finite(name: str, array) -> None:
    """Raise ExrError if `array` has a NaN or Inf; `name` (e.g. "maps/pd_texture.exr channel R") is put
    in the message together with the first bad pixel (row, column) and its value."""
    a = np.asarray(array)
    if a.dtype.kind not in "fc":
        return
    if not np.all(np.isfinite(a)):
        idx = _first_bad(a)
        n_bad = int(np.count_nonzero(~np.isfinite(a)))
        where = f"pixel (row {idx[0]}, col {idx[1]})" if len(idx) == 2 else f"index {idx}"
        if len(idx) > 2:
            where = f"pixel (row {idx[0]}, col {idx[1]}), channel index {idx[2:]}"
        raise ExrError(f"{name}: non-finite value {a[idx]} at {where} ({n_bad} non-finite values in all)")


# --- writing -----------------------------------------------------------------------------------------


def _prepare_channels(path: Path, channels: Mapping[str, np.ndarray], half: bool) -> dict[str, np.ndarray]:
    if not isinstance(channels, Mapping) or len(channels) == 0:
        raise ExrError(f"{path}: expected a non-empty dict of channel name -> (H, W) array")
    out: dict[str, np.ndarray] = {}
    shape = None
    for name, arr in channels.items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ExrError(f"{path}: invalid channel name {name!r} (a non-empty string without control characters)")
        a = np.asarray(arr)
        if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
            raise ExrError(f"{path}: channel {name!r} must be a 2-D (H, W) array, got shape {a.shape}")
        if a.dtype.kind not in "fiub":
            raise ExrError(f"{path}: channel {name!r} has dtype {a.dtype}; expected a real numeric array")
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise ExrError(f"{path}: channel {name!r} has shape {a.shape}, but the other channels are {shape}")
        if half:
            a64 = a.astype(np.float64)
            finite = np.isfinite(a64)
            if np.any(finite & (np.abs(a64) > _HALF_MAX)):
                idx = tuple(int(i) for i in np.argwhere(finite & (np.abs(a64) > _HALF_MAX))[0])
                raise ExrError(f"{path}: channel {name!r} value {a64[idx]:g} at (row {idx[0]}, col {idx[1]}) "
                               f"exceeds the half-float range ±{_HALF_MAX:g}; write with half=False")
            a = a.astype(np.float16)
        else:
            a = a.astype(np.float32)
        out[name] = np.ascontiguousarray(a)  # a copy: OpenEXR.File replaces dict values by Channel objects
    return out


def _check_attributes(path: Path, attributes: Mapping | None) -> dict:
    if not attributes:
        return {}
    out = {}
    for k, v in attributes.items():
        if not isinstance(k, str) or not _NAME_RE.match(k):
            raise ExrError(f"{path}: invalid attribute name {k!r}")
        if k in STANDARD_ATTRIBUTES:
            raise ExrError(f"{path}: attribute name {k!r} is reserved by OpenEXR")
        if isinstance(v, (bool, np.bool_)):
            v = int(v)
        elif isinstance(v, np.integer):
            v = int(v)
        elif isinstance(v, np.floating):
            v = float(v)
        if isinstance(v, (list, tuple)):
            try:
                v = [float(x) for x in v]
            except (TypeError, ValueError):
                raise ExrError(f"{path}: attribute {k!r}: a list must hold numbers only, got {v!r}") from None
        elif not isinstance(v, (str, int, float)):
            raise ExrError(f"{path}: attribute {k!r} has unsupported type {type(v).__name__} "
                           "(allowed: str, int, float, list of floats)")
        out[k] = v
    return out


def write_exr(path: str | os.PathLike, channels: Mapping[str, np.ndarray], *, half: bool = False,
              compression: str = "zip", attributes: Mapping | None = None, durable: bool = True) -> Path:
    """Write named (H, W) channels to a single-part scanline EXR, atomically. Returns the path.

    half=False stores FLOAT (float32), half=True stores HALF (float16). NaN/Inf are written as given.
    `attributes`: extra header entries (str, int, float, list of floats). `durable`: fsync before the rename
    (twin.atomic)."""
    path = Path(path)
    chans = _prepare_channels(path, channels, half)
    attrs = _check_attributes(path, attributes)
    OpenEXR = _openexr()
    header = {"compression": _compression(compression), "type": OpenEXR.scanlineimage, **attrs}
    try:
        with atomic_path(path, durable=durable) as tmp:
            with OpenEXR.File(header, chans) as f:
                f.write(str(tmp))
    except ExrError:
        raise
    except (RuntimeError, ValueError, TypeError, OSError) as e:
        raise ExrError(f"{path}: could not write EXR ({type(e).__name__}: {e})") from e
    return path


def write_rgb_exr(path: str | os.PathLike, rgb, **kw) -> Path:
    """Write an (H, W, 3) array as channels R, G, B (rgb[..., 0] is R). Keywords as `write_exr`."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ExrError(f"{path}: expected an (H, W, 3) RGB array, got shape {a.shape}")
    return write_exr(path, {c: a[..., k] for k, c in enumerate(RGB)}, **kw)


def rgb_exr_bytes(height: int, width: int) -> int:
    """The bytes of the file `write_rgb_exr` writes for a (height, width) float32 image with compression="none" and
    no attributes: the header, then one scanline a chunk, each an 8-byte entry of the line offset table and an
    8-byte chunk header (row, byte count) before its three float32 channels."""
    return _rgb_exr_header_bytes() + height * (8 + 8 + len(RGB) * 4 * width)


@functools.cache
def _rgb_exr_header_bytes() -> int:
    """The header's bytes, measured on a one-pixel file: the OpenEXR library chooses the attributes it writes."""
    with tempfile.TemporaryDirectory() as d:
        path = write_rgb_exr(Path(d) / "one.exr", np.zeros((1, 1, 3), np.float32), compression="none", durable=False)
        return path.stat().st_size - (8 + 8 + len(RGB) * 4)


# --- reading -----------------------------------------------------------------------------------------


def _open(path: Path):
    if not path.exists():
        raise ExrError(f"{path}: no such file")
    if not path.is_file():
        raise ExrError(f"{path}: not a file")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as e:
        raise ExrError(f"{path}: cannot read ({e.strerror or e})") from None
    if magic != EXR_MAGIC:
        raise ExrError(f"{path}: not an OpenEXR file (first bytes {magic!r}, expected {EXR_MAGIC!r})")
    OpenEXR = _openexr()
    try:
        return OpenEXR.File(str(path), separate_channels=True)
    except (RuntimeError, ValueError, TypeError, OSError) as e:
        raise ExrError(f"{path}: corrupt or truncated OpenEXR file ({type(e).__name__}: {e})") from None


def _header(f, path: Path) -> dict:
    try:
        return f.header()
    except (RuntimeError, ValueError, TypeError) as e:
        raise ExrError(f"{path}: corrupt or truncated OpenEXR file ({type(e).__name__}: {e})") from None


def read_exr(path: str | os.PathLike, channels: Iterable[str] | None = None,
             shape: tuple[int, int] | None = None) -> dict[str, np.ndarray]:
    """Read an EXR's channels as float32 (H, W) arrays (first part of a multi-part file).

    channels: if given, these names must be present and only they are returned, in the given order.
    shape: if given, the expected (H, W). NaN/Inf are returned as stored (see `check_finite`)."""
    path = Path(path)
    with _open(path) as f:
        return _read(f, path, channels, shape)


def _read(f, path: Path, channels, shape) -> dict[str, np.ndarray]:
    hdr = _header(f, path)
    try:
        raw = f.channels()
    except (RuntimeError, ValueError, TypeError) as e:
        raise ExrError(f"{path}: corrupt or truncated OpenEXR file ({type(e).__name__}: {e})") from None
    if not raw:
        raise ExrError(f"{path}: the file has no channels")
    for ch in hdr.get("channels", []):
        xs, ys = getattr(ch, "xSampling", 1), getattr(ch, "ySampling", 1)
        if (xs, ys) != (1, 1):
            raise ExrError(f"{path}: channel {ch.name!r} is subsampled ({xs}x{ys}); only full-resolution "
                           "channels are supported")
    names = _channel_order(raw)
    if channels is not None:
        wanted = list(channels)
        missing = [c for c in wanted if c not in raw]
        if missing:
            raise ExrError(f"{path}: missing channel(s) {', '.join(missing)}; the file has {', '.join(names)}")
        names = wanted
    out: dict[str, np.ndarray] = {}
    first_shape = None
    for name in names:
        try:
            px = raw[name].pixels
        except (RuntimeError, ValueError, TypeError, AttributeError) as e:
            raise ExrError(f"{path}: channel {name!r} cannot be read ({e})") from None
        px = np.asarray(px)
        if px.dtype.kind != "f":
            raise ExrError(f"{path}: channel {name!r} has pixel type {px.dtype} (UINT); expected HALF or FLOAT")
        if px.ndim != 2:
            raise ExrError(f"{path}: channel {name!r} has shape {px.shape}; expected (H, W)")
        if first_shape is None:
            first_shape = px.shape
        elif px.shape != first_shape:
            raise ExrError(f"{path}: channel {name!r} has shape {px.shape}, others {first_shape}")
        out[name] = np.array(px, dtype=np.float32)  # own, writeable copy
    if shape is not None and tuple(first_shape) != tuple(shape):
        raise ExrError(f"{path}: image is {first_shape[0]} x {first_shape[1]} (H x W); expected "
                       f"{shape[0]} x {shape[1]}")
    return out


def read_rgb_exr(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read channels R, G, B into one float32 (H, W, 3) array, [..., 0] = R. Other channels are ignored."""
    ch = read_exr(path, channels=RGB, shape=shape)
    return np.stack([ch[c] for c in RGB], axis=-1)


def read_exr_attributes(path: str | os.PathLike) -> dict:
    """The custom (non-standard) header attributes of an EXR file."""
    path = Path(path)
    with _open(path) as f:  # copy inside: closing the file empties the header dict
        return {k: v for k, v in _header(f, path).items() if k not in STANDARD_ATTRIBUTES}
