"""The built-in rigs (counts, mini as a subset of paper) and the unfolded-cube cross layout."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import twin
from twin import RigError
from twin.rig.cross import CROSS_SHAPE, cross_image


# --- item 2: counts -------------------------------------------------------------------------------
def test_paper_counts(paper):
    assert paper.num_leds == 16_384
    assert int(paper.is_bottom.sum()) == 4_096
    assert int((~paper.is_bottom).sum()) == 12_288
    assert len(paper.boards) == 7
    counts = np.bincount(paper.leds.board, minlength=len(paper.boards))
    assert counts.tolist() == [2048] * 6 + [4096]
    # bottom LEDs come after the upper ones
    assert np.array_equal(np.flatnonzero(paper.is_bottom), np.arange(12_288, 16_384))


def test_paper_geometry_is_consistent(paper):
    n = paper.led_normals
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    to_sample = np.asarray(paper.sample.origin) - paper.led_positions
    assert np.all(np.einsum("ij,ij->i", n, to_sample) > 0)  # all point into the cube
    # bottom LEDs lie below the sample plane and shine up
    bottom = paper.is_bottom
    assert np.all(paper.led_positions[bottom, 2] < paper.sample.origin[2])
    assert np.all(n[bottom] == [0.0, 0.0, 1.0])
    # nearest-neighbour spacing is the 10 mm pitch (never a duplicate)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(paper.led_positions).query(paper.led_positions, k=2)
    assert d[:, 1].min() > 9.0 and np.median(d[:, 1]) == pytest.approx(10.0, abs=0.1)


def test_mini_counts_and_subset(paper, mini):
    assert int((~mini.is_bottom).sum()) == 396
    assert int(mini.is_bottom.sum()) == 64
    assert mini.num_leds == 460
    # every mini LED is a paper LED: same position, normal and (board, row, col)
    key = lambda r: ((r.leds.board.astype(np.int64) << 32) | (r.leds.row.astype(np.int64) << 16)  # noqa: E731
                     | r.leds.col.astype(np.int64))
    paper_index = {k: i for i, k in enumerate(key(paper).tolist())}
    idx = np.array([paper_index[k] for k in key(mini).tolist()])
    assert len(np.unique(idx)) == mini.num_leds
    assert np.all(np.diff(idx) > 0)  # paper order is kept
    assert np.array_equal(mini.led_positions, paper.led_positions[idx])
    assert np.array_equal(mini.led_normals, paper.led_normals[idx])
    assert np.array_equal(mini.leds.cross_pixel, paper.leds.cross_pixel[idx])
    # positions as a set, independently of the (board, row, col) bookkeeping
    paper_rows = {tuple(p) for p in paper.led_positions.tolist()}
    assert all(tuple(p) in paper_rows for p in mini.led_positions.tolist())
    # per upper board 11 columns x 6 rows
    assert np.bincount(mini.leds.board, minlength=7).tolist() == [66] * 6 + [64]


def test_mini_cameras_are_paper_cameras_resized(paper, mini):
    assert list(mini.cameras) == list(paper.cameras)
    for name in paper.cameras:
        a, b = paper.cameras[name], mini.cameras[name]
        assert (b.width, b.height) == (a.width // 12, a.height // 12) == (222, 192)
        assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)


def test_builtin_rigs_are_cached_and_immutable(paper):
    assert twin.load_rig("paper") is paper
    with pytest.raises(ValueError):
        paper.leds.positions[0, 0] = 0.0
    with pytest.raises(TypeError):
        paper.cameras["new"] = paper.primary  # MappingProxyType


# --- item 5: cross layout ---------------------------------------------------------------------------
def test_paper_cross_is_a_bijection(paper):
    H, W = CROSS_SHAPE
    assert (H, W) == (128, 192)
    leds = paper.leds
    cp = leds.cross_pixel.astype(np.int64)
    L = paper.num_leds
    # inside the canvas
    assert cp[:, 0].min() >= 0 and cp[:, 0].max() < W
    assert cp[:, 1].min() >= 0 and cp[:, 1].max() < H
    # index -> pixel is injective, and its inverse recovers the index
    pixel_to_index = {tuple(p): i for i, p in enumerate(cp.tolist())}
    assert len(pixel_to_index) == L
    # index -> (board, row, col) is injective, and its inverse recovers the index
    brc = list(zip(leds.board.tolist(), leds.row.tolist(), leds.col.tolist()))
    brc_to_index = {k: i for i, k in enumerate(brc)}
    assert len(brc_to_index) == L
    for i in range(L):
        assert pixel_to_index[tuple(cp[i].tolist())] == i
        assert brc_to_index[brc[i]] == i
    # the canvas is exactly covered where LEDs exist: 6 x 2048 upper + 64 x 64 bottom pixels
    canvas = np.zeros((H, W), int)
    canvas[cp[:, 1], cp[:, 0]] += 1
    assert canvas.max() == 1 and canvas.sum() == 16_384


def test_paper_cross_regions(paper):
    cp = paper.leds.cross_pixel.astype(np.int64)
    bottom = paper.is_bottom
    # bottom LEDs fill columns 128-191, rows 32-95 completely
    assert cp[bottom, 0].min() == 128 and cp[bottom, 0].max() == 191
    assert cp[bottom, 1].min() == 32 and cp[bottom, 1].max() == 95
    assert np.all(cp[~bottom, 0] < 128)
    # top boards (faces "top") inside the central square, walls around it (reference §1.3)
    face = np.array([b.face for b in paper.boards])[paper.leds.board]
    top = face == "top"
    assert np.all((cp[top] >= 32) & (cp[top] <= 95))
    assert np.all(cp[face == "-x", 0] <= 31)
    assert np.all((cp[face == "+x", 0] >= 96) & (cp[face == "+x", 0] <= 127))
    assert np.all(cp[face == "+y", 1] <= 31)
    assert np.all(cp[face == "-y", 1] >= 96)


def test_paper_top_face_cross_follows_world_axes(paper):
    """On the top face column grows with world +x and row with world -y (a view from above)."""
    cp = paper.leds.cross_pixel.astype(float)
    face = np.array([b.face for b in paper.boards])[paper.leds.board]
    top = face == "top"
    pos = paper.led_positions[top]
    assert np.corrcoef(cp[top, 0], pos[:, 0])[0, 1] > 0.99
    assert np.corrcoef(cp[top, 1], -pos[:, 1])[0, 1] > 0.99
    bottom = paper.is_bottom
    pos = paper.led_positions[bottom]
    assert np.corrcoef(cp[bottom, 0], pos[:, 0])[0, 1] > 0.99
    assert np.corrcoef(cp[bottom, 1], -pos[:, 1])[0, 1] > 0.99


def test_cross_image_scatters_values(paper, mini):
    vals = np.arange(paper.num_leds, dtype=float)
    img = cross_image(paper, vals)
    cp = paper.leds.cross_pixel.astype(np.int64)
    assert np.array_equal(img[cp[:, 1], cp[:, 0]], vals)
    assert np.isnan(img).sum() == 128 * 192 - 16_384
    # mini: every LED keeps its own pixel, holes take a value of their own board
    mvals = np.arange(mini.num_leds, dtype=float)
    mimg = cross_image(mini, mvals)
    mcp = mini.leds.cross_pixel.astype(np.int64)
    assert np.array_equal(mimg[mcp[:, 1], mcp[:, 0]], mvals)
    assert np.isfinite(mimg).sum() == 16_384  # the same footprint as the full rig
    with pytest.raises(ValueError, match="460 LEDs"):
        cross_image(mini, np.zeros(5))


# --- in-memory validation (the rig model itself) ----------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(st.data())
def test_random_subsets_of_mini_are_valid_rigs(mini, data):
    n = mini.num_leds
    idx = data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=n, unique=True))
    idx = np.sort(np.array(idx))
    sub = replace(mini, leds=mini.leds.subset(idx))
    assert sub.num_leds == len(idx)
    assert np.array_equal(sub.led_positions, mini.led_positions[idx])
    assert sub.summary()["num_bottom_leds"] == int(mini.is_bottom[idx].sum())


def test_rig_rejects_duplicate_board_coordinates(mini):
    leds = mini.leds
    row = leds.row.copy()
    col = leds.col.copy()
    row[1], col[1] = row[0], col[0]  # LEDs 0 and 1 are on the same board
    assert leds.board[0] == leds.board[1]
    bad = replace(leds, row=row, col=col)
    with pytest.raises(RigError, match=r"same \(board, row, col\)"):
        replace(mini, leds=bad)


def test_rig_rejects_shared_cross_pixel(mini):
    cp = mini.leds.cross_pixel.copy()
    cp[1] = cp[0]
    with pytest.raises(RigError, match="share one pixel"):
        replace(mini, leds=replace(mini.leds, cross_pixel=cp))


def test_rig_rejects_cross_pixel_outside_canvas(mini):
    cp = mini.leds.cross_pixel.copy()
    cp[0] = (192, 0)
    with pytest.raises(RigError, match="outside the 192x128"):
        replace(mini, leds=replace(mini.leds, cross_pixel=cp))
