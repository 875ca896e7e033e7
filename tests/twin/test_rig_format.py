"""The rig folder format: exact round trips, length units, one clear error per bad input, atomic saves."""
from __future__ import annotations

import os
import pathlib
import tempfile
import tomllib
from dataclasses import replace

import numpy as np
import pytest
import tomli_w
from hypothesis import given, settings
from hypothesis import strategies as st

import twin
from twin import RigError
from twin.rig.format import load_rig_dir

from tests.conftest import assert_rigs_identical, pickle_bomb_array


# --- helpers --------------------------------------------------------------------------------------
@pytest.fixture
def mini_dir(mini, tmp_path) -> pathlib.Path:
    """A freshly saved, valid mini rig folder to break."""
    return twin.save_rig(mini, tmp_path / "rig")


def read_toml(d) -> dict:
    return tomllib.loads((d / "rig.toml").read_text())


def write_toml(d, doc) -> None:
    (d / "rig.toml").write_text(tomli_w.dumps(doc))


def read_npz(path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def write_npz(path, arrays, allow_pickle=False) -> None:
    with open(path, "wb") as f:
        np.savez(f, allow_pickle=allow_pickle, **arrays)


def edit_leds(d, **changes) -> None:
    arrays = read_npz(d / "leds.npz")
    for k, fn in changes.items():
        arrays[k] = fn(arrays[k].copy())
    write_npz(d / "leds.npz", arrays)


def edit_camera(d, name="primary", **changes) -> None:
    doc = read_toml(d)
    cam = next(c for c in doc["cameras"] if c["name"] == name)
    for k, fn in changes.items():
        cam[k] = fn(cam[k])
    write_toml(d, doc)


def add_camera_key(d, key, value) -> None:
    doc = read_toml(d)
    doc["cameras"][0][key] = value
    write_toml(d, doc)


def snapshot(folder) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def listing(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# --- item 4: round trips ---------------------------------------------------------------------------
def test_round_trip_paper(paper, tmp_path):
    out = twin.save_rig(paper, tmp_path / "paper")
    assert listing(out) == ["frame.npz", "leds.npz", "rig.toml"]
    back = twin.load_rig(out)
    assert back is not paper
    assert_rigs_identical(paper, back)


def test_round_trip_mini(mini, tmp_path):
    back = twin.load_rig(twin.save_rig(mini, tmp_path / "mini"))
    assert_rigs_identical(mini, back)
    # and a second generation is still identical
    again = twin.load_rig(twin.save_rig(back, tmp_path / "mini2"))
    assert_rigs_identical(mini, again)


def test_round_trip_imported(imported, tmp_path):
    out = twin.save_rig(imported, tmp_path / "imp")
    assert listing(out) == ["leds.npz", "rig.toml"]  # no holder frame in the release
    assert_rigs_identical(imported, twin.load_rig(out))


def test_saved_arrays_keep_their_dtypes(mini, mini_dir):
    from twin.rig.model import LEDs

    arrays = read_npz(mini_dir / "leds.npz")
    assert set(arrays) == set(LEDs.ARRAYS)
    for k, (dtype, tail) in LEDs.ARRAYS.items():
        assert arrays[k].dtype == np.dtype(dtype), k
        assert arrays[k].shape == (mini.num_leds, *tail), k


def test_digest_changes_with_content(mini):
    pos = mini.led_positions.copy()
    pos[0, 0] = np.nextafter(pos[0, 0], np.inf)  # one ulp
    moved = replace(mini, leds=replace(mini.leds, positions=pos))
    assert moved.digest() != mini.digest()
    assert replace(mini, notes="other").digest() != mini.digest()
    assert len(mini.digest()) == 64 and int(mini.digest(), 16) >= 0


@settings(max_examples=15, deadline=None)
@given(jitter=st.lists(st.floats(-0.4, 0.4, allow_nan=False), min_size=3, max_size=3),
       led=st.integers(0, 459),
       dt=st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3))
def test_round_trip_is_bit_exact_for_arbitrary_floats(mini, jitter, led, dt):
    """Any float64 (not just 'nice' decimals) survives save -> load: npz keeps the bits, TOML uses repr."""
    pos = mini.led_positions.copy()
    pos[led] += jitter
    cams = dict(mini.cameras)
    cams["primary"] = replace(cams["primary"], t=cams["primary"].t + np.asarray(dt))
    rig = replace(mini, leds=replace(mini.leds, positions=pos), cameras=cams)
    with tempfile.TemporaryDirectory() as d:
        back = twin.load_rig(twin.save_rig(rig, pathlib.Path(d) / "r"))
    assert_rigs_identical(rig, back)


def test_length_unit_metres_loads_to_the_same_mm(mini, mini_dir):
    doc = read_toml(mini_dir)
    doc["length_unit"] = "m"
    doc["sample"]["origin"] = [v * 1e-3 for v in doc["sample"]["origin"]]
    doc["sample"]["max_size"] *= 1e-3
    for k in ("inner_size", "outer_size", "height", "marker_size"):
        doc["frame"][k] *= 1e-3
    doc["bottom"]["acrylic_thickness"] *= 1e-3
    for c in doc["cameras"]:
        c["t"] = [v * 1e-3 for v in c["t"]]
    write_toml(mini_dir, doc)
    edit_leds(mini_dir, positions=lambda a: a * 1e-3, diffuser_radius=lambda a: a * np.float32(1e-3))
    frame = read_npz(mini_dir / "frame.npz")
    frame["marker_corners"] = frame["marker_corners"] * 1e-3
    write_npz(mini_dir / "frame.npz", frame)

    back = twin.load_rig(mini_dir)
    assert back.length_unit == "mm"
    np.testing.assert_allclose(back.led_positions, mini.led_positions, rtol=1e-12)
    assert np.array_equal(back.led_normals, mini.led_normals)  # unitless: untouched
    np.testing.assert_allclose(back.leds.diffuser_radius, mini.leds.diffuser_radius, rtol=1e-6)
    np.testing.assert_allclose(back.sample.origin, mini.sample.origin, rtol=1e-12)
    assert back.sample.max_size == pytest.approx(mini.sample.max_size, rel=1e-12)
    assert back.frame.inner_size == pytest.approx(mini.frame.inner_size, rel=1e-12)
    assert back.bottom.acrylic_thickness == pytest.approx(mini.bottom.acrylic_thickness, rel=1e-12)
    np.testing.assert_allclose(back.frame.marker_corners, mini.frame.marker_corners, rtol=1e-12)
    for n in mini.cameras:
        np.testing.assert_allclose(back.cameras[n].t, mini.cameras[n].t, rtol=1e-12)
        np.testing.assert_allclose(back.cameras[n].centre, mini.cameras[n].centre, rtol=1e-12, atol=1e-9)
        assert np.array_equal(back.cameras[n].K, mini.cameras[n].K)  # pixels: untouched


# --- item 3: one clear error per bad input ----------------------------------------------------------
BAD_CASES = {
    # name: (how to break the folder, regex the RigError message must match)
    "positions (L,2)": (lambda d: edit_leds(d, positions=lambda a: a[:, :2]),
                        r"leds\.positions: expected shape \(L, 3\) got \(460, 2\)"),
    "normals (L,)": (lambda d: edit_leds(d, normals=lambda a: a[:, 0]),
                     r"leds\.normals: expected shape \(L, 3\)"),
    "board (L,2)": (lambda d: edit_leds(d, board=lambda a: np.stack([a, a], 1)),
                    r"leds\.board: expected shape \(L\) got \(460, 2\)"),
    "row too short": (lambda d: edit_leds(d, row=lambda a: a[:-1]),
                      r"leds\.row: has 459 entries but leds\.positions has 460"),
    "NaN position": (lambda d: edit_leds(d, positions=lambda a: (a.__setitem__((7, 1), np.nan), a)[1]),
                     r"leds\.positions: NaN or Inf at LED\(s\) \[7\]"),
    "Inf position": (lambda d: edit_leds(d, positions=lambda a: (a.__setitem__((3, 2), -np.inf), a)[1]),
                     r"leds\.positions: NaN or Inf at LED\(s\) \[3\]"),
    "NaN in camera K": (lambda d: edit_camera(d, K=lambda K: [[float("nan"), *K[0][1:]], K[1], K[2]]),
                        r"camera 'primary': K contains NaN or Inf"),
    "Inf in camera K": (lambda d: edit_camera(d, "secondary", K=lambda K: [K[0], [0.0, float("inf"), K[1][2]], K[2]]),
                        r"camera 'secondary': K contains NaN or Inf"),
    "non-unit normal": (lambda d: edit_leds(d, normals=lambda a: (a.__setitem__(5, a[5] * 1.01), a)[1]),
                        r"leds\.normals must be unit vectors: LED 5 has length 1\.01"),
    "flipped normal": (lambda d: edit_leds(d, normals=lambda a: (a.__setitem__(11, -a[11]), a)[1]),
                       r"LED 11 points away from the sample"),
    "duplicate LEDs": (lambda d: edit_leds(d, positions=lambda a: (a.__setitem__(9, a[8] + [0.3, 0.4, 0.0]), a)[1]),
                       r"duplicate LEDs: LED 8 and LED 9 are closer than 1(\.0)? mm"),
    "camera turned away": (lambda d: edit_camera(d, R=lambda R: (np.diag([1.0, -1.0, -1.0]) @ np.array(R)).tolist(),
                                                 t=lambda t: (np.diag([1.0, -1.0, -1.0]) @ np.array(t)).tolist()),
                           r"camera 'primary' cannot see the sample: the sample plane is behind it"),
    "camera moved away": (lambda d: edit_camera(d, t=lambda t: [t[0] + 300.0, t[1], t[2]]),
                          r"camera 'primary' cannot see the whole 150 mm sample"),
    "camera R not a rotation": (lambda d: edit_camera(d, R=lambda R: (2 * np.array(R)).tolist()),
                                r"camera 'primary': R is not a rotation"),
    "unknown version": (lambda d: write_toml(d, read_toml(d) | {"version": 99}),
                        r"unknown rig format version 99"),
    "wrong format name": (lambda d: write_toml(d, read_toml(d) | {"format": "something-else"}),
                          r"format must be 'hemicube-rig', got 'something-else'"),
    "unknown length unit": (lambda d: write_toml(d, read_toml(d) | {"length_unit": "inch"}),
                            r"length_unit must be one of \['m', 'mm'\], got 'inch'"),
    "missing rig.toml": (lambda d: (d / "rig.toml").unlink(), r"missing rig\.toml"),
    "missing leds.npz": (lambda d: (d / "leds.npz").unlink(), r"missing leds\.npz"),
    "missing frame.npz": (lambda d: (d / "frame.npz").unlink(), r"missing frame\.npz"),
    "invalid TOML": (lambda d: (d / "rig.toml").write_text((d / "rig.toml").read_text() + "\n[[[ not toml\n"),
                     r"rig\.toml: not valid TOML"),
    "missing [sample]": (lambda d: write_toml(d, {k: v for k, v in read_toml(d).items() if k != "sample"}),
                         r"missing \[sample\] table"),
    "two cameras with one name": (lambda d: write_toml(d, read_toml(d) | {
        "cameras": [read_toml(d)["cameras"][0]] * 2}), r"two cameras are named 'primary'"),
    "unknown camera key": (lambda d: add_camera_key(d, "focal", 1.0),
                           r"malformed rig description \(TypeError: .*focal"),
    "LED normals outward, as released": (lambda d: edit_leds(d, normals=lambda a: -a),
                                         r"LED 0 points away from the sample .*460 LED\(s\) affected"),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_rig_folder_gives_its_own_error(mini_dir, case):
    breaker, pattern = BAD_CASES[case]
    breaker(mini_dir)
    with pytest.raises(RigError, match=pattern) as info:
        twin.load_rig(mini_dir)
    assert str(mini_dir) in str(info.value)  # says where


def test_each_bad_case_has_a_distinct_message(mini, tmp_path):
    messages = set()
    for i, (breaker, _) in enumerate(BAD_CASES.values()):
        d = twin.save_rig(mini, tmp_path / f"r{i}")
        breaker(d)
        with pytest.raises(RigError) as info:
            load_rig_dir(d)
        messages.add(str(info.value).replace(str(d), "<dir>"))
    assert len(messages) == len(BAD_CASES)


def test_not_a_folder(tmp_path):
    with pytest.raises(RigError, match="neither a built-in rig"):
        twin.load_rig(tmp_path / "nope")
    with pytest.raises(RigError, match="no such directory"):
        load_rig_dir(tmp_path / "nope")


def test_missing_array_in_leds_npz_is_named_not_blamed_on_pickle(mini_dir):
    arrays = read_npz(mini_dir / "leds.npz")
    del arrays["profile"]
    write_npz(mini_dir / "leds.npz", arrays)
    with pytest.raises(RigError, match=r"missing array\(s\) \['profile'\]") as info:
        twin.load_rig(mini_dir)
    # the file holds no pickled data: the message must not claim it was refused for that
    assert "pickle" not in str(info.value)


def _write_npy(path, a):
    with open(path, "wb") as f:
        np.save(f, a)


@pytest.mark.parametrize("name", ["leds.npz", "frame.npz"])
def test_plain_npy_instead_of_npz_is_a_rig_error(mini_dir, name):
    _write_npy(mini_dir / name, np.zeros((460, 3)))
    with pytest.raises(RigError, match=name.replace(".", "[.]")):
        twin.load_rig(mini_dir)


def test_garbage_leds_npz_is_refused(mini_dir):
    (mini_dir / "leds.npz").write_bytes(b"\x00garbage" * 64)
    with pytest.raises(RigError, match=r"leds\.npz"):
        twin.load_rig(mini_dir)


@pytest.mark.parametrize("npz, key", [("leds.npz", "positions"), ("leds.npz", "normals"),
                                      ("frame.npz", "marker_ids")])
def test_pickled_object_array_is_refused_not_unpickled(mini_dir, tmp_path, npz, key):
    marker = tmp_path / "UNPICKLED"
    arrays = read_npz(mini_dir / npz)
    arrays[key] = pickle_bomb_array(marker)
    write_npz(mini_dir / npz, arrays, allow_pickle=True)
    with pytest.raises(RigError, match=rf"{npz.replace('.', '[.]')}: refused to read .*never contain pickled"):
        twin.load_rig(mini_dir)
    assert not marker.exists(), "the rig loader unpickled an object array"
    # control: the planted array does run code when unpickled
    with np.load(mini_dir / npz, allow_pickle=True) as z:
        z[key]
    assert marker.exists()


# --- item 3: nothing is half-written ----------------------------------------------------------------
def test_save_onto_existing_folder_needs_overwrite(mini, paper, mini_dir):
    before = snapshot(mini_dir)
    with pytest.raises(FileExistsError, match="overwrite"):
        twin.save_rig(paper, mini_dir)
    assert snapshot(mini_dir) == before
    assert listing(mini_dir.parent) == ["rig"]  # no temp folder left


def test_overwrite_replaces_the_folder(mini, mini_dir):
    frameless = replace(mini, name="frameless", frame=None)
    twin.save_rig(frameless, mini_dir, overwrite=True)
    assert listing(mini_dir) == ["leds.npz", "rig.toml"]  # the old frame.npz is gone, not merged
    assert_rigs_identical(frameless, twin.load_rig(mini_dir))
    assert listing(mini_dir.parent) == ["rig"]


def _fail_on_call(n, real):
    calls = {"n": 0}

    def wrapper(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == n:
            raise OSError("simulated failure (disk full)")
        return real(*args, **kwargs)

    return wrapper


def _half_write_then_fail(real):
    calls = {"n": 0}

    def write_bytes(self, data):
        calls["n"] += 1
        if calls["n"] == 2:
            real(self, data[: len(data) // 2])
            raise OSError("simulated failure (disk full)")
        return real(self, data)

    return write_bytes


@pytest.mark.parametrize("how", ["np.savez", "Path.write_bytes"])
def test_failed_save_leaves_nothing(mini, tmp_path, monkeypatch, how):
    if how == "np.savez":
        monkeypatch.setattr(np, "savez", _fail_on_call(2, np.savez))
    else:
        monkeypatch.setattr(pathlib.Path, "write_bytes", _half_write_then_fail(pathlib.Path.write_bytes))
    with pytest.raises(OSError, match="simulated"):
        twin.save_rig(mini, tmp_path / "rig")
    monkeypatch.undo()
    assert listing(tmp_path) == []  # neither the target nor a temp folder


@pytest.mark.parametrize("how", ["np.savez", "Path.write_bytes"])
def test_failed_overwrite_keeps_the_old_folder(paper, mini, mini_dir, monkeypatch, how):
    before = snapshot(mini_dir)
    if how == "np.savez":
        monkeypatch.setattr(np, "savez", _fail_on_call(2, np.savez))
    else:
        monkeypatch.setattr(pathlib.Path, "write_bytes", _half_write_then_fail(pathlib.Path.write_bytes))
    with pytest.raises(OSError, match="simulated"):
        twin.save_rig(paper, mini_dir, overwrite=True)
    monkeypatch.undo()
    assert snapshot(mini_dir) == before
    assert listing(mini_dir.parent) == ["rig"]
    assert_rigs_identical(mini, twin.load_rig(mini_dir))


def test_failed_swap_on_overwrite_keeps_the_old_folder(paper, mini, mini_dir, monkeypatch):
    """If moving the new folder into place fails, the old folder must be put back, not left hidden
    under a temporary name with the target gone."""
    before = snapshot(mini_dir)
    monkeypatch.setattr(os, "rename", _fail_on_call(2, os.rename))  # 1: old aside, 2: new into place
    with pytest.raises(OSError, match="simulated"):
        twin.save_rig(paper, mini_dir, overwrite=True)
    monkeypatch.undo()
    assert mini_dir.is_dir(), f"the old rig folder vanished; the parent holds {listing(mini_dir.parent)}"
    assert snapshot(mini_dir) == before
    assert listing(mini_dir.parent) == ["rig"]


def test_saved_folder_is_world_readable(mini_dir):
    assert (mini_dir.stat().st_mode & 0o755) == 0o755
