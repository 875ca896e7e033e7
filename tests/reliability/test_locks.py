"""Locks that hold (twin.lock.FolderLock, held by `hemicube capture` on its folder and by `hemicube reconstruct` on
its stage folder): a refused process changes nothing in the folder; a lock is released by its owner alone, or found
stale by pid and host; a lock recorded by another host is taken only with --break-lock, never one that a running
process holds. The holders are real processes."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from reconstruction.output import ReconstructionFolder, stages_folder
from twin.lock import LOCK, FolderLock, LockError

from tests.reliability.conftest import CAPTURE_ARGS, digest

# a process that takes the lock of the folder argv[1], says so, and keeps it until it is killed
HOLD = ("import sys, time; from twin.lock import FolderLock; FolderLock(sys.argv[1], 'a test run').acquire(); "
        "print('held', flush=True); time.sleep(600)")
ONE_THREAD = {"OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


@pytest.fixture
def holder(tmp_path):
    """start(folder): a running process holding the folder's lock (killed at the end of the test)."""
    procs = []

    def start(folder: Path) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
        procs.append(proc)
        assert proc.stdout.readline().strip() == "held"
        return proc

    yield start
    for proc in procs:
        proc.kill()
        proc.wait()


def _foreign(folder: Path, host: str = "another-host", pid: int = 4242) -> None:
    """The lock record a run on another host (or a process of this one) leaves behind."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / LOCK).write_text(json.dumps({"pid": pid, "host": host, "since": "2026-01-01T00:00:00+0000"}))


def test_a_running_holder_refuses_others_and_its_lock_goes_with_it(holder, tmp_path):
    folder = tmp_path / "f"
    proc = holder(folder)
    before = digest(folder)
    for break_lock in (False, True):  # --break-lock never takes a lock that a running process holds
        with pytest.raises(LockError, match=f"in use by a test run \\(pid {proc.pid} on {socket.gethostname()}"):
            FolderLock(folder, "a test run").acquire(break_lock)
    assert digest(folder) == before
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    lock = FolderLock(folder, "a test run").acquire()  # stale: its pid is gone from this host
    assert json.loads((folder / LOCK).read_text())["pid"] == os.getpid()
    lock.release()
    assert list(folder.iterdir()) == []


@pytest.mark.parametrize("host,pid", [("another-host", 4242), (socket.gethostname(), os.getpid())],
                         ids=["another host", "a running process of this host"])
def test_a_lock_that_cannot_be_judged_stale_needs_break_lock(tmp_path, host, pid):
    folder = tmp_path / "f"
    _foreign(folder, host, pid)
    before = digest(folder)
    with pytest.raises(LockError, match=f"pid {pid} on {host}.*--break-lock"):
        FolderLock(folder, "a test run").acquire()
    assert digest(folder) == before
    with FolderLock(folder, "a test run").acquire(break_lock=True):
        assert json.loads((folder / LOCK).read_text())["pid"] == os.getpid()
    assert list(folder.iterdir()) == []


def test_only_the_owner_releases(tmp_path):
    folder = tmp_path / "f"
    owner, other = FolderLock(folder, "a test run").acquire(), FolderLock(folder, "a test run")
    with pytest.raises(LockError, match="in use by"):
        other.acquire()
    other.release()  # refused: it holds nothing, so nothing is released
    with pytest.raises(LockError, match="in use by"):
        FolderLock(folder, "a test run").acquire()
    owner.release()
    FolderLock(folder, "a test run").acquire().release()


def test_capture_refused_by_a_running_holder_leaves_the_folder(holder, capture_copy, cli):
    proc = holder(capture_copy)
    before = digest(capture_copy)
    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy)
    assert rc == 2 and len(err) == 1 and f"in use by another capture (pid {proc.pid}" in err[0], err
    assert digest(capture_copy) == before


def test_capture_and_reconstruct_take_a_stale_lock_of_another_host_with_break_lock(capture_copy, tmp_path, cli,
                                                                                   monkeypatch):
    _foreign(capture_copy)
    before = digest(capture_copy)
    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy)
    assert rc == 2 and len(err) == 1 and "pid 4242 on another-host" in err[0] and "--break-lock" in err[0], err
    assert digest(capture_copy) == before
    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy, "--break-lock")
    assert rc == 0 and not (capture_copy / LOCK).exists()

    import reconstruction.pipeline as pipeline

    out = tmp_path / "recon"
    _foreign(stages_folder(out))
    rc, err = cli("reconstruct", capture_copy, "-o", out, "--no-progress")
    assert rc == 2 and len(err) == 1 and str(out) in err[0] and "another-host" in err[0], err

    def past_the_lock(*a, **k):
        raise RuntimeError("past the lock")

    monkeypatch.setattr(pipeline, "_reconstruct_into", past_the_lock)
    with pytest.raises(RuntimeError, match="past the lock"):
        cli("reconstruct", capture_copy, "-o", out, "--no-progress", "--break-lock")
    assert list(tmp_path.iterdir()) == [capture_copy]  # no stage finished: the run's own stage folder is gone


# the CLI with the alignment made to wait: it leaves a mark once it is aligning (it holds the lock, its stage folder
# and its half-built folder exist, no stage is finished) and goes on when the file argv[2] appears
WAITING_ALIGNMENT = ("import sys, time; from pathlib import Path; import reconstruction.stages.alignment as a; "
                     "real = a.align_views\n"
                     "def align(*args, **kw):\n"
                     "    Path(sys.argv[1]).write_text('aligning')\n"
                     "    while not Path(sys.argv[2]).exists():\n"
                     "        time.sleep(0.05)\n"
                     "    return real(*args, **kw)\n"
                     "a.align_views = align\n"
                     "from hemicube.cli import main; sys.exit(main(sys.argv[3:]))")


def test_runs_refused_while_another_reconstructs_leave_it_alone(capture, tmp_path, cli):
    """A second and a third `reconstruct` into the OUT of a run that has finished no stage yet are refused and
    touch nothing: the first run goes on to a complete folder."""
    work = tmp_path / "work"
    work.mkdir()
    out, mark, go = work / "OUT", tmp_path / "aligning", tmp_path / "go"
    log = (tmp_path / "first.log").open("w")
    first = subprocess.Popen([sys.executable, "-c", WAITING_ALIGNMENT, str(mark), str(go), "reconstruct",
                              str(capture), "-o", str(out), "--resolution", "4", "--no-progress"],
                             env=dict(os.environ, **ONE_THREAD), stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + 120
        while not mark.exists() and first.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        assert mark.exists(), (tmp_path / "first.log").read_text()
        before = digest(work)
        for _ in ("second", "third"):
            rc, err = cli("reconstruct", capture, "-o", out, "--resolution", "4", "--no-progress")
            assert rc == 2 and len(err) == 1 and f"in use by another reconstruction (pid {first.pid}" in err[0], err
            assert digest(work) == before
        go.write_text("go")
        assert first.wait(timeout=120) == 0, (tmp_path / "first.log").read_text()
    finally:
        first.kill()
        first.wait()
        log.close()
    assert ReconstructionFolder(out).verify() == []
    assert sorted(p.name for p in work.iterdir()) == ["OUT"]
