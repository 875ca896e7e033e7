"""One line, exit code 2 (3 for the system's refusals), and nothing half-written: a setting out of range is refused before any work (no stage
folder, no output); a pattern file of another format is refused by name; a read-only place and a full disk are named
with their cause in words. CI runs as root, whom no file mode stops, and cannot fill a disk on demand, so the
operating system's refusals (EROFS, EACCES, ENOSPC) are injected in this process at the calls the writers make
(twin.atomic, twin.lock, the capture and reconstruction folders): making a folder, opening a file for writing,
writing, renaming and removing, for paths below the test's own folder only. Every case goes through
`hemicube.cli.main`, as a user's command does."""
from __future__ import annotations

import builtins
import errno
import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest

from twin.atomic import is_leftover
from twin.exitcodes import EXIT_IO, EXIT_USAGE
from twin.capture.session import CaptureSession
from twin.lock import LOCK
from reconstruction.output import ALIGNMENT, MEASUREMENTS, STAGES, stages_folder

from tests.reliability.conftest import CAPTURE_ARGS, digest, rewrite_manifest

WRITING = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC


def _below(root: Path, path) -> bool:
    if isinstance(path, int):  # an open file's descriptor
        return False
    p = os.path.abspath(os.fsdecode(path))
    return p == str(root) or p.startswith(str(root) + os.sep)


def _refuse(code: int, path) -> None:
    raise OSError(code, os.strerror(code), os.fsdecode(path))


def read_only(monkeypatch, root: Path, code: int = errno.EROFS) -> None:
    """Below `root`, every call that would change something fails with `code`, as on a read-only mount (EROFS) or in
    a folder the user may not write (EACCES); reading works, and so does making a folder that exists (EEXIST comes
    first)."""
    real_mkdir, real_open, real_io_open = os.mkdir, os.open, io.open

    def mkdir(path, *a, **k):
        if _below(root, path) and not os.path.lexists(path):
            _refuse(code, path)
        return real_mkdir(path, *a, **k)

    def os_open(path, flags, *a, **k):
        if flags & WRITING and _below(root, path):
            _refuse(code, path)
        return real_open(path, flags, *a, **k)

    def io_open(file, mode="r", *a, **k):
        if set(mode) & set("wax+") and _below(root, file):
            _refuse(code, file)
        return real_io_open(file, mode, *a, **k)

    def changing(real):
        def call(path, *a, **k):
            if _below(root, path) or (a and not isinstance(a[0], int) and _below(root, a[0])):
                _refuse(code, path)
            return real(path, *a, **k)
        return call

    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(io, "open", io_open)
    monkeypatch.setattr(builtins, "open", io_open)
    for name in ("replace", "rename", "unlink", "rmdir", "chmod"):
        monkeypatch.setattr(os, name, changing(getattr(os, name)))


