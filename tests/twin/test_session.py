"""The capture session folder's one owner (twin.capture.session): reads verify checksums and name the bad
file, a second writer is refused at once, and a capture that fails before its first photo leaves nothing."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

import twin
from hemicube.cli import main
from twin.capture.plan import CaptureError, Photo
from twin.capture.runner import capture
from twin.capture.session import CaptureSession, photo_stem


@pytest.fixture
def capture_copy(validate_dir, tmp_path):
    out = tmp_path / "capture"
    shutil.copytree(validate_dir / "capture", out, ignore=shutil.ignore_patterns(".lock"))
    return out


@pytest.mark.slow
def test_reader_gives_what_the_capture_wrote(validate_dir, mini):
    s = CaptureSession.open(validate_dir / "capture")
    assert s.verify() == [] and s.rig_digest == mini.digest() and s.sample == "ramps"
    assert s.rig().digest() == mini.digest()
    img = s.photo(129, 1)
    cam = mini.camera(list(mini.cameras)[1])
    assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.float32
    assert s.photos[photo_stem(129, 1)]["raw_shape"] == [cam.height, cam.width]
    assert s.patterns().num_patterns >= 131 - 64 and s.has_ground_truth
    assert s.ground_truth_maps().resolution == 128 and s.pixel_texel(0).shape[-1] == 2


@pytest.mark.slow
def test_rewritten_photo_stops_reconstruct_naming_it(capture_copy, tmp_path, capsys):
    """A valid EXR with other values in place of a photo: `hemicube reconstruct` exits non-zero, naming it."""
    from twin.materials.exr import read_rgb_exr, write_rgb_exr

    victim = capture_copy / f"{photo_stem(70, 0)}.exr"
    write_rgb_exr(victim, read_rgb_exr(victim) * np.float32(1.01))
    with pytest.raises(CaptureError, match=victim.name):
        CaptureSession.open(capture_copy).photo(70, 0)
    rc = main(["reconstruct", str(capture_copy), "-o", str(tmp_path / "recon"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc != 0 and victim.name in err and "checksum" in err
    assert not (tmp_path / "recon").exists()  # nothing half-written


def test_a_second_writer_is_refused_at_once(tmp_path):
    out = tmp_path / "busy"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    first = subprocess.Popen([sys.executable, "-m", "hemicube.cli", "capture", "--rig", "mini", "--sample", "ramps",
                              "--seed", "3", "--no-progress", "-o", str(out)], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while not (out / "manifest.json").exists() and time.time() < deadline and first.poll() is None:
            time.sleep(0.05)
        assert first.poll() is None, "the first capture must still be running"
        t0 = time.perf_counter()
        with pytest.raises(CaptureError, match=f"in use by another capture \\(pid {first.pid} on "):
            capture(twin.load_rig("mini"), "ramps", out, seed=3, progress=False)
        assert time.perf_counter() - t0 < 10  # refused at once, not after running to the end
    finally:
        first.kill()
        first.wait()
    # the lock goes with its process: a killed writer's folder resumes (verified here by taking the lock)
    CaptureSession.create(out, CaptureSession.open(out).header).close()


def test_bad_device_leaves_no_folder(tmp_path, capsys):
    out = tmp_path / "x"
    rc = main(["capture", "--rig", "mini", "--device", "cuda:7", "--no-progress", "-o", str(out)])
    assert rc == 2 and "unknown device 'cuda:7'" in capsys.readouterr().err
    assert not out.exists()


def test_failure_before_the_first_photo_removes_only_a_new_folder(tmp_path):
    header = {"format": "hemicube-capture", "version": 1, "rig": "mini", "rig_digest": "x"}
    with pytest.raises(RuntimeError):
        with CaptureSession.create(tmp_path / "new", header):
            raise RuntimeError("the backend failed")
    assert not (tmp_path / "new").exists()
    with CaptureSession.create(tmp_path / "kept", header) as s:  # one photo taken, then a failure
        s.write_photo(Photo(0, "primary", 0, "p", "sample"), [np.zeros((4, 4), np.uint16)],
                      np.zeros((4, 4, 3), np.float32), {"exposures_s": [1e-3]})
    with pytest.raises(RuntimeError):
        with CaptureSession.create(tmp_path / "kept", header):
            raise RuntimeError("killed later")
    assert CaptureSession.open(tmp_path / "kept").verify() == []


def test_resume_removes_what_a_killed_writer_left(tmp_path):
    header = {"format": "hemicube-capture", "version": 1, "rig": "mini", "rig_digest": "x"}
    with CaptureSession.create(tmp_path / "c", header) as s:
        s.write_photo(Photo(0, "primary", 0, "p", "sample"), [np.zeros((4, 4), np.uint16)],
                      np.zeros((4, 4, 3), np.float32), {"exposures_s": [1e-3]})
    half = [tmp_path / "c" / ".img00001_cam00.exr.k2j4h5g6.exr",
            tmp_path / "c" / "raw" / ".img00001_cam00_e0.BayerRG12p.a1b2c3d4.BayerRG12p"]
    for p in half:  # twin.atomic's temporary files, as a SIGKILL mid-write leaves them
        p.write_bytes(b"half")
    (tmp_path / "c" / ".rig.q1w2e3r4").mkdir()
    CaptureSession.create(tmp_path / "c", header).close()
    assert list((tmp_path / "c").rglob(".*")) == []  # the lock went with its owner
    assert CaptureSession.open(tmp_path / "c").verify() == []


def test_raw_frames_are_written_only_where_the_capture_keeps_them(tmp_path):
    """A header without `raw_frames` (every folder made before raw frames were optional) keeps them; one with
    `raw_frames: false` (a capture without --raw) lists the HDR photo alone, the raw frames' shape still recorded.
    Both verify, and a photo of either counts as taken on a resume (photo_done)."""
    header = {"format": "hemicube-capture", "version": 1, "rig": "mini", "rig_digest": "x"}
    photo = Photo(0, "primary", 0, "p", "sample")
    raws = [np.full((4, 6), 7, np.uint16), np.full((4, 6), 9, np.uint16)]
    for name, extra, files in (("kept", {}, ["raw/img00000_cam00_e0.BayerRG12p", "raw/img00000_cam00_e1.BayerRG12p",
                                                 "img00000_cam00.exr"]),
                               ("none", {"raw_frames": False}, ["img00000_cam00.exr"])):
        with CaptureSession.create(tmp_path / name, {**header, **extra}) as s:
            s.write_photo(photo, raws if not extra else None, np.ones((4, 6, 3), np.float32),
                          {"exposures_s": [1e-3, 8e-3]})
        s = CaptureSession.open(tmp_path / name)
        assert s.photos["img00000_cam00"]["files"] == files and s.photos["img00000_cam00"]["raw_shape"] == [4, 6]
        assert s.verify() == [] and s.photo_done(photo) and sorted(s.files) == sorted(files)
        assert (tmp_path / name / "raw").exists() == s.keeps_raw_frames == (name == "kept")
    assert [r.tolist() for r in CaptureSession.open(tmp_path / "kept").raw_frames(0, 0)] == [r.tolist() for r in raws]


def test_open_refuses_what_is_not_a_capture(tmp_path):
    with pytest.raises(CaptureError, match="not a capture folder"):
        CaptureSession.open(tmp_path)
    (tmp_path / "manifest.json").write_text("{nope")
    with pytest.raises(CaptureError, match="unreadable manifest"):
        CaptureSession.open(tmp_path)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(CaptureError, match="not a capture folder; choose another"):
        CaptureSession.create(tmp_path / "other", {"format": "hemicube-capture", "version": 1})
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


@pytest.mark.slow
def test_a_capture_without_raw_frames_says_so(validate_dir, tmp_path):
    """The default capture writes no raw frames and its manifest says so (raw_frames: false); asking it for them
    (the reader, twin.capture.raw_compare) is one line that says how to get them. (A capture with --raw reads
    them: tests/twin/test_capture.py.)"""
    from twin.capture import raw_compare

    cap = validate_dir / "capture"
    s = CaptureSession.open(cap)
    assert s.header["raw_frames"] is False and not s.keeps_raw_frames
    assert not (cap / "raw").exists() and not any(rel.startswith("raw/") for rel in s.files)
    message = (f"{cap}: the capture was made without raw frames; capture again with --raw (the same seed gives the "
               "same frames)")
    for read in (lambda: s.raw_frames(129, 1), lambda: raw_compare.digest(cap, tmp_path / "rows.npz")):
        with pytest.raises(ValueError) as e:
            read()
        assert str(e.value) == message
    r = subprocess.run([sys.executable, "-m", "twin.capture.raw_compare", "digest", str(cap), str(tmp_path / "rows.npz")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stderr == f"raw_compare: {message}\n", r.stderr
    assert not (tmp_path / "rows.npz").exists()


def test_photos_unsynced_and_a_torn_one_retaken(tmp_path, monkeypatch):
    """A photo's files are renamed into place without an fsync (twin.atomic's durable=False: ~20 GB a paper-rig
    capture), the manifest that lists them with one; a photo file a power loss left short fails verify() and is not
    done (photo_done), so a resumed capture takes it again."""
    import twin.atomic

    synced = []
    real = os.fsync

    def fsync(fd):
        synced.append(os.path.basename(os.readlink(f"/proc/self/fd/{fd}")))
        real(fd)

    monkeypatch.setattr(twin.atomic.os, "fsync", fsync)
    header = {"format": "hemicube-capture", "version": 1, "rig": "mini", "rig_digest": "x"}
    photo = Photo(0, "primary", 0, "p", "sample")
    with CaptureSession.create(tmp_path / "c", header) as s:
        s.write_photo(photo, [np.ones((4, 4), np.uint16)], np.ones((4, 4, 3), np.float32), {"exposures_s": [1e-3]})
    assert synced and all(name.startswith(".manifest.json.") for name in synced), synced
    s = CaptureSession.open(tmp_path / "c")
    assert s.photo_done(photo) and s.verify() == []
    exr = next((tmp_path / "c").glob("*.exr"))
    exr.write_bytes(exr.read_bytes()[:100])  # what a power loss before the write-back may leave
    s = CaptureSession.open(tmp_path / "c")
    assert not s.photo_done(photo) and s.verify() == [exr.name]
