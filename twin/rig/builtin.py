"""Built-in rigs: `paper` (the full device, from the facts of reference §1) and `mini` (the same
geometry with a few hundred upper LEDs and small images, for CI and quick demos)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from twin.rig.camera import Camera, cross3, dot3, orthonormalise, unit3
from twin.rig.cross import layout_pixels
from twin.rig.model import PROFILE_PARAMS, Board, BottomBoard, HolderFrame, LEDs, Rig, SamplePlane

# Released upper-LED layout (reference §1.3): per 32x32 tile, the position of its first LED and the
# steps (mm) along the fast and slow indices. Tile t belongs to board t // 2; board column =
# 32 * (t % 2) + fast, board row = slow. Rebuilt from these numbers, every LED lies within 0.37 mm of
# `lights.bin` (tests/test_rig_builtin.py checks <= 1 mm). The two tiles of the top-B and +x boards
# are 59.8 mm apart: that is the ~50 mm camera slot.
TILES = [  # (origin, fast step, slow step)
    ((-386.29, 321.00, -96.13), (-0.09, -10.00, 0.09), (0.00, 0.09, 9.99)),
    ((-389.19, -4.78, -93.17), (-0.09, -10.00, 0.09), (0.00, 0.09, 9.99)),
    ((-67.16, -315.13, 239.57), (0.10, 10.00, -0.11), (-9.99, 0.10, -0.06)),
    ((-63.79, 10.63, 235.87), (0.10, 10.00, -0.11), (-9.99, 0.10, -0.06)),
    ((256.31, -338.94, 242.00), (0.09, 10.00, -0.07), (-9.99, 0.09, -0.14)),
    ((259.74, 30.84, 239.32), (0.09, 10.00, -0.07), (-9.99, 0.09, -0.14)),
    ((293.91, -343.20, -87.25), (0.09, 10.00, -0.11), (-0.11, 0.11, 10.03)),
    ((297.29, 26.57, -91.18), (0.09, 10.00, -0.11), (-0.11, 0.11, 10.03)),
    ((-375.83, -353.15, -90.91), (10.00, -0.16, 0.04), (-0.03, 0.30, 9.99)),
    ((-50.07, -358.23, -89.70), (10.00, -0.16, 0.04), (-0.03, 0.30, 9.99)),
    ((265.13, 350.45, -94.66), (-10.00, 0.16, -0.01), (-0.01, 0.11, 9.99)),
    ((-60.63, 355.62, -95.01), (-10.00, 0.16, -0.01), (-0.01, 0.11, 9.99)),
]
UPPER_BOARDS = [  # (name, face, cross-layout key), in tile order
    ("-x wall", "-x", "-x"), ("top A", "top", "topA"), ("top B", "top", "topB"),
    ("+x wall", "+x", "+x"), ("-y wall", "-y", "-y"), ("+y wall", "+y", "+y"),
]
# Bottom board (paper §5: 4,096 LEDs under the translucent acrylic). No geometry is released
# (reference §1.4): ASSUMED a 64x64 grid at the same 10 mm pitch, 60 mm below the sample plane,
# centred between the walls in x (-389 .. +295 mm) and on y = 0; row index grows towards -y and column
# towards +x, matching its place in the cross image.
BOTTOM_GRID = 64
BOTTOM_PITCH = 10.0
BOTTOM_CENTRE = (-45.0, 0.0, -182.0)

# Per-LED radiant intensity on axis at full drive, W/sr, RGB. ASSUMED (the calibrated lights_intensity.npy
# is not released, reference §1.1): a ~0.2 W mid-power white LED behind a diffuser, ~0.05 W/sr.
LED_INTENSITY_W_SR = 0.05

# Released primary camera (reference §1.5): intrinsic.yml / extrinsic.yml, at the released
# resolution 2664 x 2304 (the a2A5328-15ucPRO's 5328 x 4608 sensor at half resolution, as the
# released pipeline uses it; `Camera.resized(2)` gives the native grid).
PRIMARY_K = [[4923.0, 0.0, 1322.3], [0.0, 4923.43, 1120.98], [0.0, 0.0, 1.0]]
PRIMARY_DIST = [0.078406, -0.602699, 0.000278, -0.000606, -1.975753]
# R is typed to 6 digits, so it is orthonormal only to ~1e-6: the rig uses its Gram-Schmidt
# orthonormalisation (an exact rotation within 1e-6 rad of it, computed reproducibly).
PRIMARY_R = [[-0.001543, 0.999923, -0.012319], [0.999992, 0.001589, 0.003767],
             [0.003786, -0.012313, -0.999917]]
PRIMARY_T = [-1.0900, -4.7868, 289.0184]
PRIMARY_SIZE = (2664, 2304)
# Secondary camera: "about 45 degrees" (paper §5); no calibration is released. ASSUMED: the same lens
# and sensor as the primary, on the 45 deg line from the sample centre towards +x, behind the +x wall's
# camera slot (the 45 deg line meets the wall at z ~ 173 mm, inside the slot, reference §1.3), at
# 467 mm from the sample centre so that it sits 35 mm outside the wall; image columns along world +y
# like the primary's.
SECONDARY_DISTANCE = 467.0


def _rigid_origin() -> np.ndarray:
    return np.array(SamplePlane().origin)


def _upper_leds():
    pos, nrm, board, row, col, layout = [], [], [], [], [], []
    centre = _rigid_origin()
    for t, (o, f, s) in enumerate(TILES):
        o, f, s = map(np.asarray, (o, f, s))
        slow, fast = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")  # index = 32*slow + fast
        p = o + fast.reshape(-1, 1) * f + slow.reshape(-1, 1) * s
        n = unit3(cross3(f, s))
        if dot3(n, centre - o) < 0:  # orient into the cube, towards the sample
            n = -n
        pos.append(p)
        nrm.append(np.repeat(n[None], len(p), 0))
        board.append(np.full(len(p), t // 2))
        row.append(slow.ravel())
        col.append(32 * (t % 2) + fast.ravel())
        layout += [UPPER_BOARDS[t // 2][2]] * len(p)
    return (np.concatenate(pos), np.concatenate(nrm), np.concatenate(board), np.concatenate(row),
            np.concatenate(col), np.array(layout))


def _bottom_leds():
    r, c = np.meshgrid(np.arange(BOTTOM_GRID), np.arange(BOTTOM_GRID), indexing="ij")
    r, c = r.ravel(), c.ravel()
    half = (BOTTOM_GRID - 1) / 2 * BOTTOM_PITCH
    cx, cy, cz = BOTTOM_CENTRE
    pos = np.stack([cx - half + c * BOTTOM_PITCH, cy + half - r * BOTTOM_PITCH, np.full(len(r), cz)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (len(r), 1))
    return pos, nrm, r, c


def holder_frame() -> HolderFrame:
    """The sample holder: a 150 mm window in a 210 mm square ring, 1.5 mm thick, with 8 ArUco markers
    (20 mm, two per side) centred in its 30 mm band. ASSUMED dimensions: the paper shows an aluminium
    frame with ARTags but gives no drawing."""
    frame = HolderFrame()
    o = np.asarray(SamplePlane().origin)
    band = (frame.inner_size + frame.outer_size) / 4  # distance of the band's centre line from the centre
    centres = [(-45, -band), (45, -band), (band, -45), (band, 45), (45, band), (-45, band),
               (-band, 45), (-band, -45)]
    h = frame.marker_size / 2
    quad = np.array([[-h, h], [h, h], [h, -h], [-h, -h]])  # TL, TR, BR, BL seen from above
    corners = np.array([[[o[0] + x + dx, o[1] + y + dy, o[2] + frame.height] for dx, dy in quad]
                        for x, y in centres])
    return replace(frame, marker_ids=np.arange(len(centres)), marker_corners=corners)


def _cameras() -> dict[str, Camera]:
    primary = Camera("primary", *PRIMARY_SIZE, PRIMARY_K, PRIMARY_DIST, orthonormalise(PRIMARY_R), PRIMARY_T,
                     note="released calibration (intrinsic.yml, extrinsic.yml), half resolution")
    o = _rigid_origin()
    d = SECONDARY_DISTANCE / np.sqrt(2)
    secondary = Camera.look_at("secondary", o + [d, 0.0, d], o, (0.0, 1.0, 0.0), PRIMARY_K, *PRIMARY_SIZE,
                               dist=PRIMARY_DIST, assumed=True,
                               note="ASSUMED: no released calibration; primary's lens at 45 deg on +x")
    return {"primary": primary, "secondary": secondary}


def paper_rig() -> Rig:
    """The full device: 12,288 upper LEDs as released + 4,096 bottom LEDs, two cameras."""
    pos, nrm, board, row, col, layout = _upper_leds()
    bpos, bnrm, brow, bcol = _bottom_leds()
    L_up, L_b = len(pos), len(bpos)
    cross = np.concatenate([
        np.concatenate([layout_pixels(k, row[layout == k], col[layout == k]) for k in
                        dict.fromkeys(layout)]),  # tiles are contiguous per board, in order
        layout_pixels("bottom", brow, bcol)])
    leds = LEDs(
        positions=np.concatenate([pos, bpos]),
        normals=np.concatenate([nrm, bnrm]),
        board=np.concatenate([board, np.full(L_b, len(UPPER_BOARDS))]),
        row=np.concatenate([row, brow]),
        col=np.concatenate([col, bcol]),
        intensity=np.full((L_up + L_b, 3), LED_INTENSITY_W_SR),
        profile=_default_profile(L_up + L_b),
        diffuser_radius=np.full(L_up + L_b, 2.5),
        is_bottom=np.concatenate([np.zeros(L_up, bool), np.ones(L_b, bool)]),
        cross_pixel=cross,
    )
    boards = [Board(n, face, 32, 64) for n, face, _ in UPPER_BOARDS] + [
        Board("bottom", "bottom", BOTTOM_GRID, BOTTOM_GRID)]
    return Rig("paper", leds, boards, _cameras(), SamplePlane(), holder_frame(), BottomBoard(),
               notes="Built from the released layout (reference §1). Bottom board and secondary camera "
                     "are ASSUMED (no released data). LED intensity 0.05 W/sr (assumed), cosine profile.")


def _default_profile(n: int) -> np.ndarray:
    """Cosine profile parameters (twin.optics.emitter): exponent 1 = Lambertian emitter behind its diffuser."""
    p = np.zeros((n, PROFILE_PARAMS), np.float32)
    p[:, 0] = 1.0
    return p


# mini: every 6th LED along both board axes (columns 2, 8, ..., 62; rows 1, 7, ..., 31 -> 66 per upper
# board, 396 upper LEDs) and every 8th of the bottom board (64); images 1/12 of the paper's (222 x 192).
MINI_UPPER_COLS = np.arange(2, 64, 6)
MINI_UPPER_ROWS = np.arange(1, 32, 6)
MINI_BOTTOM = np.arange(3, 64, 8)
MINI_IMAGE_SCALE = 1 / 12


def mini_rig() -> Rig:
    paper = paper_rig()
    leds = paper.leds
    upper = ~leds.is_bottom & np.isin(leds.col, MINI_UPPER_COLS) & np.isin(leds.row, MINI_UPPER_ROWS)
    bottom = leds.is_bottom & np.isin(leds.col, MINI_BOTTOM) & np.isin(leds.row, MINI_BOTTOM)
    cams = {n: c.resized(MINI_IMAGE_SCALE) for n, c in paper.cameras.items()}
    return replace(paper, name="mini", leds=leds.subset(upper | bottom), cameras=cams,
                   notes="The paper rig's geometry with every 6th upper LED and every 8th bottom LED per "
                         "board axis, and images at 1/12 resolution. For CI and demos.")


BUILTIN = {"paper": paper_rig, "mini": mini_rig}


def serves_for(rig: Rig, recorded_digest: str) -> bool:
    """Whether something made for a rig of `rig`'s name with digest `recorded_digest` (a shipped network, the
    default patterns) serves `rig`: it is that rig, or the built-in rig of that name has that digest and
    differs from `rig` only in how the cameras record light (Rig.geometry_digest: a vignetting or colour
    calibration of it)."""
    if recorded_digest == rig.digest():
        return True
    if rig.name not in BUILTIN:
        return False
    builtin = BUILTIN[rig.name]()
    return builtin.digest() == recorded_digest and builtin.geometry_digest() == rig.geometry_digest()