class _Disk:
    """The disk of `full_disk`: it fills while a file that `fills_at(path)` picks is written."""

    def __init__(self, fills_at):
        self.full, self.fills_at = False, fills_at

    def write(self, path: str, data, write) -> int:
        """`write(data)` to the file at `path`, as far as the disk allows."""
        if not self.full and self.fills_at(path):
            self.full = True
            write(bytes(memoryview(data))[:len(data) // 2])  # half of it lands, as the disk runs out
        if self.full:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # the system's: a failed write names no file
        return write(data)


class _Filling:
    """A file opened for writing on the disk of `full_disk`."""

    def __init__(self, f, disk: _Disk, path: str):
        self._f, self._disk, self._path = f, disk, path

    def write(self, data) -> int:
        return self._disk.write(self._path, data, self._f.write)

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()
        return False


def full_disk(monkeypatch, root: Path, fills_at) -> _Disk:
    """The disk below `root` fills while a file that `fills_at(path)` picks is written (open().write, os.write):
    that write stores half its bytes, then it and every later write below `root`, and every folder made there, fail
    with ENOSPC. Renames and removals work, as they do on a full disk."""
    real_mkdir, real_io_open, real_write = os.mkdir, io.open, os.write
    disk = _Disk(fills_at)

    def mkdir(path, *a, **k):
        if disk.full and _below(root, path) and not os.path.lexists(path):
            _refuse(errno.ENOSPC, path)
        return real_mkdir(path, *a, **k)

    def io_open(file, mode="r", *a, **k):
        f = real_io_open(file, mode, *a, **k)
        return _Filling(f, disk, os.fsdecode(file)) if set(mode) & set("wax+") and _below(root, file) else f

    def write(fd, data):
        try:
            path = os.readlink(f"/proc/self/fd/{fd}")  # Linux, as CI
        except OSError:
            path = None
        if path is not None and _below(root, path):
            return disk.write(path, data, lambda b: real_write(fd, b))
        return real_write(fd, data)

    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(io, "open", io_open)
    monkeypatch.setattr(builtins, "open", io_open)
    monkeypatch.setattr(os, "write", write)
    return disk


def _leftovers(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if is_leftover(p.name)]


def _one_line(rc: int, err: list[str], *parts: str, code: int = EXIT_USAGE) -> str:
    """The one line of an error: exit 2 for bad input, 3 (code=EXIT_IO) for the system's refusal of a write."""
    assert rc == code and len(err) == 1 and err[0].startswith("hemicube: error: "), err
    for part in parts:
        assert part in err[0], err
    return err[0]


# --- settings refused before any work --------------------------------------------------------------------------------

NO_RUN = "no-such-run"  # a --network folder that does not exist (below the test's folder)


@pytest.mark.parametrize("option, message", [
    (("--resolution", "0"), "grid resolution (--resolution) must be an integer >= 2, got 0"),
    (("--resolution", "-1"), "grid resolution (--resolution) must be an integer >= 2, got -1"),
    # ~224 GiB at the first allocation after the alignment
    (("--resolution", "100000"), "100000 texels across 150 mm of the sample, where the primary camera has 150 "
                                 "photosites across it"),
    (("--size-mm", "-5"), "grid size (--size-mm) must be a positive number of mm, got -5.0"),
    (("--size-mm", "nan"), "grid size (--size-mm) must be a positive number of mm, got nan"),
    (("--size-mm", "1e9"), "a 1e+09 mm grid is larger than the largest sample rig 'mini' holds (150 mm a side)"),
    (("--holdout-line", "99"), "--holdout-line 99: the capture has 64 line photos, 0 to 63"),
    (("--network", NO_RUN), f"{NO_RUN}: not a training run folder"),
    (("--device", "gpu"), "unknown device 'gpu'"),
    (("--device", "cuda:7"), "unknown device 'cuda:7'"),
], ids=lambda v: " ".join(v) if isinstance(v, tuple) else "")
def test_reconstruct_settings_refused_before_any_work(capture, tmp_path, cli, monkeypatch, option, message):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "recon"
    rc, err = cli("reconstruct", capture, "-o", out, "--no-progress", *option)
    line = _one_line(rc, err, message)
    if option[0] == "--device":
        assert "this machine has: cpu" in line  # the devices there are
    assert list(tmp_path.iterdir()) == []  # no stage folder (so no lock, no work), no output


def test_a_pattern_file_whose_version_is_an_array(capture, tmp_path, cli):
    bad, out = tmp_path / "patterns.npz", tmp_path / "cap"
    with np.load(capture / "patterns.npz") as z:
        np.savez(bad, **{**{k: z[k] for k in z.files}, "version": np.array([1, 1], np.int32)})
    rc, err = cli(*CAPTURE_ARGS, "--patterns", bad, "-o", out)
    _one_line(rc, err, f"{bad}: unknown pattern format version [1, 1]; this twin reads version 1")
    assert not out.exists()


# --- read-only places ------------------------------------------------------------------------------------------------

CAUSES = {errno.EROFS: "read-only file system; choose a folder on a writable file system",
          errno.EACCES: "permission denied; choose a folder you may write to"}


@pytest.mark.parametrize("code", CAUSES, ids=errno.errorcode.get)
def test_capture_into_a_read_only_place(tmp_path, cli, monkeypatch, code):
    place = tmp_path / "mount"
    place.mkdir()
    read_only(monkeypatch, place, code)
    out = place / "cap"
    rc, err = cli(*CAPTURE_ARGS, "-o", out)
    _one_line(rc, err, f"{out}: {CAUSES[code]}", code=EXIT_IO)
    monkeypatch.undo()
    assert list(place.iterdir()) == []


@pytest.mark.parametrize("code", CAUSES, ids=errno.errorcode.get)
def test_reconstruct_into_a_read_only_place(capture, tmp_path, cli, monkeypatch, code):
    place = tmp_path / "mount"
    place.mkdir()
    read_only(monkeypatch, place, code)
    out = place / "recon"
    rc, err = cli("reconstruct", capture, "-o", out, "--no-progress")
    # the first thing written is the stage folder beside OUT (reconstruction.output)
    _one_line(rc, err, f"{stages_folder(out)}: {CAUSES[code]}", code=EXIT_IO)
    monkeypatch.undo()
    assert list(place.iterdir()) == []


# --- a full disk -----------------------------------------------------------------------------------------------------

def _files(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in folder.rglob("*") if p.is_file()}


def test_a_disk_that_fills_while_a_raw_frame_is_written(capture, capture_copy, cli, monkeypatch):
    """The capture stops in one line; every photo it had finished stays listed and verified, no temporary or torn file
    is left, and the same command, run again with space, finishes it: the same bytes as a capture never stopped."""
    done = json.loads((capture / "manifest.json").read_text())
    plan = [f"img{p['index']:05d}_cam{p['camera_index']:02d}" for p in done["plan"]]
    todo = plan[-3:]  # the plan's last photos, not taken yet

    def untaken(doc):
        for stem in todo:
            for rel in doc["photos"].pop(stem)["files"]:
                del doc["files"][rel]
                (capture_copy / rel).unlink()
    rewrite_manifest(capture_copy, untaken)
    kept = set(CaptureSession.open(capture_copy).photos)
    # the disk fills in the second exposure's frame of the second photo taken
    full_disk(monkeypatch, capture_copy, lambda p: Path(p).name.startswith(f".{todo[1]}_e1."))
    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy)
    _one_line(rc, err, str(capture_copy), "no space left on device; free some space and run the command again", code=EXIT_IO)
    monkeypatch.undo()

    session = CaptureSession.open(capture_copy)
    assert kept <= set(session.photos) and session.verify() == []
    assert not _leftovers(capture_copy) and not (capture_copy / ".lock").exists()
    # nothing torn: every file there is whole, the bytes of the capture never stopped
    assert all(done["files"].get(rel) == sha for rel, sha in _files(capture_copy).items() if rel != "manifest.json")

    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy)
    assert rc == 0, err
    session = CaptureSession.open(capture_copy)
    assert session.complete() and session.files == done["files"]


