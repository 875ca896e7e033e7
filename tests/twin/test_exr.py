"""twin.materials.exr: round trips (float bit-exact, half within its rounding), channel order, attributes, errors
and atomic writes."""
from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

import twin.materials.exr as exr
from twin.materials.exr import (ExrError, check_finite, read_exr, read_exr_attributes, read_rgb_exr, write_exr,
                      write_rgb_exr)


def _rand(shape, seed=0, scale=10.0):
    return (np.random.default_rng(seed).standard_normal(shape) * scale).astype(np.float32)


def _no_temp_files(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".")] == []


def test_float32_round_trip_is_bit_exact(tmp_path):
    a = _rand((17, 23, 3))
    a[0, 0] = [np.float32(1e-40), np.float32(3.4e38), -0.0]  # denormal, near max, negative zero
    p = write_rgb_exr(tmp_path / "a.exr", a)
    assert p == tmp_path / "a.exr"
    b = read_rgb_exr(p)
    assert b.dtype == np.float32 and b.shape == (17, 23, 3)
    assert b.tobytes() == a.tobytes()


@pytest.mark.parametrize("compression", ["none", "zip", "piz", "rle"])
def test_lossless_compressions_are_bit_exact(tmp_path, compression):
    a = _rand((8, 12, 3), seed=1)
    b = read_rgb_exr(write_rgb_exr(tmp_path / "c.exr", a, compression=compression))
    assert b.tobytes() == a.tobytes()


def test_half_round_trip(tmp_path):
    a = np.random.default_rng(2).uniform(0.01, 100.0, (16, 16, 3)).astype(np.float32)
    b = read_rgb_exr(write_rgb_exr(tmp_path / "h.exr", a, half=True))
    assert b.dtype == np.float32
    np.testing.assert_array_equal(b, a.astype(np.float16).astype(np.float32))  # exactly half rounding
    rel = np.abs(b - a) / np.abs(a)
    assert rel.max() < 1e-3
    assert rel.max() > 0  # it really went through HALF
    with OpenEXR.File(str(tmp_path / "h.exr"), separate_channels=True) as f:
        assert f.channels()["R"].type() == OpenEXR.HALF
    with OpenEXR.File(str(write_rgb_exr(tmp_path / "f.exr", a)), separate_channels=True) as f:
        assert f.channels()["R"].type() == OpenEXR.FLOAT


def test_half_overflow_is_refused(tmp_path):
    a = np.ones((4, 4, 3), np.float32)
    a[1, 2, 0] = 1e5
    with pytest.raises(ExrError, match=r"channel .R. value 100000 at \(row 1, col 2\) exceeds the half-float range ±65504"):
        write_rgb_exr(tmp_path / "o.exr", a, half=True)
    assert not (tmp_path / "o.exr").exists()


def test_channel_order_is_by_name_not_position(tmp_path):
    h, w = 5, 7
    rgb = np.stack([np.full((h, w), v, np.float32) for v in (0.25, 0.5, 0.75)], axis=-1)
    p = write_rgb_exr(tmp_path / "rgb.exr", rgb)
    got = read_rgb_exr(p)
    np.testing.assert_array_equal(got[0, 0], [0.25, 0.5, 0.75])
    chans = read_exr(p)
    assert list(chans) == ["R", "G", "B"]
    assert (chans["R"][0, 0], chans["G"][0, 0], chans["B"][0, 0]) == (0.25, 0.5, 0.75)
    # independent check with OpenEXR's own merged RGB read: [..., 0] is R
    with OpenEXR.File(str(p)) as f:
        np.testing.assert_array_equal(f.channels()["RGB"].pixels[0, 0], [0.25, 0.5, 0.75])
    # a dict given in B, G, R order still reads back by name
    p2 = write_exr(tmp_path / "bgr.exr", {"B": rgb[..., 2], "G": rgb[..., 1], "R": rgb[..., 0]})
    np.testing.assert_array_equal(read_rgb_exr(p2), rgb)


def test_pixel_layout_rows_and_columns(tmp_path):
    a = np.arange(3 * 4, dtype=np.float32).reshape(3, 4)
    ch = read_exr(write_exr(tmp_path / "l.exr", {"Y": a}))
    np.testing.assert_array_equal(ch["Y"], a)
    assert ch["Y"][2, 1] == 9.0


