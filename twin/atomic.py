"""Atomic file writes: write a temp file in the target's folder, fsync, rename over the target.
A reader (or a killed writer) sees either the old file or the complete new one, never half of it. `durable=False`
skips the fsync: the rename is still atomic for readers and killed writers, but after a power loss the file may
hold less than was written, so only files whose checksum is verified before use may be written so (a capture's
photos: CaptureSession.photo_done re-takes a photo whose files fail).

A killed writer leaves its temporaries behind under names of their own (`is_leftover`), which the next writer of the
folder removes (`remove_leftovers`), and nothing else."""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
from contextlib import contextmanager, suppress
from pathlib import Path


def _file_mode() -> int:
    """rw for whom the umask allows, as open() would create it (mkstemp makes files 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "", durable: bool = True):
    """Yield a temporary path beside `path`; on success rename it to `path`, on error delete it.
    `suffix` keeps an extension some writers insist on (np.savez appends .npz otherwise); `durable`: fsync before
    the rename (module docstring). An error of the operating system (a read-only place, a full disk) leaves no
    temporary behind and names `path`, the file the caller wrote, where it named the temporary or no file at all (a
    write that fails names none)."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
        os.close(fd)
        os.chmod(tmp, _file_mode())
        yield Path(tmp)
        if durable:
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        if tmp is not None:
            with suppress(OSError):  # the error that stopped the write is the one to report
                os.unlink(tmp)
        if isinstance(e, OSError) and e.errno is not None and (e.filename is None or
                                                               is_leftover(Path(os.fsdecode(e.filename)).name)):
            raise OSError(e.errno, e.strerror, str(path)) from e  # the same subclass (PermissionError, ...)
        raise


def file_sha256(path: str | os.PathLike) -> str:
    """sha256 of a file, read in 1 MiB blocks (manifests and checkpoints record it)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_bytes_atomic(path: str | os.PathLike, data: bytes, durable: bool = True) -> Path:
    with atomic_path(path, durable=durable) as tmp:
        tmp.write_bytes(data)
    return Path(path)


@contextmanager
def atomic_folder(path: str | os.PathLike, overwrite: bool = False, scratch: str | os.PathLike | None = None):
    """Yield a temporary folder to fill; on success it replaces `path` (the old folder is moved aside, the new
    one renamed in, the old one deleted, and put back if the rename fails); on error it is deleted. A reader
    sees the old folder or the complete new one, never a mix. The temporary and the old folder are kept in
    `scratch` (default: beside `path`; on the same file system, for the renames), where a killed run leaves them.
    A `path` that is a symbolic link is written where it points, the link kept; one that is not a folder is
    refused, as rmtree would leave it behind under its hidden name."""
    dest = Path(path)
    if dest.is_symlink():
        dest = Path(os.path.realpath(dest))
    if dest.exists() and not dest.is_dir():
        raise FileExistsError(f"{dest} exists and is not a folder; choose another path")
    if dest.exists() and not overwrite:
        raise FileExistsError(f"{dest} exists; pass overwrite=True (--force) to replace it")
    dest.parent.mkdir(parents=True, exist_ok=True)
    scratch = dest.parent if scratch is None else Path(scratch)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=scratch))
    os.chmod(tmp, 0o755)  # mkdtemp makes it private; these are ordinary folders
    try:
        yield tmp
        if dest.exists():
            old = scratch / f".{dest.name}.old-{os.getpid()}"
            os.rename(dest, old)
            try:
                os.rename(tmp, dest)
            except BaseException:
                os.rename(old, dest)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# `.NAME.XXXXXXXX[SUFFIX]`: atomic_path's file (tempfile's eight random characters; SUFFIX is NAME's own) or
# atomic_folder's folder (no suffix); `.NAME.old-PID`: the folder atomic_folder is replacing
_LEFTOVER = re.compile(r"\.(?P<name>.+)\.(?:[a-z0-9_]{8}(?P<suffix>\.[^.]+)?|old-\d+)")


def is_leftover(name: str) -> bool:
    """Whether `name` is one this module gives its temporaries (what a killed writer leaves)."""
    m = _LEFTOVER.fullmatch(name)
    return m is not None and m["suffix"] in (None, Path(m["name"]).suffix)


def remove_leftovers(folder: str | os.PathLike) -> None:
    """Remove the temporaries a killed writer left below `folder` (is_leftover), and nothing else: a symbolic
    link is never one, and is neither followed nor removed. The caller holds the folder's lock (twin.lock), so
    no writer is still using them."""
    todo = [Path(folder)]
    while todo:
        with os.scandir(todo.pop()) as entries:
            for e in entries:
                if e.is_symlink():
                    continue
                if is_leftover(e.name):
                    shutil.rmtree(e.path) if e.is_dir(follow_symlinks=False) else os.unlink(e.path)
                elif e.is_dir(follow_symlinks=False):
                    todo.append(Path(e.path))
