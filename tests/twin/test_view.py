"""twin.view.rig_view: the 3-D rig view renders off-screen, and LED colours land where the LEDs are.
(`paper` and `mini` are the session fixtures of conftest.py.)"""
from __future__ import annotations

import numpy as np
import pytest

from twin.view.rig_view import board_rectangle, camera_frustum, default_view

pv = pytest.importorskip("pyvista")
from PIL import Image  # noqa: E402  (pillow comes with pyvista)


@pytest.fixture(autouse=True)
def _headless(monkeypatch):
    monkeypatch.setenv("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


# --- geometry -------------------------------------------------------------------------------------------
def test_board_rectangles_enclose_their_leds(paper, mini):
    for rig in (paper, mini):
        for b, board in enumerate(rig.boards):
            corners, n = board_rectangle(rig, b)
            p = rig.leds.positions[rig.leds.board == b]
            centre = corners.mean(0)
            assert abs(np.linalg.norm(n) - 1) < 1e-9
            assert np.dot(n, rig.leds.normals[rig.leds.board == b].mean(0)) > 0.99  # faces into the cube
            assert np.abs((p - centre) @ n).max() < 8.0  # LEDs lie on the plane (boards are slightly warped)
            u, v = corners[1] - corners[0], corners[3] - corners[0]
            assert abs(np.dot(u, v)) < 1e-6 * np.linalg.norm(u) * np.linalg.norm(v)  # a rectangle
            if rig is paper:  # all LEDs present: the LEDs' extent padded by half the 10 mm pitch each side
                for axis in (u, v):
                    extent = np.ptp(p @ axis / np.linalg.norm(axis))
                    assert np.linalg.norm(axis) == pytest.approx(extent + 10.0, abs=1.5)
                # ... which is the rows x cols grid, plus the gap between its two tiles along the columns
                # (up to the ~60 mm camera slot of top B and +x)
                assert np.linalg.norm(v) == pytest.approx(board.rows * 10.0, abs=3.0)
                assert board.cols * 10.0 - 3.0 < np.linalg.norm(u) < board.cols * 10.0 + 55.0
            a = (p - corners[0]) @ u / (u @ u)
            c = (p - corners[0]) @ v / (v @ v)
            assert a.min() > 0 and a.max() < 1 and c.min() > 0 and c.max() < 1
    # the mini rig's boards are drawn at full size although it keeps only every 6th LED
    for b in range(len(mini.boards)):
        assert np.allclose(board_rectangle(mini, b)[0], board_rectangle(paper, b)[0], atol=6.0)


def test_frustum_reaches_the_sample_plane(mini):
    for cam in mini.cameras.values():
        C, quad = camera_frustum(cam, mini.sample)
        assert np.allclose(C, cam.centre)
        assert np.allclose(quad[:, 2], mini.sample.origin[2])
        uv, z = cam.project(quad)  # the 4 points are the image corners
        w, h = cam.width, cam.height
        corners = [[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]]
        assert np.allclose(uv, corners, atol=1e-3)
        assert np.all(z > 0)


# --- rendering ------------------------------------------------------------------------------------------
def test_cli_show_rig_writes_a_picture(tmp_path, capsys):
    from hemicube.cli import main

    out = tmp_path / "rig.png"
    assert main(["show", "rig", "--rig", "mini", "-o", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape == (900, 1200, 3)  # the default --size 1200 900
    colours = np.unique(img.reshape(-1, 3), axis=0)
    assert len(colours) > 2000  # shaded spheres, translucent boards, text: far from one flat colour
    assert img.std(axis=(0, 1)).min() > 20
    assert not list(tmp_path.glob(".rig.png.*"))  # the atomic write left no temp file


def test_show_rig_default_output_and_values(tmp_path, monkeypatch, mini):
    from twin.view.rig_view import show_rig

    monkeypatch.chdir(tmp_path)
    out = show_rig(mini, values=np.linspace(0, 1, mini.num_leds), window_size=(320, 240))
    assert out == tmp_path / "rig.png" or out.resolve() == (tmp_path / "rig.png").resolve()
    assert Image.open(tmp_path / "rig.png").size == (320, 240)
    with pytest.raises(ValueError, match="values must have shape"):
        show_rig(mini, values=np.zeros(3), output=tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()


def _display_points(pl, X) -> np.ndarray:
    """(N, 2) display coordinates (x right, y up from the bottom) of world points, from vtk's own
    world->display transform of the rendered view."""
    ren = pl.renderer
    out = []
    for x, y, z in np.asarray(X, float):
        ren.SetWorldPoint(x, y, z, 1.0)
        ren.WorldToDisplay()
        out.append(ren.GetDisplayPoint()[:2])
    return np.array(out)


def _led_point_sizes(pl, rig) -> np.ndarray:
    """(L,) rendered point size in pixels of every LED, read from the plotter's actors."""
    index = {tuple(p): i for i, p in enumerate(rig.led_positions)}
    size = np.full(rig.num_leds, np.nan)
    for actor in pl.renderer.actors.values():
        data = getattr(getattr(actor, "mapper", None), "dataset", None)
        if data is None or data.n_points == 0 or data.n_cells != data.n_points:
            continue
        hits = [index.get(tuple(p)) for p in np.asarray(data.points, float)]
        if all(h is not None for h in hits):
            size[hits] = actor.prop.point_size
    assert not np.isnan(size).any(), "every LED is drawn as a point"
    return size


def _window(img, xy, half=2) -> np.ndarray:
    """Pixels (k, 3) of the (2*half+1)^2 window of the screenshot around display point xy."""
    H = img.shape[0]
    col, row = int(round(xy[0])), int(round(H - 1 - xy[1]))  # display y is from the bottom
    return img[row - half: row + half + 1, col - half: col + half + 1].reshape(-1, 3).astype(int)


def test_led_colours_land_on_the_leds(mini):
    """One LED of the +y wall (the far wall, seen face-on through the cut-away -y wall) is pure green,
    all others pure red. Projected with the plotter's camera, the green LED's pixel must be green and a
    red LED's pixel red."""
    from twin.view.rig_view import build_plotter

    rig = mini
    W, H = 800, 600
    face = {b.face: i for i, b in enumerate(rig.boards)}
    probe = build_plotter(rig, np.tile([1.0, 0.0, 0.0], (rig.num_leds, 1)), window_size=(W, H))
    probe.screenshot(return_img=True)
    xy = _display_points(probe, rig.led_positions)
    radius = _led_point_sizes(probe, rig) / 2
    probe.close()

    # candidates: LEDs with no nearer LED drawn over them (unoccluded), inside the picture and
    # away from its edges (title, axes widget); the +y wall's LED nearest the image centre becomes green
    eye = np.asarray(default_view(rig)[0])
    depth = np.linalg.norm(rig.led_positions - eye, axis=1)
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
    occluded = ((d < radius[None, :] + 4) & (depth[None, :] < depth[:, None])).any(1)
    free = ~occluded & (xy[:, 0] > 100) & (xy[:, 0] < W - 100) & (xy[:, 1] > 80) & (xy[:, 1] < H - 80)
    wall = np.flatnonzero(free & (rig.leds.board == face["+y"]))
    assert wall.size >= 5, "the +y wall should be visible through the cut-away"
    green = wall[np.argmin(np.linalg.norm(xy[wall] - [W / 2, H / 2], axis=1))]
    values = np.tile([1.0, 0.0, 0.0], (rig.num_leds, 1))
    values[green] = (0.0, 1.0, 0.0)

    pl = build_plotter(rig, values, window_size=(W, H))
    img = pl.screenshot(return_img=True)
    assert img.shape[:2] == (H, W)
    xy2 = _display_points(pl, rig.led_positions)
    pl.close()
    assert np.allclose(xy, xy2, atol=1e-6)  # the view is deterministic: it does not depend on the values

    win = _window(img, xy[green])
    r, g, b = win[:, 0], win[:, 1], win[:, 2]
    assert np.mean((g > r + 60) & (g > b + 60)) > 0.6, f"green LED {green} rendered as {win.mean(0)}"

    # a red LED, unoccluded, on the -x wall: red-dominant
    side = np.flatnonzero(free & (rig.leds.board == face["-x"]))
    red = side[np.argmin(np.linalg.norm(xy[side] - [W / 2, H / 2], axis=1))]
    win = _window(img, xy[red])
    r, g, b = win[:, 0], win[:, 1], win[:, 2]
    assert np.mean((r > g + 60) & (r > b + 60)) > 0.6, f"red LED {red} rendered as {win.mean(0)}"
    # and the green LED is the only green thing on the LEDs
    greens = [np.mean((w[:, 1] > w[:, 0] + 60)) for w in (_window(img, p) for p in xy[free])]
    assert sum(x > 0.6 for x in greens) == 1


def test_default_view_looks_in_from_minus_y_above(mini):
    eye, focus, up = default_view(mini)
    assert eye[1] < mini.led_positions[:, 1].min()  # outside the -y wall
    assert eye[2] > focus[2] > mini.sample.origin[2]  # from above, looking down at the sample
    assert up == (0.0, 0.0, 1.0)


def test_a_patterns_view_names_it_and_has_a_drive_scale_and_face_labels(mini, tmp_path):
    """`show rig --values PATTERNS --index K`: the picture names the frame, has a colour bar of the drive level and
    names the cube's faces."""
    from twin.capture.patterns import save_patterns
    from twin.capture.plan import build_patterns
    from twin.cli import load_led_values
    from twin.view.rig_view import DRIVE_BAR, build_plotter, face_centres

    patterns = build_patterns(mini)
    save_patterns(patterns, tmp_path / "p.npz")
    values, what = load_led_values(str(tmp_path / "p.npz"), mini, 70)
    assert what == f"p.npz, frame 70: {patterns.names[70]}"
    pl = build_plotter(mini, values, window_size=(320, 240), title=what)
    try:
        assert DRIVE_BAR in pl.scalar_bars.keys() and "faces-labels" in pl.actors
        title = pl.actors[next(k for k in pl.actors if k.startswith("CornerAnnotation"))]
        assert what in "".join(title.GetText(i) or "" for i in range(8))
    finally:
        pl.close()
    assert set(face_centres(mini)) == {b.face for b in mini.boards}
