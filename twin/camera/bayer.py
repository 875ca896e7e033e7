"""Colour filter arrays, GenICam PFNC raw formats and demosaicing (numpy only).

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

    ``pack_bayer_rg12p`` / ``unpack_bayer_rg12p``; a frame's size, ``bayer_rg12p_bytes``. The width must be
    even so that no pair straddles two rows. (This is NOT the older GigE Vision ``BayerRG12Packed`` layout,
    which stores the high bits first; that one is not implemented.)

    The byte layouts do not depend on the CFA layout: the same functions write BayerGR12, BayerGB12p,
    ... data; ``pfnc_name`` gives the right name for a sensor's layout.

Demosaicing
    ``demosaic(raw, pattern, method=...)`` dispatches to one function per published method (``DEMOSAICS``):
    "bilinear" (the default; the classic 3x3 kernels), exact for constant and linear images away from the
    one-pixel border, and "malvar2004" (``malvar2004``: Malvar, He & Cutler's 5x5 gradient-corrected
    kernels), exact for them away from the two-pixel border. Both mirror the mosaic about the edge pixel
    (numpy's "reflect" padding), which keeps every mirrored pixel's CFA colour and so is exact for constants.
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


def bayer_rg12p_bytes(height: int, width: int) -> int:
    """The bytes of one (height, width) frame in BayerRG12p: 3 a pixel pair."""
    return 3 * height * width // 2


def unpack_bayer_rg12p(data, height: int, width: int) -> np.ndarray:
    """Inverse of `pack_bayer_rg12p`: bytes -> uint16 (H, W)."""
    height, width = _check_dims(height, width)
    if width % 2:
        raise ValueError(f"BayerRG12p needs an even width, got {width}")
    buf = _as_bytes(data)
    need = bayer_rg12p_bytes(height, width)
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


def _mosaic_input(raw) -> tuple[np.ndarray, np.dtype]:
    """The checks every demosaicing method shares: the mosaic as an array and the output dtype (float
    input keeps its float type, anything else becomes float64)."""
    x = np.asarray(raw)
    if x.ndim != 2:
        raise ValueError(f"demosaic needs a 2-D (H, W) mosaic, got shape {x.shape}")
    H, W = x.shape
    if H < 2 or W < 2:
        raise ValueError(f"demosaic needs H, W >= 2, got {H}x{W}")
    dtype = x.dtype if np.issubdtype(x.dtype, np.floating) else np.dtype(np.float64)
    return x, dtype


def _bilinear(raw: np.ndarray, pattern: str = "RG") -> np.ndarray:
    """Bilinear demosaicing of an (H, W) mosaic to (H, W, 3).

    Known sites keep their value; missing ones are the mean of the nearest same-colour sites (2 or 4).
    The border mirrors the mosaic about the edge pixel, which preserves the CFA, so constants are exact
    everywhere and linear ramps everywhere but the outermost pixel ring."""
    x, dtype = _mosaic_input(raw)
    H, W = x.shape
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


# Malvar, He & Cutler (2004), Fig. 2, in eighths; the centre is the site being filled. Each kernel is a
# bilinear estimate of the missing colour plus a gain times the site's own colour's Laplacian; the gains
# (1/2 for G, 5/8 for R/B at G, 3/4 for R/B at B/R) are the paper's least-squares (Wiener) optima on the
# Kodak set, rounded to small multiples of powers of 2.
_MHC_G_AT_RB = np.array([[0, 0, -1, 0, 0],
                         [0, 0, 2, 0, 0],
                         [-1, 2, 4, 2, -1],
                         [0, 0, 2, 0, 0],
                         [0, 0, -1, 0, 0]], dtype=np.float64)
# at a G site whose wanted colour is its left/right neighbour (e.g. R in an R row); transposed when that
# colour is above/below (R in a B row, where R sits in the site's column)
_MHC_AT_G_ROW = np.array([[0, 0, 0.5, 0, 0],
                          [0, -1, 0, -1, 0],
                          [-1, 4, 5, 4, -1],
                          [0, -1, 0, -1, 0],
                          [0, 0, 0.5, 0, 0]], dtype=np.float64)
_MHC_AT_G_COL = _MHC_AT_G_ROW.T.copy()
# R at a B site and B at an R site: the wanted colour is on the diagonals
_MHC_RB_AT_BR = np.array([[0, 0, -1.5, 0, 0],
                          [0, 2, 0, 2, 0],
                          [-1.5, 0, 6, 0, -1.5],
                          [0, 2, 0, 2, 0],
                          [0, 0, -1.5, 0, 0]], dtype=np.float64)


def _taps_by_weight(kernel: np.ndarray) -> list[tuple[float, list[tuple[int, int]]]]:
    """A 5x5 kernel as (weight, [(drow, dcol), ...]) groups, so that equal-weight taps are summed before
    one multiply."""
    groups: dict[float, list[tuple[int, int]]] = {}
    for i, j in zip(*np.nonzero(kernel)):
        groups.setdefault(float(kernel[i, j]), []).append((int(i) - 2, int(j) - 2))
    return sorted(groups.items())


_MHC_TAPS = {name: _taps_by_weight(k) for name, k in
             (("g", _MHC_G_AT_RB), ("row", _MHC_AT_G_ROW), ("col", _MHC_AT_G_COL), ("diag", _MHC_RB_AT_BR))}


def malvar2004(raw: np.ndarray, pattern: str = "RG") -> np.ndarray:
    """Malvar-He-Cutler demosaicing of an (H, W) mosaic to (H, W, 3).

    H. S. Malvar, L.-W. He and R. Cutler, "High-quality linear interpolation for demosaicing of
    Bayer-patterned color images", Proc. IEEE ICASSP 2004, vol. 3, pp. 485-488: the 5x5 gradient-corrected
    linear kernels of its Fig. 2.

    Why: bilinear interpolation averages a neighbour's light across an edge into the missing colours (the
    colour fringes at sharp edges); correcting each bilinear estimate by the Laplacian of the colour
    actually measured at the site removes most of that spill, because across an edge the colours mostly
    move together. The price: the correction adds the measured colour's noise (scaled up) to red and blue
    in particular, and where the colours do not move together (a saturated coloured edge) it paints false
    colour instead of removing it.

    Float input keeps its float type, anything else becomes float64; known sites keep their value. The
    border mirrors the mosaic about the edge pixel as the bilinear method does, which preserves the CFA, so
    constants are exact everywhere and linear ramps everywhere but the outer two pixel rings. H and W must
    be at least 2."""
    x, dtype = _mosaic_input(raw)
    H, W = x.shape
    t = cfa_table(pattern)
    xp = np.pad(x.astype(np.float64), 2, mode="reflect")
    # Each of the four CFA phases (row % 2, col % 2) has one colour and one kernel per missing colour, so
    # the work runs per phase on half-resolution grids: no site evaluates a kernel whose result would be
    # thrown away. The padded mosaic is split into its four phase planes once, so that every tap is a
    # contiguous slice of one plane (strided taps of the full mosaic ran about twice as slow at 24 MP).
    planes = [[np.ascontiguousarray(xp[p::2, q::2]) for q in (0, 1)] for p in (0, 1)]
    out = np.empty((H, W, 3), dtype=dtype)
    for a in (0, 1):
        h = (H - a + 1) // 2
        for b in (0, 1):
            w = (W - b + 1) // 2

            def tap(di: int, dj: int) -> np.ndarray:
                p, q = (a + di) % 2, (b + dj) % 2
                r0, c0 = (2 + a + di - p) // 2, (2 + b + dj - q) // 2
                return planes[p][q][r0:r0 + h, c0:c0 + w]

            def apply(kernel: str) -> np.ndarray:
                acc = np.zeros((h, w))
                s = np.empty((h, w))
                for weight, offsets in _MHC_TAPS[kernel]:
                    np.copyto(s, tap(*offsets[0]))
                    for o in offsets[1:]:
                        s += tap(*o)
                    s *= weight
                    acc += s
                acc *= 0.125
                return acc

            c = int(t[a, b])
            out[a::2, b::2, c] = tap(0, 0)
            if c == 1:
                # the colour of the left/right neighbours fills from the row kernel, the other from the column one
                row_colour = int(t[a, 1 - b])
                out[a::2, b::2, row_colour] = apply("row")
                out[a::2, b::2, 2 - row_colour] = apply("col")
            else:
                out[a::2, b::2, 1] = apply("g")
                out[a::2, b::2, 2 - c] = apply("diag")
    return out


DEMOSAICS = {"bilinear": _bilinear, "malvar2004": malvar2004}


def demosaic(raw: np.ndarray, pattern: str = "RG", method: str = "bilinear") -> np.ndarray:
    """Demosaicing of an (H, W) mosaic to (H, W, 3) by `method`, one of ``DEMOSAICS``: "bilinear" (the
    default; the mean of the nearest same-colour sites) or "malvar2004" (`malvar2004`).

    Float input keeps its float type, anything else becomes float64. Known sites keep their value. The
    border mirrors the mosaic about the edge pixel, which preserves the CFA, so constants are exact
    everywhere and linear ramps everywhere but the outermost pixel ring (bilinear) or two rings
    (malvar2004). H and W must be at least 2."""
    try:
        f = DEMOSAICS[method]
    except (KeyError, TypeError):
        raise ValueError(f"unknown demosaicing method {method!r}; expected one of {sorted(DEMOSAICS)}") from None
    return f(raw, pattern)
