"""Pattern files (twin.capture.patterns): exact round trips, 8-bit quantisation, clear errors, atomic writes."""
from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from twin.capture.patterns import FORMAT_NAME, FORMAT_VERSION, PatternError, PatternSet, load_patterns, save_patterns

from tests.conftest import pickle_bomb_array

NAME_CHARS = st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00")


def _valid_arrays(K=2, L=5):
    rng = np.random.default_rng(0)
    return dict(format=np.str_(FORMAT_NAME), version=np.int32(FORMAT_VERSION),
                levels=rng.integers(0, 256, (K, L, 3), dtype=np.uint8),
                names=np.array([f"p{i}" for i in range(K)]), rig=np.str_("mini"), note=np.str_("made by hand"))


def _write(path, arrays, allow_pickle=False):
    with open(path, "wb") as f:
        np.savez(f, allow_pickle=allow_pickle, **arrays)
    return path


# --- round trip -------------------------------------------------------------------------------------
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(levels=hnp.arrays(np.uint8, hnp.array_shapes(min_dims=3, max_dims=3, min_side=0, max_side=6).map(
           lambda s: (s[0], s[1], 3))),
       rig=st.text(NAME_CHARS, max_size=12), note=st.text(NAME_CHARS, max_size=40), data=st.data())
def test_round_trip_is_exact(tmp_path, levels, rig, note, data):
    names = data.draw(st.lists(st.text(NAME_CHARS, min_size=1, max_size=10), min_size=levels.shape[0],
                               max_size=levels.shape[0], unique=True))
    ps = PatternSet(levels, tuple(names), rig, note)
    path = save_patterns(ps, tmp_path / "p.npz")
    back = load_patterns(path)
    assert back.levels.dtype == np.uint8
    assert back.levels.shape == levels.shape
    assert np.array_equal(back.levels, levels)
    assert back.names == tuple(names)
    assert back.rig == rig
    assert back.note == note
    assert (back.num_patterns, back.num_leds) == levels.shape[:2]


def test_round_trip_mini_sized(mini, tmp_path):
    rng = np.random.default_rng(5)
    w = rng.uniform(0, 1, (4, mini.num_leds, 3))
    ps = PatternSet.from_weights(w, ["learned_00+", "learned_00-", "line_12", "full_on"], mini.name, "test set")
    back = load_patterns(save_patterns(ps, tmp_path / "set.npz"))
    assert np.array_equal(back.levels, ps.levels)
    assert back.names == ("learned_00+", "learned_00-", "line_12", "full_on")
    assert (back.rig, back.note) == ("mini", "test set")
    back.check_rig(mini)  # no error


def test_names_with_nul_are_not_silently_changed(tmp_path):
    """NumPy's fixed-width unicode arrays drop trailing NULs: 'a\\0' would load as 'a'. Such names must be
    refused up front or survive the round trip; they must not come back different (or as duplicates)."""
    try:
        ps = PatternSet(np.zeros((2, 1, 3), np.uint8), ("a\x00", "a"), "r")
        path = save_patterns(ps, tmp_path / "p.npz")
    except PatternError:
        return  # refused up front: fine
    back = load_patterns(path)
    assert back.names == ("a\x00", "a")


def test_pattern_levels_are_immutable():
    ps = PatternSet(np.zeros((1, 2, 3), np.uint8), ("a",), "r")
    with pytest.raises(ValueError):
        ps.levels[0, 0, 0] = 1


# --- quantisation ------------------------------------------------------------------------------------
def test_from_weights_fixed_values():
    w = np.array([[0.0, 1.0, 0.5, 1 / 255, 254 / 255, 0.25, 0.75, 0.001, 0.999]])
    ps = PatternSet.from_weights(w, ["a"], "r")
    assert ps.levels.dtype == np.uint8
    assert ps.levels.shape == (1, 9, 3)  # (K, L) weights -> the same level on all three channels
    assert ps.levels[0, :, 0].tolist() == [0, 255, 128, 1, 254, 64, 191, 0, 255]
    assert np.array_equal(ps.levels[..., 0], ps.levels[..., 1])
    assert np.array_equal(ps.levels[..., 0], ps.levels[..., 2])
    # 0 and 1 are exact through weights
    assert ps.weights[0, 0, 0] == 0.0 and ps.weights[0, 1, 0] == 1.0
    assert ps.weights.dtype == np.float32


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float64, (2, 7, 3), elements=st.floats(0.0, 1.0)))
def test_from_weights_rounds_to_nearest(w):
    ps = PatternSet.from_weights(w, ["a", "b"], "r")
    levels = ps.levels.astype(np.float64)
    assert np.all(np.abs(levels - 255.0 * w) <= 0.5 + 1e-9)
    # exact multiples of 1/255 come back exactly
    k = np.rint(w * 255)
    assert np.array_equal(PatternSet.from_weights(k / 255, ["a", "b"], "r").levels, k.astype(np.uint8))
    # monotone: a larger weight never gets a smaller level
    order = np.argsort(w, axis=None, kind="stable")
    assert np.all(np.diff(ps.levels.ravel()[order].astype(int)) >= 0)


