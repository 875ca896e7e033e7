"""3-D view of the rig (pyvista): boards, LEDs coloured by a per-LED vector, cameras, sample and holder.

`hemicube show rig` calls `show_rig`. It renders off-screen to a PNG when an output is given or no display
exists, and opens an interactive window otherwise. pyvista (and vtk) are imported inside the functions:
the GPU benchmark machines do not have them, and `import twin.view.rig_view` must not fail there.

The view is fixed and deterministic: an oblique look down into the cube from outside it, on the -y side
and about 30 degrees above the horizon. Every exterior view looks through at least one board, so the
boards the viewer sees from behind (here the -y wall and the two top boards) are cut away: only their
outline is drawn and their LEDs shrink to small flat dots, between which the far walls, the sample with
its holder and the bottom board stay visible.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

# Tableau 10: distinct, print-friendly colours for "colour by board" (values=None).
BOARD_COLOURS = ("#4e79a7", "#f28e2b", "#59a14f", "#e15759", "#76b7b2", "#b07aa1", "#edc948",
                 "#ff9da7", "#9c755f", "#bab0ac")
CAMERA_COLOURS = ("#1f3b73", "#8c2d04", "#225522", "#5b2a86")
# Viewing direction (from the focal point towards the eye) and distance, in units of the rig's largest
# extent: ~29 degrees of elevation, so the sample and the bottom board are seen well, not at a graze.
VIEW_DIRECTION = (-0.05, -1.0, 0.55)
VIEW_DISTANCE = 2.3
DRIVE_BAR = "drive level"  # the scale bar of a pattern's RGB drive weights, 0 to 255 (255 = full drive)


# --- geometry (numpy only, testable without pyvista) ------------------------------------------------
def board_rectangle(rig, b: int) -> tuple[np.ndarray, np.ndarray]:
    """(4, 3) corners of board `b` and its unit normal (into the cube).

    The in-plane axes follow the board's column and row directions, fitted by least squares to the
    LED positions (an affine map (row, col) -> position), so the rectangle is aligned with the grid
    even for a tilted board. Its extent covers the whole rows x cols grid, padded by half a pitch, so a
    subsampled board (the mini rig) still shows its full physical size. The pitch along each axis is the
    median step between neighbouring LEDs present on the board, which ignores gaps such as the camera
    slot between the two tiles of a board."""
    sel = rig.leds.board == b
    p = rig.leds.positions[sel]
    r = rig.leds.row[sel].astype(float)
    c = rig.leds.col[sel].astype(float)
    board = rig.boards[b]
    A = np.stack([np.ones_like(r), c, r], axis=1)
    coef, *_ = np.linalg.lstsq(A, p, rcond=None)
    u, v = coef[1], coef[2]  # world step per column and per row
    n = rig.leds.normals[sel].mean(0)
    if np.linalg.norm(u) < 1e-9 or np.linalg.norm(v) < 1e-9:  # a single row or column: use a PCA plane
        _, _, vt = np.linalg.svd(p - p.mean(0))
        u, v = vt[0], vt[1]
    u = u / np.linalg.norm(u)
    v = v - np.dot(v, u) * u
    v = v / np.linalg.norm(v)
    n = n - np.dot(n, u) * u - np.dot(n, v) * v
    n = n / np.linalg.norm(n)
    centre = p.mean(0)
    pu, pv = (p - centre) @ u, (p - centre) @ v
    pitch_u, pitch_v = _pitch(pu, c, r), _pitch(pv, r, c)
    u0 = pu.min() - (c.min() + 0.5) * pitch_u
    u1 = pu.max() + (board.cols - 1 - c.max() + 0.5) * pitch_u
    v0 = pv.min() - (r.min() + 0.5) * pitch_v
    v1 = pv.max() + (board.rows - 1 - r.max() + 0.5) * pitch_v
    plane = centre + np.dot(p - centre, n).mean() * n
    corners = np.array([plane + a * u + bb * v for a, bb in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))])
    return corners, n


def _pitch(coord: np.ndarray, index: np.ndarray, other: np.ndarray) -> float:
    """Median spacing per unit of `index` between LEDs that are neighbours along `index` on one line of
    constant `other`."""
    steps = []
    for o in np.unique(other):
        k = np.flatnonzero(other == o)
        k = k[np.argsort(index[k])]
        di = np.diff(index[k])
        ok = di > 0
        steps.append(np.abs(np.diff(coord[k]))[ok] / di[ok])
    steps = np.concatenate(steps) if steps else np.zeros(0)
    return float(np.median(steps)) if steps.size else 10.0


def camera_frustum(cam, sample) -> tuple[np.ndarray, np.ndarray]:
    """The camera centre (3,) and the 4 image corners (4, 3) where their rays meet the sample plane."""
    w, h = cam.width, cam.height
    uv = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    return cam.centre, cam.plane_points(uv, sample.origin, sample.normal)


def led_colours(values, num_leds: int) -> tuple[str, np.ndarray | None]:
    """Classify a per-LED vector: ("none", None), ("scalar", (L,) float) or ("rgb", (L, 3) uint8).
    RGB values above 1 are normalised by their maximum (drive weights are already in [0, 1])."""
    if values is None:
        return "none", None
    v = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError("values contain NaN or Inf")
    if v.shape == (num_leds,):
        return "scalar", v
    if v.shape == (num_leds, 3):
        v = np.clip(v, 0, None)
        if v.max() > 1:
            v = v / v.max()
        return "rgb", np.rint(v * 255).astype(np.uint8)
    raise ValueError(f"values must have shape ({num_leds},) or ({num_leds}, 3), got {v.shape}")


def default_view(rig) -> tuple[tuple, tuple, tuple]:
    """(position, focal point, view up) of the fixed view: from outside the -y wall and above the top,
    looking at a point halfway between the sample and the top; slightly towards -x, so that the +x
    wall (with the secondary camera's slot) is seen less edge-on."""
    pos = rig.leds.positions
    lo, hi = pos.min(0), pos.max(0)
    centre = 0.5 * (lo + hi)
    centre[2] = 0.5 * (rig.sample.origin[2] + hi[2])  # the sample and the top both in the picture
    size = float(np.max(hi - lo))
    d = np.asarray(VIEW_DIRECTION, float)
    eye = centre + VIEW_DISTANCE * size * d / np.linalg.norm(d)
    return tuple(eye), tuple(centre), (0.0, 0.0, 1.0)


# --- the scene -----------------------------------------------------------------------------------------
def build_plotter(rig, values=None, window_size=(1200, 900), off_screen: bool = True, title: str = ""):
    """A pyvista Plotter holding the rig scene with the fixed view (`show_rig` renders it). `title` names what the
    LEDs show (a pattern's frame and name), after the rig's line. Scalar values get a colour bar of their range, RGB
    values (a pattern's drive weights, in [0, 1]) one of the drive level, 0 to 255."""
    try:
        import pyvista as pv
    except ImportError:
        raise ValueError("the 3-D rig view needs pyvista: pip install 'hemicube-twin[view]'") from None

    kind, colours = led_colours(values, rig.num_leds)
    pl = pv.Plotter(off_screen=off_screen, window_size=tuple(int(s) for s in window_size))
    pl.set_background("white", top="#c9d3e0")
    # No depth peeling: with VTK 9.7 on Mesa/EGL it drops translucent surfaces altogether. VTK's default
    # blending (translucent actors after the opaque ones) is right here, as translucent surfaces rarely
    # overlap each other in this view.
    eye, focus, up = default_view(rig)
    eye_dir = np.subtract(eye, focus)

    # Pixels per mm at the focal point: sets the LED sphere size from the LED pitch so that neighbouring
    # LEDs stay separate dots whatever the rig's density and the window size.
    view_angle = 30.0  # vtk's default vertical view angle, degrees
    px_per_mm = window_size[1] / (2 * np.linalg.norm(eye_dir) * np.tan(np.radians(view_angle / 2)))

    bar_shown = False
    for b, board in enumerate(rig.boards):
        sel = np.flatnonzero(rig.leds.board == b)
        if sel.size == 0:
            continue
        colour = BOARD_COLOURS[b % len(BOARD_COLOURS)]
        corners, n = board_rectangle(rig, b)
        # The viewer sees a board from behind when it is outside the board's plane: cut it away, i.e.
        # draw only its outline, and its LEDs as small flat dots between which the inside shows.
        cut = np.dot(np.subtract(eye, corners.mean(0)), n) < 0
        size = float(np.clip(0.65 * led_pitch(rig, sel) * px_per_mm, 3, 24))
        if cut:
            pl.add_mesh(pv.PolyData(np.vstack([corners, corners[:1]]), lines=[5, 0, 1, 2, 3, 4]),
                        color="#555555", line_width=1.5)
            size = max(2.0, 0.3 * size)
        else:
            pl.add_mesh(pv.PolyData(corners, faces=[4, 0, 1, 2, 3]),
                        color=colour if kind == "none" else "#7a8494", opacity=0.18, show_edges=True,
                        edge_color="#555555", line_width=1.5)
        kw = dict(point_size=size, render_points_as_spheres=not cut, lighting=True)
        cloud = pv.PolyData(rig.leds.positions[sel])
        if kind == "none":
            pl.add_mesh(cloud, color=colour, label=f"{board.name} ({sel.size})", **kw)
        elif kind == "rgb":
            cloud["rgb"] = colours[sel]
            pl.add_mesh(cloud, scalars="rgb", rgb=True, **kw)
        else:  # one shared colour range for all boards, so one scalar bar describes them all
            cloud["value"] = colours[sel]
            lo, hi = float(colours.min()), float(colours.max())
            pl.add_mesh(cloud, scalars="value", cmap="inferno", clim=(lo, hi if hi > lo else lo + 1),
                        show_scalar_bar=not bar_shown,
                        scalar_bar_args=dict(title="LED value", vertical=True, position_x=0.88,
                                             position_y=0.25, height=0.5, color="black"), **kw)
            bar_shown = True

    if kind == "rgb":  # the drive level's bar, from a point that draws nothing (a bar needs a mapped mesh)
        probe = pv.PolyData(np.asarray(rig.sample.origin, float)[None].repeat(2, 0))
        probe["drive level"] = np.array([0.0, 255.0])
        pl.add_mesh(probe, scalars="drive level", cmap="gray", clim=(0, 255), opacity=0.0,
                    scalar_bar_args=dict(title=DRIVE_BAR, vertical=True, position_x=0.88,
                                         position_y=0.25, height=0.5, color="black"))
    _add_bottom(pl, rig, pv)
    _add_sample(pl, rig, pv)
    _add_cameras(pl, rig, pv)
    _add_faces(pl, rig)
    if kind == "none":
        pl.add_legend(bcolor="white", face="circle", size=(0.14, 0.2), loc="upper left")
    pl.add_text(f"rig {rig.name}: {rig.num_leds} LEDs on {len(rig.boards)} boards, "
                f"{len(rig.cameras)} cameras" + (f"\n{title}" if title else ""), position="upper_edge", font_size=11,
                color="black")
    pl.add_axes(color="black")
    pl.camera_position = [eye, focus, up]
    pl.camera.view_angle = view_angle
    return pl


def led_pitch(rig, sel) -> float:
    """Typical distance between an LED and its nearest neighbour on the same board (mm)."""
    from scipy.spatial import cKDTree

    p = rig.leds.positions[sel]
    if len(p) < 2:
        return 10.0
    d, _ = cKDTree(p).query(p, k=2)
    return float(np.median(d[:, 1]))


def _add_bottom(pl, rig, pv) -> None:
    """The translucent acrylic board the sample rests on: a slab over the bottom LED board's footprint,
    its top face in the sample plane."""
    if rig.bottom is None or not rig.is_bottom.any():
        return
    b = int(np.bincount(rig.leds.board[rig.is_bottom]).argmax())
    corners, _ = board_rectangle(rig, b)
    n, o = np.asarray(rig.sample.normal), np.asarray(rig.sample.origin)
    top = corners - np.dot(corners - o, n)[:, None] * n  # the bottom board's outline in the sample plane
    t = max(rig.bottom.acrylic_thickness, 0.5)
    verts = np.vstack([top, top - t * n])
    faces = [4, 0, 1, 2, 3, 4, 4, 7, 6, 5, 4, 0, 4, 5, 1, 4, 1, 5, 6, 2, 4, 2, 6, 7, 3, 4, 3, 7, 4, 0]
    pl.add_mesh(pv.PolyData(verts, faces=faces), color="#9ecae1", opacity=0.22, show_edges=True,
                edge_color="#3b7ca8", line_width=2)


def _add_sample(pl, rig, pv) -> None:
    """Sample square, holder frame and its ArUco markers (dark quads, lifted 0.3 mm above the frame's
    top so they do not z-fight with it)."""
    pl.add_mesh(pv.PolyData(rig.sample.corners(), faces=[4, 0, 1, 2, 3]), color="#e8dcc0",
                show_edges=True, edge_color="#8a7a50")
    if rig.frame is None:
        return
    mesh = rig.frame.mesh(rig.sample)
    if mesh is not None:
        verts, tris = mesh
        faces = np.hstack([np.full((len(tris), 1), 3), tris]).ravel()
        pl.add_mesh(pv.PolyData(verts, faces=faces), color="#b8bcc4", smooth_shading=False)
    mc = np.asarray(rig.frame.marker_corners, float)
    if len(mc):
        lift = 0.3 * np.asarray(rig.sample.normal)
        verts = mc.reshape(-1, 3) + lift
        faces = np.hstack([np.full((len(mc), 1), 4), np.arange(4 * len(mc)).reshape(-1, 4)]).ravel()
        pl.add_mesh(pv.PolyData(verts, faces=faces), color="#151515", lighting=False)


def face_centres(rig) -> dict[str, np.ndarray]:
    """Each face's name (twin.rig.model.Board.face) -> the centre (3,) of its boards' rectangles, mm."""
    return {face: np.mean([board_rectangle(rig, b)[0].mean(0) for b in np.unique(rig.leds.board[idx])], axis=0)
            for face, idx in rig.face_leds().items()}


def _add_faces(pl, rig) -> None:
    """Each face's name at its centre, so that a reader knows which wall is which."""
    centres = face_centres(rig)
    pl.add_point_labels(np.array(list(centres.values())), list(centres), font_size=12, text_color="black",
                        shape_color="white", shape_opacity=0.6, show_points=False, always_visible=True,
                        name="faces")


def _add_cameras(pl, rig, pv) -> None:
    """Each camera's frustum down to the sample plane (centre-to-corner lines and the image rectangle
    on the plane), labelled with its name."""
    for k, (name, cam) in enumerate(rig.cameras.items()):
        C, quad = camera_frustum(cam, rig.sample)
        verts = np.vstack([C[None], quad])
        lines = [2, 0, 1, 2, 0, 2, 2, 0, 3, 2, 0, 4, 5, 1, 2, 3, 4, 1]
        colour = CAMERA_COLOURS[k % len(CAMERA_COLOURS)]
        pl.add_mesh(pv.PolyData(verts, lines=lines), color=colour, line_width=2.5)
        pl.add_point_labels(C[None], [name], font_size=14, text_color=colour, point_color=colour,
                            point_size=10, render_points_as_spheres=True, shape_opacity=0.6,
                            shape_color="white", always_visible=True)


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def show_rig(rig, values=None, output=None, window_size=(1200, 900), title: str = "") -> Path | None:
    """Draw the rig (build_plotter). Off-screen (output given, or no display): write a PNG (default "rig.png")
    atomically and return its path. Otherwise open an interactive window and return None."""
    if output is None and has_display():
        build_plotter(rig, values, window_size, off_screen=False, title=title).show()
        return None
    from twin.atomic import atomic_path

    output = Path(output if output is not None else "rig.png")
    pl = build_plotter(rig, values, window_size, off_screen=True, title=title)
    try:
        with atomic_path(output, suffix=".png") as tmp:
            pl.screenshot(str(tmp))
    finally:
        pl.close()
    return output