def test_reconstruct_on_a_disk_that_fills(capture, tmp_path, cli, monkeypatch):
    """Full while the extraction's measurements are written: one line; the finished alignment stays in the stage
    folder (a run with space goes on from it), with no temporary, no half-built OUT and no lock. Run again on the
    full disk: the lock's record cannot be written, so the lock is not taken, and the stage folder stays as it was."""
    out, argv = tmp_path / "recon", ("reconstruct", capture, "-o", tmp_path / "recon", "--no-progress",
                                     "--resolution", "16")
    stages = stages_folder(out)
    full_disk(monkeypatch, tmp_path, lambda p: Path(p).name.startswith(f".{MEASUREMENTS}."))
    rc, err = cli(*argv)
    _one_line(rc, err, f"{stages / MEASUREMENTS}: no space left on device; free some space", code=EXIT_IO)
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == [stages]
    assert sorted(p.name for p in stages.iterdir()) == [ALIGNMENT, STAGES]
    assert list(json.loads((stages / STAGES).read_text())) == ["alignment"]

    before = digest(stages)
    full_disk(monkeypatch, tmp_path, lambda p: True)
    rc, err = cli(*argv)
    _one_line(rc, err, f"{stages / LOCK}: no space left on device", code=EXIT_IO)
    monkeypatch.undo()
    assert digest(stages) == before and list(tmp_path.iterdir()) == [stages]
