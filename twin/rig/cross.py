"""The unfolded-cube ("cross") image: LED index <-> (board, row, col) <-> pixel, as in the paper's Fig. 5
and the reference's 128 x 192 preview (reference §1.3).

The canvas is 128 rows x 192 columns. The top face occupies rows 32-95, columns 32-95, seen from above
(+x to the right, +y up). Each wall is folded out so that its high edge touches the top face. The
64 x 64 bottom face, absent from the released preview, fills the spare columns 128-191 (rows 32-95),
also seen from above.
"""
from __future__ import annotations

import numpy as np

CROSS_SHAPE = (128, 192)  # (rows, cols)

# Per face: the (col, row) pixel of board LED (row=0, col=0) and the pixel steps per board column and
# per board row, read off the released preview map (reference §1.3 table; board col = fast index across
# the board's two 32x32 tiles, board row = slow index).
FACE_LAYOUT = {
    "-x": ((0, 32), (0, 1), (1, 0)),
    "topA": ((63, 95), (0, -1), (-1, 0)),
    "topB": ((95, 95), (0, -1), (-1, 0)),
    "+x": ((127, 95), (0, -1), (-1, 0)),
    "-y": ((32, 127), (1, 0), (0, -1)),
    "+y": ((95, 0), (-1, 0), (0, 1)),
    "bottom": ((128, 32), (1, 0), (0, 1)),
}


def layout_pixels(layout: str, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """(col, row) canvas pixels of board LEDs at (row, col) for a face layout key of FACE_LAYOUT."""
    (c0, r0), (dc_col, dr_col), (dc_row, dr_row) = FACE_LAYOUT[layout]
    row, col = np.asarray(row, np.int64), np.asarray(col, np.int64)
    return np.stack([c0 + col * dc_col + row * dc_row, r0 + col * dr_col + row * dr_row], axis=-1)


def cross_image(rig, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
    """Scatter a per-LED vector (L,) or (L, C) into the canvas, (128, 192) or (128, 192, C).

    A rig with a subsampled layout (the mini rig) leaves holes between its LEDs: each hole inside a
    board's footprint takes the value of the nearest LED of the same board, so every LED shows as a
    block. Pixels outside every board stay `fill`."""
    values = np.asarray(values)
    if values.shape[0] != rig.num_leds:
        raise ValueError(f"values have {values.shape[0]} entries but rig {rig.name!r} has {rig.num_leds} LEDs")
    H, W = CROSS_SHAPE
    out = np.full((H, W) + values.shape[1:], fill, dtype=np.float64)
    cp = rig.leds.cross_pixel.astype(np.int64)
    owner = np.full((H, W), -1, np.int64)
    owner[cp[:, 1], cp[:, 0]] = np.arange(rig.num_leds)
    board_of_pixel = np.full((H, W), -1, np.int64)
    for b, board in enumerate(rig.boards):
        sel = np.flatnonzero(rig.leds.board == b)
        if sel.size == 0:
            continue
        # the board's full footprint in the canvas: the bounding box of its LEDs' grid extended to
        # the whole rows x cols grid, read from the pixels of its corner LEDs' layout
        rr, cc = np.meshgrid(np.arange(board.rows), np.arange(board.cols), indexing="ij")
        foot = _board_footprint(rig, sel, rr.ravel(), cc.ravel())
        board_of_pixel[foot[:, 1], foot[:, 0]] = b
        holes = foot[owner[foot[:, 1], foot[:, 0]] < 0]
        if len(holes):
            d = ((holes[:, None, :] - cp[sel][None, :, :]) ** 2).sum(-1)
            owner[holes[:, 1], holes[:, 0]] = sel[np.argmin(d, axis=1)]
    mask = owner >= 0
    out[mask] = values[owner[mask]]
    return out


def _board_footprint(rig, sel, rows, cols) -> np.ndarray:
    """Canvas pixels of every grid position of a board, by fitting the affine (row, col) -> pixel map
    of its LEDs (exact for the built-in and imported layouts)."""
    r = rig.leds.row[sel].astype(float)
    c = rig.leds.col[sel].astype(float)
    A = np.stack([np.ones_like(r), c, r], axis=1)
    coef, *_ = np.linalg.lstsq(A, rig.leds.cross_pixel[sel].astype(float), rcond=None)
    pix = np.rint(np.stack([np.ones(len(rows)), cols, rows], axis=1) @ coef).astype(np.int64)
    H, W = CROSS_SHAPE
    ok = (pix[:, 0] >= 0) & (pix[:, 0] < W) & (pix[:, 1] >= 0) & (pix[:, 1] < H)
    return pix[ok]
