"""Import the released OpenSVBRDF device configuration (reference §1.1) as a rig.

Reads `lights.bin` (float32 (2, N, 3): positions in mm, then OUTWARD unit normals, which are flipped
here to point into the cube, reference §1.2), `intrinsic.yml` and `extrinsic.yml` (OpenCV YAML, read
without OpenCV), `cam_pos.bin` (checked against -R^T t), and `visualize_config_torch.bin` (the preview
map, int32 header (128, 192) then N (col, row) pairs). `mask.npy` is a pickled object array and is
never loaded: unpickling can run arbitrary code, and the data is unused legacy (reference §1.7).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.rig.builtin import UPPER_BOARDS
from twin.rig.camera import Camera
from twin.rig.cross import CROSS_SHAPE
from twin.rig.opencv_yaml import OpenCVYamlError, read_opencv_yaml
from twin.rig.model import PROFILE_PARAMS, Board, LEDs, Rig, RigError, SamplePlane

REQUIRED = ("lights.bin", "cam_pos.bin", "intrinsic.yml", "extrinsic.yml")
CAMERA_CENTRE_TOLERANCE_MM = 0.01  # cam_pos.bin vs -R^T t: equal to float32 precision in the release


def import_opensvbrdf(directory: str | Path) -> Rig:
    d = Path(directory)
    missing = [f for f in REQUIRED if not (d / f).is_file()]
    if missing:
        raise RigError(f"{d}: not an OpenSVBRDF configuration folder, missing {missing}")
    raw = np.fromfile(d / "lights.bin", dtype="<f4")
    if raw.size % 6:
        raise RigError(f"{d / 'lights.bin'}: {raw.size} floats is not (2, N, 3)")
    lights = raw.reshape(2, -1, 3)
    n = lights.shape[1]
    if n != 12 * 1024:
        raise RigError(f"{d / 'lights.bin'}: {n} LEDs; the released layout has 12,288 (6 boards x 64 x 32)")
    positions = lights[0].astype(np.float64)
    normals = -lights[1].astype(np.float64)  # stored outward; the twin's normals point into the cube

    idx = np.arange(n)
    tile, slow, fast = idx // 1024, (idx % 1024) // 32, idx % 32
    board, row, col = tile // 2, slow, 32 * (tile % 2) + fast
    cross = _read_preview(d / "visualize_config_torch.bin", n) if (d / "visualize_config_torch.bin").is_file() \
        else _formula_cross(board, row, col)

    try:
        intr = read_opencv_yaml(d / "intrinsic.yml")
        extr = read_opencv_yaml(d / "extrinsic.yml")
        K, dist = intr["camera_matrix"], intr["distortion_coefficients"].ravel()
        width, height = int(intr["image_width"]), int(intr["image_height"])
        R, t = extr["rmat"].astype(np.float64), extr["tvec"].astype(np.float64).ravel()
        U, _, Vt = np.linalg.svd(R)  # float32 rmat -> nearest rotation (|R R^T - I| ~ 2e-8 as released)
        R = U @ Vt
    except (OpenCVYamlError, KeyError) as e:
        raise RigError(f"{d}: cannot read the camera calibration ({e})") from None
    camera = Camera("primary", width, height, K, dist, R, t,
                    note=f"imported from {d.name}/intrinsic.yml, extrinsic.yml")
    cam_pos = np.fromfile(d / "cam_pos.bin", dtype="<f4").astype(np.float64)
    if cam_pos.shape != (3,) or np.linalg.norm(cam_pos - camera.centre) > CAMERA_CENTRE_TOLERANCE_MM:
        raise RigError(f"{d}: cam_pos.bin {cam_pos} disagrees with the extrinsics' centre {camera.centre}")

    profile = np.zeros((n, PROFILE_PARAMS), np.float32)
    profile[:, 0] = 1.0
    skipped = [f for f in ("mask.npy", "color_tensor.bin") if (d / f).exists()]
    leds = LEDs(positions=positions, normals=normals, board=board, row=row, col=col,
                intensity=np.ones((n, 3)), profile=profile, diffuser_radius=np.zeros(n),
                is_bottom=np.zeros(n, bool), cross_pixel=cross)
    return Rig("opensvbrdf", leds, [Board(nm, face, 32, 64) for nm, face, _ in UPPER_BOARDS], {"primary": camera},
               SamplePlane(), frame=None, bottom=None,
               notes=f"Imported from the released OpenSVBRDF configuration ({d.name}). Upper LEDs and the "
                     f"primary camera only; no bottom board, secondary camera or holder frame are released. "
                     f"Not read: {skipped or 'nothing'} (mask.npy is pickled and unused; color_tensor.bin is "
                     f"unused by the released pipeline).")


def _read_preview(path: Path, n: int) -> np.ndarray:
    raw = np.fromfile(path, dtype="<i4")
    if raw.size != 2 + 2 * n or tuple(raw[:2]) != CROSS_SHAPE:
        raise RigError(f"{path}: expected header {CROSS_SHAPE} and {n} (col, row) pairs")
    return raw[2:].reshape(n, 2)


def _formula_cross(board, row, col):
    from twin.rig.cross import layout_pixels

    keys = np.array([UPPER_BOARDS[b][2] for b in range(len(UPPER_BOARDS))])[board]
    out = np.zeros((len(board), 2), np.int64)
    for k in np.unique(keys):
        sel = keys == k
        out[sel] = layout_pixels(k, row[sel], col[sel])
    return out
