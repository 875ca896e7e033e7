"""Importing the released OpenSVBRDF configuration, and the `paper` rig against the released geometry."""
from __future__ import annotations

import numpy as np
import pytest

import twin
from twin import RigError
from twin.rig.opensvbrdf_import import import_opensvbrdf

from tests.conftest import NUM_UPPER, assert_rigs_identical, copy_reference, pickle_bomb_array


# --- item 1: import ------------------------------------------------------------------------------
def test_import_counts_bbox_camera(imported, released_cam_pos):
    assert imported.num_leds == NUM_UPPER == 12_288
    assert not imported.is_bottom.any()
    pos = imported.led_positions
    np.testing.assert_allclose(pos.min(0), [-391.96, -363.05, -96.17], atol=0.01)
    np.testing.assert_allclose(pos.max(0), [300.12, 363.87, 242.00], atol=0.01)
    cam = imported.primary
    np.testing.assert_allclose(cam.centre, [3.69, 4.66, 289.00], atol=0.01)
    np.testing.assert_allclose(cam.centre, released_cam_pos, atol=0.01)
    assert cam.K[0, 0] == 4923.0
    assert (cam.width, cam.height) == (2664, 2304)
    # every board has its full 64 x 32 grid
    assert np.bincount(imported.leds.board).tolist() == [2048] * 6


def test_import_positions_and_normals_are_lights_bin_exactly(imported, released_lights):
    pos32, nrm32 = released_lights
    pos, nrm = imported.led_positions, imported.led_normals
    assert pos.dtype == np.float64 and nrm.dtype == np.float64
    # mm -> mm: the float32 values, widened to float64, unchanged
    assert np.array_equal(pos, pos32.astype(np.float64))
    assert np.array_equal(nrm, -nrm32.astype(np.float64))
    # and the flipped normals really point towards the sample (reference §1.2: stored outward)
    to_sample = np.asarray(imported.sample.origin) - pos
    assert np.all(np.einsum("ij,ij->i", nrm, to_sample) > 0)


