"""Output folders are owned, never clobbered (docs/reliability.md, "An output folder is never clobbered"). Every
command that writes a folder claims its output path with `claim_output` before any work, and is refused, in one line
naming the path, when the path
- is one of the command's inputs (the capture being read, a rig or sample folder, a design file, ...), lies inside
  one or holds one;
- lies below a file, or is itself a file (anything but a folder);
- is a folder that holds something and is not of the command's own `Kind` (a file that each such folder has always
  had says so, so folders written before this check are recognised too);
- is of the command's kind where the command replaces it only when told (`force=False`: no --force);
- holds a symbolic link (twin.paths.files_below): a folder is replaced or resumed only when nothing in it points
  elsewhere.
`--force` never replaces another kind of folder. The output path itself may be a symbolic link (a folder on a
scratch disk): what it points to is checked, and written. The claim writes nothing; the command then resumes or
replaces the folder as it does (twin.atomic.atomic_folder, which replaces folders only)."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path

from twin.lock import LOCK
from twin.paths import files_below


@dataclass(frozen=True)
class Kind:
    """A kind of output folder: `name` for the messages ("a capture folder"), `markers` the relative paths of
    which any one says a folder is of the kind (a part may be a pattern: "*/figures.json"), and, for kinds that
    share a marker file (the batches' batch.json), `field`: a key its JSON object holds for this kind alone."""
    name: str
    markers: tuple[str, ...]
    field: str | None = None

    def _marks(self, rel: str) -> bool:
        parts = rel.split("/")
        return any(len(m.split("/")) == len(parts) and all(map(fnmatchcase, parts, m.split("/")))
                   for m in self.markers)

    def missing(self, folder: Path, files: list[str]) -> str | None:
        """None when `files` (the folder's, from files_below) mark the kind; else what is missing."""
        found = [f for f in files if self._marks(f)]
        if self.field is not None:
            found = [f for f in found if _has_key(folder / f, self.field)]
        if found:
            return None
        return f"no {' or '.join(self.markers)}" + (f" naming {self.field!r}" if self.field else "")


def _has_key(path: Path, key: str) -> bool:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and key in doc


def _relation(out: Path, path: Path) -> str | None:
    if out == path:
        return "would be"
    if path in out.parents:
        return "would lie inside"
    if out in path.parents:
        return "would hold"
    return None


def claim_output(out, kind: Kind, inputs=(), force: bool | None = None) -> bool:
    """Check the output path `out` of a command that writes `kind` (module docstring), before its work; a
    ValueError names the path otherwise. `inputs`: (what, path) pairs of what the command reads ("the capture
    being read", CAPTURE); a path that is None or does not exist (a built-in rig's name) is passed over. `force`:
    None for a command that resumes or replaces its own kind without being told, else whether --force was given.
    Returns whether `out` is an existing folder (empty, or of the kind) that the command may replace."""
    out = Path(out)
    real = Path(os.path.realpath(out))
    for what, path in inputs:
        if path is None or not os.path.lexists(path):
            continue
        rel = _relation(real, Path(os.path.realpath(path)))
        if rel is not None:
            raise ValueError(f"{out}: the output {rel} {what} ({path}); choose a folder outside it")
    if not os.path.lexists(real):
        if out.is_symlink():
            raise ValueError(f"{out} is a symbolic link to {real}, which does not exist; make that folder or choose "
                             "another output path")
        above = next(p for p in real.parents if os.path.lexists(p))
        if not above.is_dir():
            raise ValueError(f"{out}: {above} is not a folder; choose another output path")
        return False
    if not real.is_dir():
        raise ValueError(f"{out} exists and is not a folder; choose another output path")
    if all(name == LOCK for name in os.listdir(real)):
        return True  # nothing to lose (a lock alone: its owner's, which the command's own lock then meets)
    missing = kind.missing(real, files_below(out))
    if missing is not None:
        raise ValueError(f"{out} exists and is not {kind.name} ({missing}); choose another output path or empty it "
                         "first")
    if force is False:
        raise ValueError(f"{out} exists ({kind.name}); pass --force to replace it")
    return True
