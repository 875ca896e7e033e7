"""The rig as one self-contained interactive web page (`hemicube show rig --html OUT.html`).

The page holds everything it shows: the rig's geometry and every frame's LED colours as base64 data, and a small
viewer (`rig_page.html`: plain JavaScript on a 2-D canvas, no library, no WebGL), so it opens from a file with no
network and renders in a browser without a GPU. It shows the same scene as the PNG view (twin.view.rig_view): the
boards, whose LEDs are coloured by board or by the chosen frame, the cameras' frusta to the sample plane, the sample
and its holder's markers, each face named; the boards the viewer sees from behind are cut away to their outline.
Drag turns the rig about its centre, the wheel zooms, a selector (or the arrow keys) picks the frame; the address's
`#frame=K` opens frame K (0-based) and follows the selector, so a view can be linked to.

Coordinates stay the rig's (millimetres, right-handed, +z out of the sample; twin/rig/units.py); the page looks at
them with +z up on the screen.
"""
from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

from twin.view.rig_view import (BOARD_COLOURS, CAMERA_COLOURS, DRIVE_BAR, board_rectangle, camera_frustum,
                                default_view, face_centres, led_colours, led_pitch)

TEMPLATE = Path(__file__).with_name("rig_page.html")
DATA_MARK = "/*RIG_DATA*/null"  # the template's placeholder for the scene's JSON
SCALAR_MAP = "inferno"
BAR_STOPS = 11  # colour stops of a scalar frame's bar


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def page_frames(values, num_leds: int, names=None) -> list[dict]:
    """The page's frames from per-LED values: (L,) or (L, 3) one frame, (N, L, 3) N frames (a pattern set's drive
    weights in [0, 1], 1 = full drive). Each frame is {name, rgb (base64 of (L, 3) uint8), bar}; its bar is the
    drive level 0-255 for RGB, or for scalars the colour map (inferno) over their range with its end values."""
    from matplotlib import colormaps

    v = np.asarray(values, np.float64)
    stack = list(v) if v.ndim == 3 and v.shape[1:] == (num_leds, 3) else [v]
    names = list(names) if names is not None else [f"frame {k}" for k in range(len(stack))]
    frames = []
    for name, f in zip(names, stack):
        kind, colours = led_colours(f, num_leds)  # the PNG view's reading of a per-LED vector: one rule for both
        if kind == "scalar":
            lo, hi = float(colours.min()), float(colours.max())
            cmap = colormaps[SCALAR_MAP]
            rgb = np.rint(cmap((colours - lo) / (hi - lo) if hi > lo else np.zeros_like(colours))[:, :3] * 255)
            bar = {"title": "LED value", "lo": lo, "hi": hi,
                   "stops": [_hex(cmap(t)[:3]) for t in np.linspace(0, 1, BAR_STOPS)]}
        else:
            rgb = colours
            bar = {"title": DRIVE_BAR, "lo": 0, "hi": 255, "stops": ["#000000", "#ffffff"]}
        frames.append({"name": str(name), "rgb": _b64(rgb.astype(np.uint8)), "bar": bar})
    return frames


def _hex(rgb) -> str:
    return "#" + "".join(f"{int(round(255 * c)):02x}" for c in rgb)


def scene(rig, frames: list[dict] | None = None, title: str = "", start: int = 0) -> dict:
    """The page's data: the rig's geometry in mm (LED positions and boards, cameras, sample, holder markers, face
    centres), the initial view (rig_view.default_view), the frames (page_frames) and the one shown first."""
    boards = []
    for b, board in enumerate(rig.boards):
        sel = np.flatnonzero(rig.leds.board == b)
        if sel.size == 0:
            continue
        corners, n = board_rectangle(rig, b)
        boards.append({"index": b, "name": board.name, "face": board.face, "colour": BOARD_COLOURS[b % len(BOARD_COLOURS)],
                       "corners": corners.round(3).tolist(), "normal": n.round(6).tolist(),
                       "pitch": round(led_pitch(rig, sel), 3)})
    cameras = []
    for k, (name, cam) in enumerate(rig.cameras.items()):
        centre, quad = camera_frustum(cam, rig.sample)
        cameras.append({"name": name, "colour": CAMERA_COLOURS[k % len(CAMERA_COLOURS)],
                        "centre": np.round(centre, 3).tolist(), "quad": np.round(quad, 3).tolist()})
    markers = np.asarray(rig.frame.marker_corners, float) if rig.frame is not None else np.zeros((0, 4, 3))
    eye, focus, up = default_view(rig)
    frames = frames or []
    if frames and not 0 <= start < len(frames):
        raise ValueError(f"frame {start} out of range 0..{len(frames) - 1}")
    return {
        "rig": rig.name, "title": title,
        "summary": f"rig {rig.name}: {rig.num_leds} LEDs on {len(rig.boards)} boards, {len(rig.cameras)} cameras",
        "num_leds": int(rig.num_leds),
        "positions": _b64(rig.leds.positions.astype(np.float32)),
        "board": _b64(rig.leds.board.astype(np.uint16)),
        "boards": boards, "cameras": cameras,
        "faces": [{"name": f, "centre": np.round(c, 3).tolist()} for f, c in face_centres(rig).items()],
        "sample": np.round(rig.sample.corners(), 3).tolist(),
        "markers": np.round(markers, 3).tolist(),
        "view": {"eye": np.round(eye, 3).tolist(), "focus": np.round(focus, 3).tolist(), "up": list(up)},
        "frames": frames, "start": int(start) if frames else -1,
    }


def page_html(data: dict) -> str:
    """The page: the template with the scene's JSON in place of its placeholder. `</` is escaped inside the JSON so
    that no name can close the script element that holds it."""
    template = TEMPLATE.read_text(encoding="utf-8")
    if template.count(DATA_MARK) != 1:
        raise RuntimeError(f"{TEMPLATE}: expected one {DATA_MARK!r}")
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    return template.replace(DATA_MARK, payload)


def write_rig_page(rig, output, values=None, names=None, title: str = "", start: int = 0) -> Path:
    """Write the page to `output` (a new .html file; atomic) and return its path. `values`, `names`: page_frames';
    `start`: the frame shown first."""
    from twin.atomic import atomic_path

    output = Path(output)
    if output.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"{output}: the page's name must end in .html")
    frames = page_frames(values, rig.num_leds, names) if values is not None else None
    html = page_html(scene(rig, frames, title, start))
    with atomic_path(output, suffix=".html") as tmp:
        Path(tmp).write_text(html, encoding="utf-8")
    return output