def test_from_weights_of_an_empty_set():
    """PatternSet accepts K = 0 frames (and save/load round-trips it); from_weights must too."""
    ps = PatternSet.from_weights(np.zeros((0, 5)), [], "r")
    assert ps.levels.shape == (0, 5, 3)


# --- errors -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad, pattern", [
    (1.0 + 1e-9, r"must lie in \[0, 1\]"),
    (-0.01, r"must lie in \[0, 1\].*negative light"),
    (2.0, r"got \[0, 2\]"),
    (np.nan, r"NaN or Inf"),
    (np.inf, r"NaN or Inf"),
])
def test_from_weights_rejects(bad, pattern):
    w = np.zeros((1, 4, 3))
    w[0, 2, 1] = bad
    with pytest.raises(PatternError, match=pattern):
        PatternSet.from_weights(w, ["a"], "r")


@pytest.mark.parametrize("levels, names, pattern", [
    (np.zeros((2, 5), np.uint8), ("a", "b"), r"shape \(K, L, 3\), got \(2, 5\)"),
    (np.zeros((2, 5, 4), np.uint8), ("a", "b"), r"shape \(K, L, 3\), got \(2, 5, 4\)"),
    (np.zeros((5, 3), np.uint8), ("a",), r"shape \(K, L, 3\)"),
    (np.zeros((2, 5, 3), np.float32), ("a", "b"), r"must be uint8 drive levels, got float32"),
    (np.zeros((2, 5, 3), np.uint16), ("a", "b"), r"must be uint8 drive levels, got uint16"),
    (np.zeros((2, 5, 3), np.int64), ("a", "b"), r"must be uint8 drive levels, got int64"),
    (np.zeros((2, 5, 3), np.uint8), ("a",), r"1 pattern names for 2 frames"),
    (np.zeros((2, 5, 3), np.uint8), ("a", "a"), r"names must be unique"),
])
def test_pattern_set_rejects(levels, names, pattern):
    with pytest.raises(PatternError, match=pattern):
        PatternSet(levels, names, "r")


def test_from_weights_rejects_wrong_shape():
    with pytest.raises(PatternError, match=r"shape \(K, L, 3\)"):
        PatternSet.from_weights(np.zeros((2, 5, 2)), ["a", "b"], "r")
    with pytest.raises(PatternError, match=r"shape \(K, L, 3\)"):
        PatternSet.from_weights(np.zeros(5), ["a"], "r")


def test_check_rig_led_count(mini, paper):
    ps = PatternSet(np.zeros((1, mini.num_leds, 3), np.uint8), ("a",), "mini")
    ps.check_rig(mini)
    with pytest.raises(PatternError, match=r"460 LEDs per frame but rig 'paper' has 16384"):
        ps.check_rig(paper)


@pytest.mark.parametrize("change, pattern", [
    (lambda a: a | {"format": np.str_("hemicube-rig")}, r"not a hemicube-patterns file"),
    (lambda a: {k: v for k, v in a.items() if k != "format"}, r"not a hemicube-patterns file"),
    (lambda a: a | {"version": np.int32(2)}, r"unknown pattern format version 2"),
    (lambda a: {k: v for k, v in a.items() if k != "version"}, r"version"),
    (lambda a: {k: v for k, v in a.items() if k != "levels"}, r"missing \['levels'\]"),
    (lambda a: a | {"levels": a["levels"].astype(np.float32)}, r"must be uint8"),
    (lambda a: a | {"levels": a["levels"][0]}, r"shape \(K, L, 3\)"),
    (lambda a: a | {"names": a["names"][:1]}, r"1 pattern names for 2 frames"),
])
def test_load_rejects_bad_files(tmp_path, change, pattern):
    path = _write(tmp_path / "bad.npz", change(_valid_arrays()))
    with pytest.raises(PatternError, match=pattern) as info:
        load_patterns(path)
    assert str(path) in str(info.value)  # says which file


