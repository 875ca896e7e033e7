"""twin.view.cross_plot: per-LED vectors on the unfolded cube, and pattern pictures.
(`paper` and `mini` are the session fixtures of conftest.py.)"""
from __future__ import annotations

import numpy as np
import pytest
from matplotlib import colormaps
from PIL import Image

from twin.rig.cross import CROSS_SHAPE
from twin.view.cross_plot import (BACKGROUND, BAR_PX, GRID_SCALE, MARGIN_PX, SCALE, TITLE_PX, cross_rgb, face_labels,
                                  save_cross_image, save_pattern_image)
from twin.capture.patterns import PatternSet, save_patterns


def test_scalar_values_land_on_their_cross_pixels(paper):
    L = paper.num_leds
    img = cross_rgb(paper, np.arange(L, dtype=float))
    assert img.shape == (128, 192, 3) and img.dtype == np.float64
    assert img.min() >= 0 and img.max() <= 1
    col, row = paper.leds.cross_pixel[:, 0], paper.leds.cross_pixel[:, 1]
    expected = colormaps["inferno"](np.arange(L) / (L - 1))[:, :3]
    assert np.allclose(img[row, col], expected)
    # the ends of the scale, literally: LED 0 is inferno's black, the last LED inferno's pale yellow
    assert np.allclose(img[row[0], col[0]], [0.001462, 0.000466, 0.013866], atol=1e-6)
    assert np.allclose(img[row[-1], col[-1]], [0.988362, 0.998364, 0.644924], atol=1e-6)
    # 16,384 LEDs fill 16,384 of the 24,576 canvas pixels; the rest is the dark background
    outside = np.ones(CROSS_SHAPE, bool)
    outside[row, col] = False
    assert outside.sum() == 128 * 192 - 16384
    assert np.all(img[outside] == BACKGROUND)


def test_rgb_values_are_kept_or_normalised(paper):
    L = paper.num_leds
    rgb = np.zeros((L, 3))
    rgb[:, 1] = 0.5
    rgb[7] = (1.0, 0.0, 0.25)
    col, row = paper.leds.cross_pixel[7]
    img = cross_rgb(paper, rgb)
    assert np.allclose(img[row, col], (1.0, 0.0, 0.25))  # within [0, 1]: as is
    c2, r2 = paper.leds.cross_pixel[8]
    assert np.allclose(img[r2, c2], (0.0, 0.5, 0.0))
    img = cross_rgb(paper, rgb * 40.0)  # radiometric values: normalised by their maximum
    assert np.allclose(img[row, col], (1.0, 0.0, 0.25)) and np.allclose(img[r2, c2], (0.0, 0.5, 0.0))
    with pytest.raises(ValueError, match="shape"):
        cross_rgb(paper, np.zeros((L, 2)))


def test_mini_rig_fills_every_board_footprint(paper, mini):
    """Each of the mini rig's 460 LEDs fills a block: its boards cover exactly the paper rig's pixels."""
    board_value = mini.leds.board.astype(float) + 1.0  # 1..7, so no board is black
    img = cross_rgb(mini, board_value)
    palette = colormaps["inferno"](np.arange(1, len(mini.boards) + 1) / len(mini.boards))[:, :3]
    col, row = paper.leds.cross_pixel[:, 0], paper.leds.cross_pixel[:, 1]
    # every pixel of a paper LED (the full footprint of every board) has the colour of its mini board
    assert np.allclose(img[row, col], palette[paper.leds.board])
    outside = np.ones(CROSS_SHAPE, bool)
    outside[row, col] = False
    assert np.all(img[outside] == BACKGROUND)
    # and each mini LED sits on its own pixel inside its block
    mc = mini.leds.cross_pixel
    assert np.allclose(img[mc[:, 1], mc[:, 0]], palette[mini.leds.board])


def _gradient_patterns(rig, k=3):
    d = rig.led_positions - np.asarray(rig.sample.origin)
    elev = np.clip(d[:, 2] / np.linalg.norm(d, axis=1), 0, 1)
    w = np.stack([elev ** (i + 1) for i in range(k)])
    return PatternSet.from_weights(w, names=[f"elev^{i + 1}" for i in range(k)], rig=rig.name)


