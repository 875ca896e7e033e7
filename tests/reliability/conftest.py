"""The reliability tests' capture: one small real capture of the mini rig a session (one frame an exposure, a 16^2
sample, its raw frames kept; only its folder matters here), read by every test, and hard-linked copies of it for
the tests that change a folder, so that a copy costs neither time nor space."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

import hemicube.cli

# `hemicube capture` as the session's capture was taken: run again on a copy, it resumes that copy
CAPTURE_ARGS = ("capture", "--rig", "mini", "--sample", "ramps", "--seed", "1", "--frames", "1", "--sample-resolution",
                "16", "--raw", "--no-progress")


def digest(root: Path) -> str:
    """sha256 over every path below `root`, hidden ones included: each file's bytes, each link's target (never
    followed)."""
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        h.update(str(p.relative_to(root)).encode())
        if p.is_symlink():
            h.update(os.readlink(p).encode())
        elif p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def rewrite_manifest(folder: Path, change) -> None:
    """change(doc) edits the manifest, written back as a new file (the copy's files are hard links to the
    session's capture: writing into one would change both)."""
    path = folder / "manifest.json"
    doc = json.loads(path.read_text())
    change(doc)
    path.unlink()
    path.write_text(json.dumps(doc))


@pytest.fixture(scope="session")
def capture(tmp_path_factory) -> Path:
    cap = tmp_path_factory.mktemp("rel") / "capture"
    assert hemicube.cli.main([*CAPTURE_ARGS, "-o", str(cap)]) == 0
    return cap


@pytest.fixture
def capture_copy(capture, tmp_path) -> Path:
    """A copy of the session's capture made of hard links to its files (a test replaces a file, never writes
    into one)."""
    out = tmp_path / "copy"
    shutil.copytree(capture, out, copy_function=os.link, ignore=shutil.ignore_patterns(".lock"))
    return out


@pytest.fixture
def cli(capsys):
    """Run `hemicube ARGS` in this process: (exit code, the lines it wrote to stderr)."""
    def run(*argv) -> tuple[int, list[str]]:
        capsys.readouterr()
        rc = hemicube.cli.main([str(a) for a in argv])
        return rc, capsys.readouterr().err.strip().splitlines()
    return run