def test_load_rejects_non_npz(tmp_path):
    with pytest.raises(PatternError, match="no such pattern file"):
        load_patterns(tmp_path / "missing.npz")
    p = tmp_path / "text.npz"
    p.write_text("levels = 1\n")
    with pytest.raises(PatternError, match="not a readable pattern file"):
        load_patterns(p)


def test_load_rejects_plain_npy(tmp_path):
    p = tmp_path / "levels.npz"
    with open(p, "wb") as f:
        np.save(f, np.zeros((1, 2, 3), np.uint8))  # a bare .npy array is not a pattern file
    with pytest.raises(PatternError, match="not a hemicube-patterns file"):
        load_patterns(p)


@pytest.mark.parametrize("key", ["levels", "names", "format", "note"])
def test_pickled_object_is_refused_not_unpickled(tmp_path, key):
    marker = tmp_path / "UNPICKLED"
    arrays = _valid_arrays()
    arrays[key] = pickle_bomb_array(marker)
    path = _write(tmp_path / "evil.npz", arrays, allow_pickle=True)
    with pytest.raises(PatternError, match="not a readable pattern file"):
        load_patterns(path)
    assert not marker.exists(), f"load_patterns unpickled {key}"
    with np.load(path, allow_pickle=True) as z:  # control: the file is a real threat
        z[key]
    assert marker.exists()


# --- atomic writes -------------------------------------------------------------------------------------
@pytest.fixture
def existing(tmp_path):
    old = PatternSet(np.full((1, 3, 3), 7, np.uint8), ("old",), "mini", "the old set")
    path = save_patterns(old, tmp_path / "set.npz")
    return path, path.read_bytes()


def _failing_write_bytes(real):
    def write_bytes(self, data):
        real(self, data[: len(data) // 2])  # half the file reaches the disk
        raise OSError("simulated failure (disk full)")
    return write_bytes


def test_failed_write_leaves_old_file(tmp_path, existing, monkeypatch):
    path, before = existing
    new = PatternSet(np.zeros((2, 3, 3), np.uint8), ("a", "b"), "mini")
    monkeypatch.setattr(pathlib.Path, "write_bytes", _failing_write_bytes(pathlib.Path.write_bytes))
    with pytest.raises(OSError, match="simulated"):
        save_patterns(new, path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set.npz"]  # no temp file left
    assert load_patterns(path).names == ("old",)


def test_failed_rename_leaves_old_file(tmp_path, existing, monkeypatch):
    path, before = existing

    def fail(*a, **k):
        raise OSError("simulated failure (rename)")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="simulated"):
        save_patterns(PatternSet(np.zeros((1, 3, 3), np.uint8), ("a",), "mini"), path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set.npz"]


def test_failed_first_write_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(pathlib.Path, "write_bytes", _failing_write_bytes(pathlib.Path.write_bytes))
    with pytest.raises(OSError, match="simulated"):
        save_patterns(PatternSet(np.zeros((1, 3, 3), np.uint8), ("a",), "mini"), tmp_path / "sub" / "p.npz")
    monkeypatch.undo()
    assert list((tmp_path / "sub").iterdir()) == []


def test_successful_overwrite(tmp_path, existing):
    path, before = existing
    new = PatternSet(np.full((2, 3, 3), 200, np.uint8), ("a", "b"), "mini", "new")
    save_patterns(new, path)
    assert path.read_bytes() != before
    back = load_patterns(path)
    assert back.names == ("a", "b") and np.all(back.levels == 200)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set.npz"]


def test_atomic_files_get_ordinary_permissions(tmp_path):
    """Atomic writes go through mkstemp (mode 0600); the final file must have the umask's ordinary mode."""
    import os
    import stat

    from twin.atomic import write_bytes_atomic

    p = write_bytes_atomic(tmp_path / "x.bin", b"abc")
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask
