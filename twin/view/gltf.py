"""The rig as a glTF 2.0 scene (`hemicube rig export RIG --gltf OUT.glb`), for CAD and 3-D tools: the LED boards as
quads, every LED a node of its board's one shared LED mesh (instanced: 16,384 nodes, 7 meshes on the paper rig), each
camera a node posed as a glTF camera with its frustum down to the sample plane as its mesh, the sample square and the
holder frame. Node names: `board_<name>`, `led_<index>` (the rig's LED order), `camera_<name>`, `sample`, `frame`.

Units and axes. The rig is in millimetres in its right-handed world, +z out of the sample (twin/rig/units.py); glTF is
in metres, right-handed, +Y up (glTF 2.0 §3.4). A point goes over as

    (x, y, z)_glTF = (x, z, -y)_rig / 1000          (TO_GLTF, a rotation of -90° about x, and mm -> m)

so the sample's normal is +Y and the rig's +x stays +x. A glTF camera looks along its local -Z with +Y up; an OpenCV
camera along +z with +y down: a camera node's rotation is TO_GLTF · R^T · diag(1, -1, -1) (R world -> camera, OpenCV)
and its translation the camera's centre, converted.
"""
from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from twin.view.rig_view import BOARD_COLOURS, CAMERA_COLOURS, board_rectangle, camera_frustum, led_pitch

# rig world (mm, +z up) -> glTF (m, +Y up): a proper rotation, then the unit
TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
MM = 1e-3
OPENCV_TO_GLTF_CAMERA = np.diag([1.0, -1.0, -1.0])  # +z forward, +y down -> -Z forward, +Y up


def to_gltf(points_mm: np.ndarray) -> np.ndarray:
    """Rig points (..., 3) in mm -> glTF points in metres (module docstring)."""
    return np.asarray(points_mm, np.float64) @ TO_GLTF.T * MM


def camera_pose(cam) -> np.ndarray:
    """(4, 4) the camera node's transform in glTF's frame: its rotation maps the glTF camera's local axes (-Z
    forward, +Y up) to the scene's, its translation is the camera's centre."""
    T = np.eye(4)
    T[:3, :3] = TO_GLTF @ cam.R.T @ OPENCV_TO_GLTF_CAMERA
    T[:3, 3] = to_gltf(cam.centre)
    return T


def _colour(hex_colour: str) -> list[int]:
    return [int(hex_colour[k:k + 2], 16) for k in (1, 3, 5)] + [255]


def _quad(corners_mm, colour):
    """A double-sided quad (both windings: a board is seen from inside and outside the cube)."""
    faces = [[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]]
    return _trimesh().Trimesh(to_gltf(corners_mm), faces, face_colors=_colour(colour), process=False)


def _trimesh():
    try:
        import trimesh
    except ImportError:
        raise ValueError("the glTF export needs trimesh: pip install 'hemicube-twin[view]'") from None
    return trimesh


def rig_scene(rig):
    """A trimesh.Scene of the rig in glTF's frame (module docstring)."""
    trimesh = _trimesh()

    scene = trimesh.Scene()
    for b, board in enumerate(rig.boards):
        colour = BOARD_COLOURS[b % len(BOARD_COLOURS)]
        corners, _ = board_rectangle(rig, b)
        scene.add_geometry(_quad(corners, colour), node_name=f"board_{board.name}", geom_name=f"board_{board.name}")
        sel = np.flatnonzero(rig.leds.board == b)
        if sel.size == 0:
            continue
        # an LED's marker: a third of its board's pitch (rig_view's), at least 1 mm across
        led = trimesh.creation.icosphere(subdivisions=0, radius=max(0.3 * led_pitch(rig, sel), 1.0) * MM / 2)
        led.visual.face_colors = _colour(colour)
        geom = f"led_{board.name}"
        # one mesh, a node per LED added to the graph itself: scene.add_geometry per node re-derives the scene's
        # caches each time, which for the paper rig's 16,384 LEDs is most of the export
        scene.geometry[geom] = led
        for i in sel:
            T = np.eye(4)
            T[:3, 3] = to_gltf(rig.leds.positions[i])
            scene.graph.update(frame_to=f"led_{i:05d}", frame_from=scene.graph.base_frame, matrix=T, geometry=geom)
    for k, (name, cam) in enumerate(rig.cameras.items()):
        centre, quad = camera_frustum(cam, rig.sample)
        T = camera_pose(cam)
        local = (to_gltf(np.vstack([centre[None], quad])) - T[:3, 3]) @ T[:3, :3]  # in the node's own frame
        faces = [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]]
        frustum = trimesh.Trimesh(local, faces + [f[::-1] for f in faces], process=False,
                                  face_colors=_colour(CAMERA_COLOURS[k % len(CAMERA_COLOURS)]))
        scene.add_geometry(frustum, node_name=f"camera_{name}", geom_name=f"camera_{name}", transform=T)
    scene.add_geometry(_quad(rig.sample.corners(), "#e8dcc0"), node_name="sample", geom_name="sample")
    mesh = rig.frame.mesh(rig.sample) if rig.frame is not None else None
    if mesh is not None:
        verts, tris = mesh
        scene.add_geometry(trimesh.Trimesh(to_gltf(verts), tris, face_colors=_colour("#b8bcc4"), process=False),
                           node_name="frame", geom_name="frame")
    return scene


def export_gltf(rig, path) -> Path:
    """Write the rig's scene (rig_scene) to `path` atomically: binary glTF (.glb) or, for .gltf, JSON with its buffers
    embedded. Returns the path."""
    from twin.atomic import write_bytes_atomic

    path = Path(path)
    kind = {".glb": "glb", ".gltf": "gltf"}.get(path.suffix.lower())
    if kind is None:
        raise ValueError(f"--gltf {path}: name a .glb or a .gltf file")
    glb = _instanced(rig_scene(rig).export(file_type="glb"))
    if kind == "gltf":  # one JSON file, its buffer embedded as a data URI
        doc, binary = _glb_parts(glb)
        doc["buffers"] = [{"byteLength": len(binary),
                           "uri": "data:application/octet-stream;base64," + base64.b64encode(binary).decode()}]
        return write_bytes_atomic(path, json.dumps(doc, separators=(",", ":")).encode())
    return write_bytes_atomic(path, glb)


def _glb_parts(glb: bytes) -> tuple[dict, bytes]:
    """The JSON document and the binary chunk of a GLB file (glTF 2.0 §4.4)."""
    n = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20:20 + n])
    rest = glb[20 + n:]
    return doc, rest[8:8 + struct.unpack_from("<I", rest, 0)[0]] if rest else b""


def _instanced(glb: bytes) -> bytes:
    """The GLB with its nodes that draw the same data pointing at one mesh: trimesh writes a mesh per node (their
    data already shared), which for 16,384 LEDs is 16,384 identical mesh entries instead of one per board."""
    doc, binary = _glb_parts(glb)
    meshes = doc.get("meshes", [])
    first, remap = {}, []
    for mesh in meshes:
        remap.append(first.setdefault(json.dumps(mesh["primitives"], sort_keys=True), len(first)))
    doc["meshes"] = [meshes[remap.index(i)] for i in range(len(first))]
    for node in doc.get("nodes", []):
        if "mesh" in node:
            node["mesh"] = remap[node["mesh"]]
    body = json.dumps(doc, separators=(",", ":")).encode()
    body += b" " * (-len(body) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<I4s", len(body), b"JSON") + body + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks
