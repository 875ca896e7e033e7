"""The virtual capture: plan, session folder, checksums, determinism, and resume after a hard kill.

One uninterrupted capture (A, with its raw frames: --raw) and one that is SIGKILLed mid-way and re-run (B, the
default: no raw frames), both with seed 1: B must end byte-identical to A less A's raw frames (determinism,
including across a resume; keeping the raw frames changes nothing else) without rewriting the photos it had
finished before the kill.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import twin
import hemicube.cli
from twin.capture.plan import DEFAULT_FRAMES, CaptureError, bracket_frames, exposure_frames, frames_per_photo
from twin.capture.runner import capture, capture_bytes
from twin.capture.session import CaptureSession, verify

ARGS = ["capture", "--backend", "sim", "--rig", "mini", "--sample", "ramps", "--seed", "1", "--no-progress"]


@pytest.fixture(scope="module")
def run_a(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "A"
    assert hemicube.cli.main(ARGS + ["--raw", "-o", str(out)]) == 0
    return out


def _manifest(d):
    return json.loads((Path(d) / "manifest.json").read_text())


def _raw(files) -> dict:
    return {k: v for k, v in files.items() if k.startswith("raw/")}


def test_session_folder(run_a):
    from twin.camera.bayer import unpack_bayer_rg12p
    from twin.materials.exr import read_rgb_exr
    from twin.materials.samples import read_maps

    m = _manifest(run_a)
    rig = twin.load_rig("mini")
    assert m["rig_digest"] == rig.digest() and m["seed"] == 1 and m["backend"] == "sim"
    assert m["frames_per_exposure"] == DEFAULT_FRAMES == 4
    assert "raw_frames" not in m  # kept, as in every folder made before raw frames were optional
    assert verify(run_a) == []
    # 64 learned x 2 views + 64 linear lights + bottom + 2 uniform + empty-board bottom
    assert len(m["plan"]) == 128 + 64 + 1 + 2 + 1 == len(m["photos"])
    names = sorted(p.name for p in Path(run_a).glob("img*_cam*.exr"))
    assert names[0] == "img00000_cam00.exr" and "img00063_cam01.exr" in names and "img00130_cam00.exr" in names
    assert len(names) == 196
    cam = rig.camera("primary")
    hdr = read_rgb_exr(Path(run_a) / "img00129_cam00.exr")  # uniform light
    assert hdr.shape == (cam.height, cam.width, 3) and np.all(np.isfinite(hdr)) and hdr.max() > 0
    rec = m["photos"]["img00129_cam00"]
    ts = rec["exposures_s"]  # the bracket's 3 exposures ascending, the shortest taken twice as often
    assert exposure_frames(DEFAULT_FRAMES) == [8, 4, 4] and len(ts) == frames_per_photo(DEFAULT_FRAMES) == 16
    assert ts == sorted(ts) and ts == bracket_frames([ts[0], ts[8], ts[12]], DEFAULT_FRAMES)
    raw = unpack_bayer_rg12p((Path(run_a) / rec["files"][0]).read_bytes(), cam.height, cam.width)
    assert raw.dtype == np.uint16 and raw.max() <= 4095 and raw.max() > raw.min()
    raws = CaptureSession.open(run_a).raw_frames(129, 0)  # the reader's, in bracket order
    assert len(raws) == 16 and np.array_equal(raws[0], raw) and all(r.shape == (cam.height, cam.width) for r in raws)
    gt = np.load(Path(run_a) / "ground_truth" / "pixel_texel_cam00.npy")
    assert gt.shape == (cam.height, cam.width, 2) and np.isnan(gt).any() and np.isfinite(gt).any()
    maps = read_maps(Path(run_a) / "ground_truth" / "maps")
    assert maps.rho_d.shape[0] == 128
    # transparency: bottom-lit photo over the empty-board photo is ~1 on the board, < 1 on the sample
    t = read_rgb_exr(Path(run_a) / "img00128_cam00.exr").mean(-1) / np.maximum(
        read_rgb_exr(Path(run_a) / "img00130_cam00.exr").mean(-1), 1e-9)
    on = np.isfinite(gt[..., 0])
    assert np.median(t[on]) < 0.9


def test_kill_and_resume_is_byte_identical(run_a, tmp_path):
    out = tmp_path / "B"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "hemicube.cli", *ARGS, "-o", str(out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    done_before = {}
    while time.time() < deadline:
        try:
            done_before = _manifest(out)["photos"]
        except (OSError, ValueError, KeyError):
            done_before = {}
        if len(done_before) >= 40:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 40 <= len(done_before) < 196, "the kill must land mid-capture"
    before = _manifest(out)
    assert verify(out) == []  # whatever the manifest lists is complete: atomic writes
    mtimes = {rel: (out / rel).stat().st_mtime_ns for rel in before["files"]}

    assert hemicube.cli.main(ARGS + ["-o", str(out)]) == 0
    after = _manifest(out)
    assert verify(out) == [] and len(after["photos"]) == 196
    for rec in before["photos"].values():  # finished photos were verified, not redone
        for rel in rec["files"]:
            assert (out / rel).stat().st_mtime_ns == mtimes[rel], rel
    a = _manifest(run_a)
    # same seed: identical bytes (sha256), A's raw frames aside; B (the default) wrote none and says so
    assert len(_raw(a["files"])) == 196 * frames_per_photo(DEFAULT_FRAMES) and _raw(after["files"]) == {}
    assert after["files"] == {k: v for k, v in a["files"].items() if k not in _raw(a["files"])}
    assert not (out / "raw").exists() and after["raw_frames"] is False
    assert after["photos"] == {stem: {**rec, "files": [f for f in rec["files"] if not f.startswith("raw/")]}
                               for stem, rec in a["photos"].items()}


@pytest.mark.slow
def test_raw_compare_finds_no_difference_in_a_capture_against_itself(run_a, tmp_path):
    """twin.capture.raw_compare, the cross-machine comparison of raw frames (docs/performance.md): a capture against
    itself gives no differing row (a tampered frame cannot be read at all: its checksum fails)."""
    from twin.capture import raw_compare

    raw_compare.digest(run_a, tmp_path / "rows.npz")
    raw_compare.rows(run_a, tmp_path / "rows.npz", tmp_path / "diff.npz")
    rep = raw_compare.report(run_a, tmp_path / "diff.npz")
    assert rep["frames"] == rep["frames_compared"] == rep["identical_frames"] > 500
    assert rep["differing_pixels"] == 0 and rep["missing_frames"] == []


def test_capture_bytes_from_the_plan_are_the_photos_files(run_a):
    """twin.capture.runner.capture_bytes, computed from the plan without rendering, is what the photos' files hold,
    to the byte: the HDR photos, and the raw frames with --raw (docs/performance.md gives the paper rig's)."""
    exr = sum(p.stat().st_size for p in Path(run_a).glob("img*_cam*.exr"))
    raw = sum(p.stat().st_size for p in (Path(run_a) / "raw").iterdir())
    rig = twin.load_rig("mini")
    assert capture_bytes(rig, raw=True) == {"hdr": exr, "raw": raw, "total": exr + raw}
    assert capture_bytes(rig) == {"hdr": exr, "raw": 0, "total": exr}
    assert capture_bytes(rig, raw=True, frames=1)["raw"] * 4 == raw  # 4 raw frames a photo against 16
    # the default capture's goal is 15 GB, the rest of its folder (ground truth, rig, patterns) about 0.1 GB
    assert capture_bytes(twin.load_rig("paper"))["total"] < 14.5e9


def test_refuses_other_capture_and_repairs_corruption(run_a, tmp_path, capsys):
    out = tmp_path / "C"
    shutil.copytree(run_a, out)
    with pytest.raises(CaptureError, match="different capture"):
        capture(twin.load_rig("mini"), "ramps", out, seed=2, progress=False, raw=True)
    # resumed without the --raw it was made with: one line naming the option, nothing written
    before = _manifest(out)
    assert hemicube.cli.main(ARGS + ["-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(f"{out} holds a different capture (raw_frames differ: it was made with "
                                             "--raw); resume it with --raw or choose another folder"), err
    assert _manifest(out) == before
    victim = out / "img00070_cam00.exr"
    victim.write_bytes(b"garbage")
    assert verify(out) == ["img00070_cam00.exr"]
    capture(twin.load_rig("mini"), "ramps", out, seed=1, progress=False, raw=True)
    assert verify(out) == [] and _manifest(out)["files"] == _manifest(run_a)["files"]


def test_capture_errors(tmp_path):
    rig = twin.load_rig("mini")
    with pytest.raises(CaptureError, match="unknown backend"):
        capture(rig, "ramps", tmp_path / "x", backend="basler", progress=False)
    with pytest.raises(ValueError):
        capture(rig, "no_such_sample", tmp_path / "y", progress=False)
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_frames_per_exposure(run_a, tmp_path):
    """The default capture takes the longer exposures of each photo's bracket DEFAULT_FRAMES times and the shortest
    twice as often (the HDR merge averages them; tests/test_hdr.py checks the statistics), against `hemicube capture
    --frames 1`: the same metered bracket, each exposure's frames in a row, each frame its own file and its own noise.
    A one-frame folder's header lacks `frames_per_exposure` (as every folder made before frame averaging) and both
    list their `exposure_frames` (which folders made before the shortest's repeat lack), so such folders refuse each
    other as another capture; counts that the frame streams cannot hold are refused before a folder is made. The
    one-frame folder is a default one, without raw frames: each photo lists its HDR photo alone, and a resume with
    --raw is refused."""
    out = tmp_path / "x1"
    assert hemicube.cli.main(ARGS + ["--frames", "1", "-o", str(out)]) == 0
    m, m1 = _manifest(run_a), _manifest(out)
    assert m["frames_per_exposure"] == DEFAULT_FRAMES and "frames_per_exposure" not in m1 and verify(out) == []
    assert m["exposure_frames"] == exposure_frames(DEFAULT_FRAMES) and m1["exposure_frames"] == [2, 1, 1]
    n = DEFAULT_FRAMES
    for stem in ("img00000_cam00", "img00070_cam00", "img00129_cam01"):
        rec, rec1 = m["photos"][stem], m1["photos"][stem]
        bracket = rec1["exposures_s"][1:]  # [t0, t0, t1, t2]: the shortest twice (t1 = t2 where clamped at 1 s)
        assert bracket == sorted(bracket) and rec1["exposures_s"] == bracket_frames(bracket, 1)
        assert rec["exposures_s"] == bracket_frames(bracket, n)
        raws = [f for f in rec["files"] if f.startswith("raw/")]
        assert len(raws) == frames_per_photo(n) == len(set(rec["frames"]))
        assert rec1["files"] == [f"{stem}.exr"] and len(rec1["frames"]) == frames_per_photo(1)
        first, second = ((run_a / f).read_bytes() for f in raws[:2])
        assert first != second  # two frames of one exposure: two noise draws
    with pytest.raises(CaptureError, match="different capture"):
        capture(twin.load_rig("mini"), "ramps", out, seed=1, progress=False)
    with pytest.raises(CaptureError, match=r"\(raw_frames differ: it was made without --raw\); resume it without "
                                           "--raw or choose another folder$"):
        capture(twin.load_rig("mini"), "ramps", out, seed=1, progress=False, frames=1, raw=True)
    for bad in (0, 5, 2.0):
        with pytest.raises(CaptureError, match=r"frames per exposure must be an integer in \[1, 4\]"):
            capture(twin.load_rig("mini"), "ramps", tmp_path / "bad", seed=1, progress=False, frames=bad)
    assert not (tmp_path / "bad").exists()
    # the reader's count (the fit weighs the photos by it, reconstruction.pipeline); a bad one names the folder
    assert CaptureSession.open(run_a).frames_per_exposure == DEFAULT_FRAMES
    assert CaptureSession.open(out).frames_per_exposure == 1
    s = CaptureSession.open(out)
    s.header["frames_per_exposure"] = 0
    with pytest.raises(CaptureError, match=r"x1: manifest's frames_per_exposure 0: frames per exposure must be"):
        s.frames_per_exposure  # noqa: B018 (the property raises)


def test_validate_refuses_a_bad_frame_count_in_one_line(tmp_path, capsys):
    """`hemicube validate --frames 0` (one sample, or the suite): one line, before any check runs or folder is made."""
    for args in (["validate"], ["validate", "--suite", "satin"]):
        assert hemicube.cli.main(args + ["--frames", "0", "-o", str(tmp_path / "v")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "frames per exposure must be an integer in [1, 4]" in err
    assert not (tmp_path / "v").exists()
