"""`hemicube rig export RIG --gltf FILE` (twin.view.gltf), read back by trimesh as a 3-D tool would: every LED a node
at its position, each camera a node at its pose, in glTF's metres and +Y-up axes; the LEDs instanced (one mesh a
board); an existing file kept unless --force."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import hemicube.cli
import twin
from twin.view.gltf import TO_GLTF, camera_pose, to_gltf

trimesh = pytest.importorskip("trimesh")


def test_the_frame_conversion_is_a_rotation_to_y_up_in_metres():
    assert np.allclose(TO_GLTF @ TO_GLTF.T, np.eye(3)) and np.isclose(np.linalg.det(TO_GLTF), 1.0)
    np.testing.assert_allclose(to_gltf([0.0, 0.0, 1000.0]), [0.0, 1.0, 0.0])  # the sample's normal: +Y
    np.testing.assert_allclose(to_gltf([1000.0, 0.0, 0.0]), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(to_gltf([0.0, 1000.0, 0.0]), [0.0, 0.0, -1.0])


@pytest.mark.parametrize("rig_name, suffix", [("mini", ".glb"), ("mini", ".gltf"), ("paper", ".glb")])
def test_gltf_export_loads_back_with_the_rigs_leds_and_camera_poses(rig_name, suffix, tmp_path, capsys):
    rig = twin.load_rig(rig_name)
    path = tmp_path / f"rig{suffix}"
    assert hemicube.cli.main(["rig", "export", rig_name, "--gltf", str(path)]) == 0
    scene = trimesh.load(str(path))
    leds = sorted(n for n in scene.graph.nodes_geometry if n.startswith("led_"))
    assert len(leds) == rig.num_leds == len(set(leds))
    got = np.array([scene.graph[n][0][:3, 3] for n in leds])  # led_<index>: the rig's order
    np.testing.assert_allclose(got, to_gltf(rig.leds.positions), atol=1e-6)  # glTF stores float32 metres
    for name, cam in rig.cameras.items():
        T = scene.graph[f"camera_{name}"][0]
        np.testing.assert_allclose(T, camera_pose(cam), atol=1e-6)
        # a glTF camera looks along its local -Z: the camera's optical axis, converted
        np.testing.assert_allclose(T[:3, :3] @ [0, 0, -1], TO_GLTF @ cam.optical_axis, atol=1e-6)
        np.testing.assert_allclose(T[:3, 3], to_gltf(cam.centre), atol=1e-6)
    # the primary camera sits above the sample and looks down (-Y)
    assert (scene.graph["camera_primary"][0][:3, :3] @ [0, 0, -1])[1] < -0.9
    assert f"{rig.num_leds} LEDs" in capsys.readouterr().out


def test_the_leds_are_instanced(tmp_path):
    """One mesh a board for the LEDs, not one a node: the paper rig's 16,384 LED nodes point at 7 meshes."""
    rig = twin.load_rig("paper")
    path = tmp_path / "paper.glb"
    hemicube.cli.main(["rig", "export", "paper", "--gltf", str(path)])
    glb = path.read_bytes()
    doc = json.loads(glb[20:20 + struct.unpack_from("<I", glb, 12)[0]])
    led_meshes = {n["mesh"] for n in doc["nodes"] if n.get("name", "").startswith("led_")}
    assert len(led_meshes) == len(rig.boards) and len(doc["meshes"]) <= 2 * len(rig.boards) + len(rig.cameras) + 2


def test_an_existing_file_is_kept_unless_forced(tmp_path, capsys):
    path = tmp_path / "rig.glb"
    path.write_bytes(b"mine")
    assert hemicube.cli.main(["rig", "export", "mini", "--gltf", str(path)]) == 2
    assert "the file exists; --force replaces it" in capsys.readouterr().err and path.read_bytes() == b"mine"
    assert hemicube.cli.main(["rig", "export", "mini", "--gltf", str(path), "--force"]) == 0
    assert path.read_bytes()[:4] == b"glTF"
    assert hemicube.cli.main(["rig", "export", "mini", "--gltf", str(tmp_path / "rig.obj")]) == 2
    assert "name a .glb or a .gltf file" in capsys.readouterr().err