def test_save_pattern_image_sizes(tmp_path, mini):
    ps = _gradient_patterns(mini, 3)
    H, W = CROSS_SHAPE
    one = save_pattern_image(ps, mini, tmp_path / "one.png", index=1)
    assert one == tmp_path / "one.png"
    img = np.asarray(Image.open(one).convert("RGB"))
    assert img.shape == (H * SCALE + TITLE_PX + 2 * MARGIN_PX, W * SCALE + 2 * MARGIN_PX + BAR_PX, 3) == (552, 874, 3)
    # nearest-neighbour upscaling: the block of a top LED is uniformly that pattern's colour (the one farthest from
    # the face's label, which is drawn over the LEDs at the face's centre)
    top = np.flatnonzero(mini.leds.board == 1)
    lx, ly = next((x, y) for x, y, face in face_labels(mini) if face == mini.boards[1].face)
    l = top[np.argmax(np.hypot(*(mini.leds.cross_pixel[top] - [lx, ly]).T))]
    c, r = mini.leds.cross_pixel[l]
    y0, x0 = MARGIN_PX + TITLE_PX + r * SCALE, MARGIN_PX + c * SCALE
    block = img[y0:y0 + SCALE, x0:x0 + SCALE].reshape(-1, 3)
    assert np.all(block == block[0]) and abs(int(block[0, 0]) - int(ps.levels[1, l, 0])) <= 1

    grid = save_pattern_image(ps, mini, tmp_path / "grid.png")  # 3 frames: 2 columns x 2 rows
    img = np.asarray(Image.open(grid).convert("RGB"))
    assert img.shape == (2 * (H * GRID_SCALE + TITLE_PX) + 3 * MARGIN_PX,
                         2 * W * GRID_SCALE + 3 * MARGIN_PX + BAR_PX, 3)
    assert not list(tmp_path.glob(".*.png"))  # atomic writes leave no temp files


def test_save_pattern_image_bad_index(tmp_path, mini):
    ps = _gradient_patterns(mini, 2)
    for bad in (2, -1, 99):
        with pytest.raises(ValueError, match="out of range"):
            save_pattern_image(ps, mini, tmp_path / "bad.png", index=bad)
    assert not (tmp_path / "bad.png").exists()


def test_cli_show_pattern(tmp_path, mini, capsys):
    from hemicube.cli import main

    path = tmp_path / "p.npz"
    save_patterns(_gradient_patterns(mini, 2), path)
    out = tmp_path / "p.png"
    assert main(["show", "pattern", str(path), "-o", str(out), "--index", "0"]) == 0
    assert Image.open(out).size == (874, 552)
    assert main(["show", "pattern", str(path), "-o", str(out), "--index", "5"]) == 2
    assert "out of range" in capsys.readouterr().err


def test_save_cross_image_lumitexel(tmp_path, mini):
    lumi = np.linspace(0.0, 3.0, mini.num_leds)
    out = save_cross_image(mini, lumi, tmp_path / "lumi.png", title="a lumitexel")
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape[0] == 128 * SCALE + TITLE_PX + 2 * MARGIN_PX
    assert img.shape[1] > 192 * SCALE + 2 * MARGIN_PX  # plus the colour bar
    # the last LED (the maximum) is inferno's top colour
    c, r = mini.leds.cross_pixel[-1]
    px = img[MARGIN_PX + TITLE_PX + r * SCALE + 1, MARGIN_PX + c * SCALE + 1]
    assert np.allclose(px, np.rint(np.array(colormaps["inferno"](1.0)[:3]) * 255), atol=1)


def test_pattern_pictures_name_the_faces_and_show_their_scale(mini):
    """A pattern's cross picture names every face of the cube on it and has a scale of the drive level."""
    from twin.view.cross_plot import PATTERN_SCALE, tiles_figure

    labels = face_labels(mini)
    assert sorted(f for _, _, f in labels) == sorted({b.face for b in mini.boards})
    ps = _gradient_patterns(mini, 1)
    fig = tiles_figure([(cross_rgb(mini, ps.weights[0]), "0: p")], SCALE, PATTERN_SCALE, labels)
    texts = {t.get_text() for ax in fig.axes for t in ax.texts}
    assert {f for _, _, f in labels} <= texts
    bar = fig.axes[-1]
    assert bar.get_ylabel() == PATTERN_SCALE[2] and bar.get_ylim() == (0.0, 255.0)