def test_72_latent_channels(tmp_path):
    rng = np.random.default_rng(3)
    lat = {f"L_{k}": rng.standard_normal((9, 11)).astype(np.float32) for k in range(72)}
    given = dict(lat)
    p = write_exr(tmp_path / "latent.exr", given)
    assert all(isinstance(v, np.ndarray) for v in given.values())  # the caller's dict is not mutated
    got = read_exr(p)
    assert list(got) == [f"L_{k}" for k in range(72)]  # natural order, not L_0, L_1, L_10
    for k, v in lat.items():
        assert got[k].tobytes() == v.tobytes(), k
    sub = read_exr(p, channels=["L_71", "L_3"])
    assert list(sub) == ["L_71", "L_3"]
    assert sub["L_3"].tobytes() == lat["L_3"].tobytes()
    half = read_exr(write_exr(tmp_path / "latent16.exr", lat, half=True))
    for k, v in lat.items():
        np.testing.assert_array_equal(half[k], v.astype(np.float16).astype(np.float32))


def test_mixed_input_dtypes_are_stored_as_float32(tmp_path):
    ch = {"a": np.arange(6, dtype=np.float64).reshape(2, 3) / 3, "b": np.arange(6, dtype=np.int64).reshape(2, 3)}
    got = read_exr(write_exr(tmp_path / "m.exr", ch))
    np.testing.assert_array_equal(got["a"], (np.arange(6) / 3).astype(np.float32).reshape(2, 3))
    np.testing.assert_array_equal(got["b"], np.arange(6, dtype=np.float32).reshape(2, 3))


def test_attributes_round_trip(tmp_path):
    attrs = {"sample": "satin0002", "size_mm": 120.5, "count": 7, "flag": True, "scales": [1.0, 2.5],
             "np_float": np.float64(0.25)}
    p = write_rgb_exr(tmp_path / "a.exr", np.zeros((2, 2, 3)), attributes=attrs)
    got = read_exr_attributes(p)
    assert got == {"sample": "satin0002", "size_mm": 120.5, "count": 7, "flag": 1, "scales": [1.0, 2.5],
                   "np_float": 0.25}
    assert read_exr_attributes(write_rgb_exr(tmp_path / "b.exr", np.zeros((2, 2, 3)))) == {}


@pytest.mark.parametrize("attrs, msg", [
    ({"compression": "zip"}, "reserved by OpenEXR"),
    ({"channels": 1}, "reserved by OpenEXR"),
    ({"x": None}, "unsupported type NoneType"),
    ({"x": {"a": 1}}, "unsupported type dict"),
    ({"x": ["a", 1]}, "a list must hold numbers"),
])
def test_bad_attributes(tmp_path, attrs, msg):
    with pytest.raises(ExrError, match=msg):
        write_rgb_exr(tmp_path / "a.exr", np.zeros((2, 2, 3)), attributes=attrs)


@pytest.mark.parametrize("channels, msg", [
    ({}, "non-empty dict"),
    ({"R": np.zeros((2, 2)), "G": np.zeros((2, 3))}, r"channel 'G' has shape \(2, 3\), but the other channels are \(2, 2\)"),
    ({"R": np.zeros((2, 2, 3))}, r"must be a 2-D \(H, W\) array"),
    ({"R": np.zeros((0, 2))}, r"must be a 2-D \(H, W\) array"),
    ({"": np.zeros((2, 2))}, "invalid channel name"),
    ({"R": np.array([["a", "b"]])}, "expected a real numeric array"),
])
def test_bad_channels_on_write(tmp_path, channels, msg):
    with pytest.raises(ExrError, match=msg):
        write_exr(tmp_path / "w.exr", channels)


def test_write_rgb_needs_three_channels(tmp_path):
    with pytest.raises(ExrError, match=r"expected an \(H, W, 3\) RGB array, got shape \(2, 2, 4\)"):
        write_rgb_exr(tmp_path / "x.exr", np.zeros((2, 2, 4)))


def test_unknown_compression(tmp_path):
    with pytest.raises(ExrError, match="unknown EXR compression 'lzw'"):
        write_rgb_exr(tmp_path / "x.exr", np.zeros((2, 2, 3)), compression="lzw")


