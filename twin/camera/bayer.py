"""Colour filter arrays, GenICam PFNC raw formats and bilinear demosaicing (numpy only).

CFA layouts
    A layout is named by the two colours of the top-left 2x2 cell's first row, as GenICam does:
    "RG" means (row 0, col 0) = R, (0, 1) = G, (1, 0) = G, (1, 1) = B; "GR", "GB" and "BG" likewise.
    Pixel (row, col) takes the colour of cell position (row % 2, col % 2). Channel indices: R=0, G=1, B=2.

Raw formats (GenICam Pixel Format Naming Convention, PFNC 2.x)
    ``BayerRG12``: one pixel per 16-bit little-endian container, the value in the low 12 bits
    (LSB-aligned), the upper 4 bits zero. ``to_bayer_rg12`` / ``from_bayer_rg12``.

    ``BayerRG12p``: 12-bit packed, LSB first. Two consecutive pixels p0, p1 (in row-major order) share
    three bytes::

        byte0 = p0 & 0xFF
        byte1 = (p0 >> 8) | ((p1 & 0x0F) << 4)
        byte2 = p1 >> 4

    ``pack_bayer_rg12p`` / ``unpack_bayer_rg12p``. The width must be even so that no pair straddles
    two rows. (This is NOT the older GigE Vision ``BayerRG12Packed`` layout, which stores the high
    bits first; that one is not implemented.)

    The byte layouts do not depend on the CFA layout: the same functions write BayerGR12, BayerGB12p,
    ... data; ``pfnc_name`` gives the right name for a sensor's layout.

Demosaicing
    ``demosaic`` is bilinear interpolation (the classic 3x3 kernels), exact for constant and linear
    images away from the one-pixel border; the border mirrors the mosaic about the edge pixel (numpy's
    "reflect" padding), which keeps every mirrored pixel's CFA colour and so is exact for constants.
"""
from __future__ import annotations

import numpy as np

CHANNELS = ("R", "G", "B")
# colour index at (row % 2, col % 2)
CFA_LAYOUTS: dict[str, tuple[tuple[int, int], tuple[int, int]]] = {
    "RG": ((0, 1), (1, 2)),
    "GR": ((1, 0), (2, 1)),
    "GB": ((1, 2), (0, 1)),
    "BG": ((2, 1), (1, 0)),
}
MAX_12BIT = 0xFFF


def cfa_table(pattern: str) -> np.ndarray:
    """(2, 2) int array: channel index at (row % 2, col % 2)."""
    try:
        return np.array(CFA_LAYOUTS[pattern], dtype=np.int64)
    except (KeyError, TypeError):
        raise ValueError(f"unknown Bayer layout {pattern!r}; expected one of {sorted(CFA_LAYOUTS)}") from None


def cfa_index(pattern: str, height: int, width: int) -> np.ndarray:
    """(H, W) int array: the channel (0=R, 1=G, 2=B) of every pixel of a `pattern` mosaic."""
    t = cfa_table(pattern)
    r = np.arange(height) % 2
    c = np.arange(width) % 2
    return t[r[:, None], c[None, :]]


