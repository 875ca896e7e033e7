"""`hemicube rig info / export` through hemicube.cli.main."""
from __future__ import annotations

import json

import numpy as np
import pytest

import twin
from hemicube.cli import main

from tests.conftest import assert_rigs_identical


@pytest.fixture
def paper_info(capsys):
    """`hemicube rig info paper --json`, parsed."""
    assert main(["rig", "info", "paper", "--json"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    return json.loads(captured.out)


def test_info_json_led_counts(paper_info):
    info = paper_info
    assert info["name"] == "paper"
    assert info["length_unit"] == "mm"
    assert (info["num_leds"], info["num_upper_leds"], info["num_bottom_leds"]) == (16384, 12288, 4096)
    boards = info["boards"]
    assert len(boards) == 7
    assert [b["leds"] for b in boards] == [2048] * 6 + [4096]
    assert [b["grid"] for b in boards] == [[32, 64]] * 6 + [[64, 64]]
    assert sorted(b["face"] for b in boards) == sorted(["-x", "top", "top", "+x", "-y", "+y", "bottom"])
    assert sum(b["leds"] for b in boards) == info["num_leds"]


def test_info_json_bounding_box(paper_info, paper):
    bb = paper_info["bounding_box"]
    pos = paper.led_positions
    np.testing.assert_allclose(bb["min"], pos.min(0), atol=5e-4)
    np.testing.assert_allclose(bb["max"], pos.max(0), atol=5e-4)
    # the upper LEDs' box is the released one (reference §1.2, within the builder's 0.37 mm); the
    # assumed bottom board extends it downwards only
    np.testing.assert_allclose(bb["max"], [300.12, 363.87, 242.00], atol=1.0)
    np.testing.assert_allclose(bb["min"][:2], [-391.96, -363.05], atol=1.0)
    assert bb["min"][2] < -122.0  # the bottom board is under the sample plane


def test_info_json_cameras(paper_info, paper):
    cams = paper_info["cameras"]
    assert list(cams) == ["primary", "secondary"]
    p = cams["primary"]
    np.testing.assert_allclose(p["centre"], [3.69, 4.66, 289.00], atol=0.01)  # cam_pos.bin
    assert p["resolution"] == [2664, 2304]
    assert (p["fx"], p["fy"], p["cx"], p["cy"]) == (4923.0, 4923.43, 1322.3, 1120.98)
    np.testing.assert_allclose(p["dist"], [0.078406, -0.602699, 0.000278, -0.000606, -1.975753], atol=1e-6)
    assert p["assumed"] is False
    s = cams["secondary"]
    assert s["assumed"] is True
    np.testing.assert_allclose(s["centre"], paper.camera("secondary").centre, atol=1e-4)
    # 45 deg from the sample centre, 467 mm away
    v = np.asarray(s["centre"]) - np.asarray(paper.sample.origin)
    assert np.linalg.norm(v) == pytest.approx(467.0, abs=1e-3)
    assert np.degrees(np.arctan2(v[2], v[0])) == pytest.approx(45.0, abs=1e-3)


def test_info_json_digest_and_sample(paper_info, paper):
    assert paper_info["digest"] == paper.digest()
    assert paper_info["sample"] == {"origin": [0.0, 0.0, -122.0], "normal": [0.0, 0.0, 1.0], "max_size": 150.0}


def test_info_text(capsys):
    assert main(["rig", "info", "mini"]) == 0
    out = capsys.readouterr().out
    assert "rig mini: 460 LEDs (396 upper, 64 bottom), unit mm" in out
    assert out.count(": 66 LEDs") == 6 and ": 64 LEDs" in out
    assert "camera secondary" in out and "(ASSUMED)" in out
    assert "222x192 px" in out


def test_info_nonexistent_exits_2(capsys):
    assert main(["rig", "info", "/nonexistent"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("hemicube: error:")
    assert "/nonexistent" in captured.err
    assert "neither a built-in rig" in captured.err and "paper" in captured.err


def test_info_broken_folder_exits_2(tmp_path, capsys):
    (tmp_path / "rig").mkdir()
    assert main(["rig", "info", str(tmp_path / "rig")]) == 2
    assert "missing rig.toml" in capsys.readouterr().err


def test_info_of_saved_folder_matches_builtin(mini, tmp_path, capsys):
    assert main(["rig", "export", "mini", "-o", str(tmp_path / "m")]) == 0
    assert "460 LEDs" in capsys.readouterr().out
    assert_rigs_identical(mini, twin.load_rig(tmp_path / "m"))
    assert main(["rig", "info", "mini", "--json"]) == 0
    a = json.loads(capsys.readouterr().out)
    assert main(["rig", "info", str(tmp_path / "m"), "--json"]) == 0
    b = json.loads(capsys.readouterr().out)
    assert a == b
    # export refuses to replace without --force
    assert main(["rig", "export", "paper", "-o", str(tmp_path / "m")]) == 2
    assert "exists" in capsys.readouterr().err
    assert twin.load_rig(tmp_path / "m").name == "mini"
    assert main(["rig", "export", "paper", "-o", str(tmp_path / "m"), "--force"]) == 0
    assert twin.load_rig(tmp_path / "m").name == "paper"