def test_import_index_layout(imported):
    """l = 1024*tile + 32*slow + fast; board = tile // 2, board col = 32*(tile % 2) + fast, row = slow."""
    leds = imported.leds
    for l in (0, 31, 32, 1023, 1024, 2047, 4959, 6143, 8192, 12287):
        tile, slow, fast = l // 1024, (l % 1024) // 32, l % 32
        assert (leds.board[l], leds.row[l], leds.col[l]) == (tile // 2, slow, 32 * (tile % 2) + fast)


def test_import_cross_equals_released_preview(imported, released_preview):
    assert imported.leds.cross_pixel.shape == released_preview.shape
    assert np.array_equal(imported.leds.cross_pixel.astype(np.int64), released_preview.astype(np.int64))


def test_cli_import_matches_library_import(reference_dir, imported, tmp_path, capsys):
    from hemicube.cli import main

    out = tmp_path / "rig"
    assert main(["rig", "import-opensvbrdf", str(reference_dir), "-o", str(out)]) == 0
    assert "12288" in capsys.readouterr().out
    loaded = twin.load_rig(out)
    assert_rigs_identical(imported, loaded)
    assert loaded.num_leds == 12_288
    np.testing.assert_allclose(loaded.primary.centre, [3.69, 4.66, 289.00], atol=0.01)
    assert loaded.primary.K[0, 0] == 4923.0
    # a second import onto the same folder is refused (exit 2) unless --force, and leaves it unchanged
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert main(["rig", "import-opensvbrdf", str(reference_dir), "-o", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert main(["rig", "import-opensvbrdf", str(reference_dir), "-o", str(out), "--force"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["leds.npz", "rig.toml"]
    assert (out / "rig.toml").read_bytes() == before["rig.toml"]  # (npz members carry a zip timestamp)
    assert twin.load_rig(out).digest() == imported.digest()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig"]  # no temp or old folder left


def test_import_never_unpickles_mask(reference_dir, tmp_path):
    folder = copy_reference(reference_dir, tmp_path / "lightstage")
    marker = tmp_path / "UNPICKLED"
    np.save(folder / "mask.npy", pickle_bomb_array(marker), allow_pickle=True)

    rig = import_opensvbrdf(folder)
    assert rig.num_leds == 12_288
    assert not marker.exists(), "import_opensvbrdf unpickled mask.npy"

    # control: the planted file really is dangerous when unpickled, so the check above means something
    np.load(folder / "mask.npy", allow_pickle=True)
    assert marker.exists()


@pytest.mark.parametrize("name", ["lights.bin", "cam_pos.bin", "intrinsic.yml", "extrinsic.yml"])
def test_import_missing_file_is_named(reference_dir, tmp_path, name):
    folder = copy_reference(reference_dir, tmp_path / "lightstage")
    (folder / name).unlink()
    with pytest.raises(RigError, match=name.replace(".", r"\.")):
        import_opensvbrdf(folder)


def test_import_rejects_truncated_lights_bin(reference_dir, tmp_path):
    folder = copy_reference(reference_dir, tmp_path / "lightstage")
    data = (folder / "lights.bin").read_bytes()
    (folder / "lights.bin").write_bytes(data[: 2 * 3 * 4 * 100])  # 100 LEDs instead of 12,288
    with pytest.raises(RigError, match="lights.bin"):
        import_opensvbrdf(folder)


def test_import_rejects_inconsistent_cam_pos(reference_dir, tmp_path):
    folder = copy_reference(reference_dir, tmp_path / "lightstage")
    np.array([3.69, 4.66, 300.0], "<f4").tofile(folder / "cam_pos.bin")  # 11 mm off
    with pytest.raises(RigError, match="cam_pos.bin"):
        import_opensvbrdf(folder)


def test_import_cli_missing_lights_bin_exits_2(reference_dir, tmp_path, capsys):
    from hemicube.cli import main

    folder = copy_reference(reference_dir, tmp_path / "lightstage")
    (folder / "lights.bin").unlink()
    out = tmp_path / "rig"
    assert main(["rig", "import-opensvbrdf", str(folder), "-o", str(out)]) == 2
    assert "lights.bin" in capsys.readouterr().err
    assert not out.exists()


# --- item 2: the built-in paper rig against the released geometry ---------------------------------
def test_paper_upper_leds_match_lights_bin(paper, released_lights):
    pos32, nrm32 = released_lights
    upper = ~paper.is_bottom
    assert np.array_equal(np.flatnonzero(upper), np.arange(NUM_UPPER))  # upper LEDs first, same order
    dist = np.linalg.norm(paper.led_positions[:NUM_UPPER] - pos32.astype(np.float64), axis=1)
    assert dist.max() < 1.0, f"LED {dist.argmax()} is {dist.max():.3f} mm from lights.bin"
    expected = -nrm32.astype(np.float64)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    cos = np.clip(np.einsum("ij,ij->i", paper.led_normals[:NUM_UPPER], expected), -1, 1)
    angle = np.degrees(np.arccos(cos))
    assert angle.max() < 0.1, f"LED {angle.argmax()} normal is {angle.max():.4f} deg off"


def test_paper_board_grid_matches_import(paper, imported):
    """Same (board, row, col) for every upper LED as the released index formula gives."""
    for k in ("board", "row", "col"):
        assert np.array_equal(getattr(paper.leds, k)[:NUM_UPPER], getattr(imported.leds, k)), k


def test_paper_cross_matches_released_preview(paper, released_preview):
    assert np.array_equal(paper.leds.cross_pixel[:NUM_UPPER].astype(np.int64), released_preview)


def test_paper_primary_camera_matches_released_calibration(paper, imported):
    a, b = paper.primary, imported.primary
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.K, b.K, rtol=1e-9)
    np.testing.assert_allclose(a.dist, b.dist, atol=1e-6)  # builtin rounds to 6 decimals
    np.testing.assert_allclose(a.R, b.R, atol=1e-6)
    np.testing.assert_allclose(a.centre, b.centre, atol=0.01)