def test_read_errors(tmp_path):
    with pytest.raises(ExrError, match=r"nope\.exr: no such file"):
        read_exr(tmp_path / "nope.exr")
    (tmp_path / "d.exr").mkdir()
    with pytest.raises(ExrError, match="not a file"):
        read_exr(tmp_path / "d.exr")
    (tmp_path / "text.exr").write_text("hello, not an image")
    with pytest.raises(ExrError, match=r"text\.exr: not an OpenEXR file"):
        read_exr(tmp_path / "text.exr")
    (tmp_path / "empty.exr").write_bytes(b"")
    with pytest.raises(ExrError, match="not an OpenEXR file"):
        read_exr(tmp_path / "empty.exr")


@pytest.mark.parametrize("keep", [0.02, 0.5, 0.99])
def test_truncated_file(tmp_path, keep):
    p = write_rgb_exr(tmp_path / "full.exr", _rand((64, 64, 3), seed=4))
    data = p.read_bytes()
    t = tmp_path / "trunc.exr"
    t.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ExrError, match=r"trunc\.exr: corrupt or truncated OpenEXR file"):
        read_rgb_exr(t)


def test_missing_channel_and_wrong_size(tmp_path):
    p = write_exr(tmp_path / "rg.exr", {"R": np.zeros((3, 4)), "G": np.ones((3, 4))})
    with pytest.raises(ExrError, match=r"rg\.exr: missing channel\(s\) B; the file has R, G"):
        read_rgb_exr(p)
    p = write_rgb_exr(tmp_path / "s.exr", np.zeros((3, 4, 3)))
    with pytest.raises(ExrError, match=r"s\.exr: image is 3 x 4 \(H x W\); expected 4 x 3"):
        read_rgb_exr(p, shape=(4, 3))
    assert read_rgb_exr(p, shape=(3, 4)).shape == (3, 4, 3)


def test_uint_channel_is_refused(tmp_path):
    p = tmp_path / "u.exr"
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"R": np.zeros((2, 2), np.uint32)}) as f:
        f.write(str(p))
    with pytest.raises(ExrError, match="UINT"):
        read_exr(p)


def test_non_finite_values_are_read_and_check_finite_names_them(tmp_path):
    a = np.ones((4, 5, 3), np.float32)
    a[2, 3, 1] = np.nan
    a[3, 0, 0] = np.inf
    p = write_rgb_exr(tmp_path / "nan.exr", a)
    b = read_rgb_exr(p)
    assert np.isnan(b[2, 3, 1]) and b[3, 0, 0] == np.inf
    with pytest.raises(ExrError, match=r"nan\.exr: non-finite value nan at pixel \(row 2, col 3\), channel "
                                       r"index \(1,\) \(2 non-finite values in all\)"):
        check_finite(str(p), b)
    with pytest.raises(ExrError, match=r"nan\.exr channel G: non-finite value nan at pixel \(row 2, col 3\)"):
        check_finite(f"{p} channel G", read_exr(p)["G"])
    check_finite("ok", np.ones((2, 2)))
    check_finite("ints", np.ones((2, 2), int))


def test_failed_write_keeps_old_file_and_leaves_no_temp(tmp_path, monkeypatch):
    target = write_rgb_exr(tmp_path / "keep.exr", np.full((4, 4, 3), 0.5, np.float32))
    before = target.read_bytes()

    class Boom:
        """Stands in for OpenEXR.File: writes half a file, then fails (disk full, killed writer…)."""

        def __init__(self, header, channels):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def write(self, path):
            with open(path, "wb") as fh:
                fh.write(before[:10])
            raise RuntimeError("disk full")

    real = exr._openexr()

    class FakeModule:
        def __getattr__(self, name):
            return Boom if name == "File" else getattr(real, name)

    monkeypatch.setattr(exr, "_openexr", lambda: FakeModule())
    with pytest.raises(ExrError, match=r"keep\.exr: could not write EXR \(RuntimeError: disk full\)"):
        write_rgb_exr(target, np.zeros((4, 4, 3), np.float32))
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.exr"]
    monkeypatch.undo()
    np.testing.assert_array_equal(read_rgb_exr(target), np.full((4, 4, 3), 0.5, np.float32))


def test_write_creates_parent_folders_and_replaces(tmp_path):
    p = tmp_path / "a" / "b" / "x.exr"
    write_rgb_exr(p, np.zeros((2, 2, 3)))
    write_rgb_exr(p, np.ones((2, 2, 3)))
    np.testing.assert_array_equal(read_rgb_exr(p), np.ones((2, 2, 3), np.float32))
    assert _no_temp_files(p.parent)