def mosaic(rgb: np.ndarray, pattern: str = "RG") -> np.ndarray:
    """(H, W, 3) -> (H, W): each pixel keeps the channel of its colour filter."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"mosaic needs an (H, W, 3) image, got shape {rgb.shape}")
    idx = cfa_index(pattern, rgb.shape[0], rgb.shape[1])
    return np.take_along_axis(rgb, idx[..., None], axis=2)[..., 0]


def pfnc_name(pattern: str = "RG", bits: int = 12, packed: bool = False) -> str:
    """The PFNC pixel-format name, e.g. ("RG", 12, True) -> "BayerRG12p"."""
    cfa_table(pattern)
    if bits not in (8, 10, 12, 16):
        raise ValueError(f"bits must be 8, 10, 12 or 16, got {bits}")
    return f"Bayer{pattern}{bits}{'p' if packed else ''}"


# --- raw formats ----------------------------------------------------------------------------------
def _check_raw12(raw) -> np.ndarray:
    if not isinstance(raw, np.ndarray):
        raise TypeError(f"raw frame must be a numpy array, got {type(raw).__name__}")
    if raw.dtype != np.uint16:
        raise TypeError(f"raw frame must have dtype uint16, got {raw.dtype}")
    if raw.ndim != 2 or raw.shape[0] < 1 or raw.shape[1] < 1:
        raise ValueError(f"raw frame must be a non-empty 2-D (H, W) array, got shape {raw.shape}")
    if raw.size and int(raw.max()) > MAX_12BIT:
        bad = np.argwhere(raw > MAX_12BIT)[0]
        raise ValueError(f"raw value {int(raw[tuple(bad)])} at (row, col) = {tuple(int(b) for b in bad)} "
                         f"does not fit in 12 bits (max {MAX_12BIT})")
    return raw


def _check_dims(height, width) -> tuple[int, int]:
    for name, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"{name} must be a positive integer, got {v!r}")
    return int(height), int(width)


def _as_bytes(data) -> memoryview:
    if isinstance(data, np.ndarray):
        data = data.tobytes()
    try:
        return memoryview(data).cast("B")
    except TypeError:
        raise TypeError(f"raw data must be bytes-like, got {type(data).__name__}") from None


def to_bayer_rg12(raw: np.ndarray) -> bytes:
    """BayerRG12: each pixel in a 16-bit little-endian container, value LSB-aligned (upper 4 bits 0)."""
    raw = _check_raw12(raw)
    return np.ascontiguousarray(raw, dtype="<u2").tobytes()


def from_bayer_rg12(data, height: int, width: int) -> np.ndarray:
    """Inverse of `to_bayer_rg12`: bytes -> uint16 (H, W). Rejects a wrong byte count and any
    container whose upper 4 bits are set."""
    height, width = _check_dims(height, width)
    buf = _as_bytes(data)
    need = 2 * height * width
    if buf.nbytes != need:
        raise ValueError(f"BayerRG12 {height}x{width} needs {need} bytes, got {buf.nbytes}")
    out = np.frombuffer(buf, dtype="<u2").reshape(height, width).astype(np.uint16)
    if int(out.max()) > MAX_12BIT:
        i = int(np.argmax(out > MAX_12BIT))
        raise ValueError(f"BayerRG12 container {i} holds 0x{int(out.flat[i]):04X}: upper 4 bits must be zero")
    return out


def pack_bayer_rg12p(raw: np.ndarray) -> bytes:
    """BayerRG12p (PFNC 12-bit packed, LSB first): pixels p0, p1 -> 3 bytes
    (p0 & 0xFF, (p0 >> 8) | ((p1 & 0xF) << 4), p1 >> 4). The width must be even."""
    raw = _check_raw12(raw)
    if raw.shape[1] % 2:
        raise ValueError(f"BayerRG12p needs an even width (pixel pairs must not straddle rows), got {raw.shape[1]}")
    p = np.ascontiguousarray(raw).reshape(-1, 2)
    p0, p1 = p[:, 0], p[:, 1]
    out = np.empty((p.shape[0], 3), dtype=np.uint8)
    out[:, 0] = p0 & 0xFF
    out[:, 1] = (p0 >> 8) | ((p1 & 0x0F) << 4)
    out[:, 2] = p1 >> 4
    return out.tobytes()


def unpack_bayer_rg12p(data, height: int, width: int) -> np.ndarray:
    """Inverse of `pack_bayer_rg12p`: bytes -> uint16 (H, W)."""
    height, width = _check_dims(height, width)
    if width % 2:
        raise ValueError(f"BayerRG12p needs an even width, got {width}")
    buf = _as_bytes(data)
    need = 3 * height * width // 2
    if buf.nbytes != need:
        raise ValueError(f"BayerRG12p {height}x{width} needs {need} bytes, got {buf.nbytes}")
    b = np.frombuffer(buf, dtype=np.uint8).reshape(-1, 3).astype(np.uint16)
    out = np.empty((b.shape[0], 2), dtype=np.uint16)
    out[:, 0] = b[:, 0] | ((b[:, 1] & 0x0F) << 8)
    out[:, 1] = (b[:, 1] >> 4) | (b[:, 2] << 4)
    return out.reshape(height, width)


# --- demosaicing ----------------------------------------------------------------------------------
# Bilinear kernels applied to each colour plane with the other sites zeroed: green has 4-neighbours,
# red and blue have 2 (same row or column) or 4 (diagonal) neighbours of their colour.
_K_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], dtype=np.float64) / 4
_K_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], dtype=np.float64) / 4


def demosaic(raw: np.ndarray, pattern: str = "RG") -> np.ndarray:
    """Bilinear demosaicing of an (H, W) mosaic to (H, W, 3).

    Float input keeps its float type, anything else becomes float64. Known sites keep their value;
    missing ones are the mean of the nearest same-colour sites (2 or 4). The border mirrors the mosaic
    about the edge pixel, which preserves the CFA, so constants are exact everywhere and linear ramps
    everywhere but the outermost pixel ring. H and W must be at least 2."""
    x = np.asarray(raw)
    if x.ndim != 2:
        raise ValueError(f"demosaic needs a 2-D (H, W) mosaic, got shape {x.shape}")
    H, W = x.shape
    if H < 2 or W < 2:
        raise ValueError(f"demosaic needs H, W >= 2, got {H}x{W}")
    dtype = x.dtype if np.issubdtype(x.dtype, np.floating) else np.float64
    idx = np.pad(cfa_index(pattern, H, W), 1, mode="reflect")
    xp = np.pad(x.astype(np.float64), 1, mode="reflect")
    out = np.empty((H, W, 3), dtype=dtype)
    for c in range(3):
        plane = np.where(idx == c, xp, 0.0)
        k = _K_G if c == 1 else _K_RB
        acc = np.zeros((H, W))
        for di in range(3):
            for dj in range(3):
                if k[di, dj]:
                    acc += k[di, dj] * plane[di:di + H, dj:dj + W]
        out[..., c] = acc
    return out
