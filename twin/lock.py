"""One writer a folder: the lock `hemicube capture` holds on its capture folder and `hemicube reconstruct` on its
stage folder (docs/reliability.md, "Locks").

The lock is the file LOCK in the folder, held with the operating system's lock on it (filelock.lock_descriptor: flock
on Unix, LockFileEx on Windows), which goes with its process however that ends, and holding its owner's record: pid,
host and the time it was taken. A process that wants the folder finds one of these:
- the system's lock held: a running process has the folder; refused, naming it (--break-lock changes nothing here);
- the system's lock free and no record, or the record of a process of this host that is no longer running (a killed
  run): stale, taken;
- the system's lock free and the record of a process on another host (a folder on a shared file system, where that
  host's lock may not be seen here), or of a process of this host that is running but holds no lock (its pid reused,
  or a file system without locks): it cannot be told from a live owner, so refused, naming it, unless `break_lock`
  (`--break-lock`: the user says that run has ended).
A refused process writes nothing to the folder. The owner alone releases the lock: it removes the file while it still
holds the system's lock, so a process that took the lock of a removed file lets go and tries again, and two owners
never hold one folder.
"""
from __future__ import annotations

import json
import os
import shutil
import socket
import time
from contextlib import suppress
from pathlib import Path

from filelock import lock_descriptor

LOCK = ".lock"
BREAK_LOCK_HELP = ("take the folder's lock when the run it names has ended on another host (or is not this host's "
                   "running process); never a lock a running process holds (docs/reliability.md, \"Locks\")")
ATTEMPTS = 50  # tries to lock a file that is still the folder's lock file (each lost race is an owner releasing)


class LockError(ValueError):
    """The folder is, or may be, another process's."""


def _same_file(fd: int, path: Path) -> bool:
    """Whether the open file `fd` is still the one at `path` (an owner removes it as it releases it)."""
    try:
        here, there = os.fstat(fd), os.lstat(path)
    except FileNotFoundError:
        return False
    return (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino)


def _record(fd: int) -> dict | None:
    """The owner's record in the lock file, or None (none, or not one this module wrote)."""
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        doc = json.loads(os.read(fd, 4096))
    except (OSError, ValueError):
        return None
    ok = isinstance(doc, dict) and isinstance(doc.get("pid"), int) and 0 < doc["pid"] < 2**31 \
        and isinstance(doc.get("host"), str)
    return doc if ok else None


def _running(pid: int) -> bool:
    if os.name == "nt":  # os.kill(pid, 0) would end the process there: a pid on Windows counts as running
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        return True
    return True


def _owner(rec: dict | None) -> str:
    if rec is None:
        return "another process"
    return f"pid {rec['pid']} on {rec['host']} since {rec.get('since', '?')}"


class FolderLock:
    """The lock of `folder` (module docstring), taken by `acquire` and given back by `release` (or the `with` block
    around it). `what` names the holder in the messages ("another capture"), `shown` the folder (default `folder`)."""

    def __init__(self, folder, what: str, shown=None):
        self.folder = Path(folder)
        self.path = self.folder / LOCK
        self.what, self.shown = what, Path(shown) if shown is not None else self.folder
        self._fd: int | None = None

    def acquire(self, break_lock: bool = False) -> "FolderLock":
        """Take the lock (making the folder if need be), or raise LockError naming its holder, the folder unchanged."""
        for _ in range(ATTEMPTS):
            fd = self._open()
            if fd is None:
                continue
            try:
                got = lock_descriptor(fd, blocking=False)
            except OSError as e:
                os.close(fd)
                raise LockError(f"{self.path}: cannot lock it ({e.strerror or e}); the folder must be on a file "
                                "system with file locks") from None
            if not got:
                rec = _record(fd)
                os.close(fd)
                raise LockError(f"{self.shown} is in use by {self.what} ({_owner(rec)}); wait for it or choose "
                                "another folder")
            if not _same_file(fd, self.path):
                os.close(fd)  # its owner released it as we locked it: the next file is the lock
                continue
            rec = _record(fd)
            if rec is not None and not break_lock:
                here = rec["host"] == socket.gethostname()
                if not here or _running(rec["pid"]):
                    os.close(fd)
                    why = ("a running process of this host that holds no lock on it (its pid reused?)" if here else
                           "a host whose processes this one cannot see")
                    raise LockError(f"{self.shown} is locked by {self.what} ({_owner(rec)}), {why}; if that run has "
                                    "ended, run again with --break-lock")
            try:
                self._write_record(fd)
            except OSError as e:  # a full disk: not taken, and the file that holds no record goes
                with suppress(OSError):
                    os.unlink(self.path)
                os.close(fd)
                raise OSError(e.errno, e.strerror, str(self.path)) from e
            self._fd = fd
            return self
        raise LockError(f"{self.path}: the lock file kept being replaced while it was being taken; try again")

    def _open(self) -> int | None:
        """The lock file, opened (made if absent, never through a link), or None when its folder was just removed by
        an owner releasing it."""
        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            return os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except FileNotFoundError:
            return None
        except OSError as e:
            raise LockError(f"{self.path}: cannot open the lock ({e.strerror or e})") from None

    @staticmethod
    def _write_record(fd: int) -> None:
        rec = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, json.dumps(rec).encode())  # not synced: after a power loss no process holds it anyway

    def release(self) -> None:
        """Give the lock back (the owner only: a FolderLock that holds nothing releases nothing). Its file is removed
        first, so a process waiting on it takes the next one."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            if _same_file(fd, self.path):
                try:
                    os.unlink(self.path)
                except OSError:  # a file system that keeps open files (Windows): the record goes, the file stays
                    os.ftruncate(fd, 0)
        finally:
            os.close(fd)

    def remove_folder(self) -> None:
        """The owner removes its folder: the contents, then (releasing) the lock, then the folder itself, which stays
        when another process has taken it meanwhile. Links inside are removed, never followed."""
        if self._fd is None:
            raise LockError(f"{self.shown}: only the owner of its lock removes {self.folder}")
        with os.scandir(self.folder) as entries:
            for e in entries:
                if e.name == LOCK:
                    continue
                shutil.rmtree(e.path) if e.is_dir(follow_symlinks=False) else os.unlink(e.path)
        self.release()
        with suppress(OSError):
            self.folder.rmdir()

    def __enter__(self) -> "FolderLock":
        return self

    def __exit__(self, *exc) -> bool:
        self.release()
        return False
