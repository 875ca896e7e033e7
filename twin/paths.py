"""Paths inside a capture or reconstruction folder, for the one module that owns each folder (twin.capture.session,
reconstruction.output): a path a manifest lists is relative, normalised and inside the folder, checked before anything
is opened; and a symbolic link inside the folder is refused by name, never followed, when the folder is read or
written. The folder itself may be a link (a folder on a scratch disk): only what lies below it is checked.

Each check raises `error` (a ValueError by default; the capture's own CaptureError where it reads), one line naming the
path."""
from __future__ import annotations

import os
import stat
from pathlib import Path, PureWindowsPath


def relative_path(rel, where, error=ValueError) -> str:
    """`rel` when it names a path inside a folder: a relative POSIX path without empty, '.' or '..' parts, backslashes
    or a drive; else `error` naming it and `where` (the file that lists it, or the folder)."""
    ok = isinstance(rel, str) and "\\" not in rel and "\0" not in rel and not PureWindowsPath(rel).drive \
        and all(part not in ("", ".", "..") for part in rel.split("/"))
    if not ok:
        raise error(f"{where}: {rel!r} is not a relative path inside the folder; nothing outside it is opened")
    return rel


def _link(path, root, more: int = 0) -> str:
    also = f" (and {more} more)" if more else ""
    return (f"{path}: a symbolic link inside {root}{also}, which is never followed there; put what it points to in its "
            "place, or remove it")


def inside(root, rel: str, error=ValueError) -> Path:
    """root / rel, for a `rel` relative_path accepts, when no part of it below `root` is a symbolic link (parts that
    do not exist yet are fine: a writer makes them as folders)."""
    relative_path(rel, root, error)
    path = Path(root)
    for part in rel.split("/"):
        path = path / part
        try:
            if stat.S_ISLNK(os.lstat(path).st_mode):
                raise error(_link(path, root))
        except FileNotFoundError:
            break
    return Path(root) / rel


def files_below(root, error=ValueError) -> list[str]:
    """Every regular file below `root`, as sorted relative POSIX paths; a symbolic link anywhere below it is `error`,
    naming the first (and counting the others)."""
    root = Path(root)
    if not root.is_dir():
        return []
    found, links, todo = [], [], [root]
    while todo:
        try:
            entries = os.scandir(todo.pop())
        except FileNotFoundError:  # gone since it was listed: a writer's temporary folder, renamed or removed
            continue
        with entries:
            for e in entries:
                if e.is_symlink():
                    links.append(e.path)
                elif e.is_dir(follow_symlinks=False):
                    todo.append(Path(e.path))
                elif e.is_file(follow_symlinks=False):
                    found.append(Path(e.path).relative_to(root).as_posix())
    if links:
        raise error(_link(min(links), root, len(links) - 1))
    return sorted(found)
