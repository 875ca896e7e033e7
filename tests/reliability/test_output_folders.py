"""Output folders are owned, never clobbered (docs/reliability.md, "An output folder is never clobbered"): every
command that writes a folder refuses, in one line naming the path, before any work, an output that is a user's
folder, a file, a path below a file, another command's kind of folder (--force included), an input of the command,
a folder inside one or a folder holding one, or its own kind of folder holding a symbolic link; the refused path
and the inputs stay byte for byte as they were, with nothing hidden left beside. Every case runs the command line,
as a user does."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest

from twin.capture.session import CaptureSession

from tests.reliability.conftest import CAPTURE_ARGS, digest

DESIGN = Path(__file__).resolve().parents[2] / "docs" / "designs" / "learned-32.toml"


def _state(path: Path):
    """What lies at `path`: a link's target, a folder's digest, a file's bytes, or None."""
    if path.is_symlink():
        return "link", os.readlink(path)
    if path.is_dir():
        return "folder", digest(path)
    return ("file", path.read_bytes()) if path.exists() else None


def _refused(cli, argv, out: Path, message: str, *inputs: Path) -> None:
    """`hemicube ARGV` exits 2 with one stderr line naming `out` and saying `message`; `out` and `inputs` are as
    they were, and nothing new lies beside `out` (no stage folder, temporary, hidden copy or lock)."""
    watched = [p for p in {out, *inputs} if not any(q in p.parents for q in (out, *inputs))]  # the outermost
    before = [_state(p) for p in watched]
    near = next(p for p in out.parents if p.is_dir())
    beside = sorted(os.listdir(near))
    rc, err = cli(*argv)
    assert rc == 2 and len(err) == 1, err
    assert str(out) in err[0] and message in err[0], err
    assert [_state(p) for p in watched] == before
    assert sorted(os.listdir(near)) == beside


# --- reconstruct, the first command that checked its output --------------------------------------------------
def _reconstruct_refused(cli, capture: Path, out: Path, message: str) -> None:
    _refused(cli, ["reconstruct", capture, "-o", out, "--no-progress"], out, message, capture)
    assert CaptureSession.open(capture).verify() == []


def test_a_users_folder_is_refused_and_kept(capture, tmp_path, cli):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"not ours")
    _reconstruct_refused(cli, capture, out, "is not a reconstruction folder")


def test_a_file_is_refused_and_kept(capture, tmp_path, cli):
    out = tmp_path / "notes.txt"
    out.write_text("keep me")
    _reconstruct_refused(cli, capture, out, "is not a folder")


def test_the_capture_itself_is_refused(capture, cli):
    _reconstruct_refused(cli, capture, capture, "the capture being read")


def test_a_folder_inside_the_capture_is_refused(capture, cli):
    out = capture / "recon"
    _reconstruct_refused(cli, capture, out, "the capture being read")
    assert not out.exists()


def test_a_folder_holding_the_capture_is_refused(capture, cli):
    _reconstruct_refused(cli, capture, capture.parent, "the capture being read")


def test_an_empty_folder_is_accepted(capture, tmp_path):
    from reconstruction.pipeline import check_output

    out = tmp_path / "empty"
    out.mkdir()
    check_output(out, capture)  # no error: an empty folder holds nothing to lose
    check_output(tmp_path / "absent", capture)


# --- every command that writes a folder ------------------------------------------------------------------------
@pytest.fixture
def inputs(capture, tmp_path) -> SimpleNamespace:
    """What the commands read: the session's capture, a samples file, a design file (each in a folder of its own)."""
    (tmp_path / "in").mkdir()
    samples = tmp_path / "in" / "samples.toml"
    samples.write_text('rig = "mini"\n[[sample]]\nname = "ramps"\n')
    design = tmp_path / "in" / "design.toml"
    shutil.copyfile(DESIGN, design)
    return SimpleNamespace(capture=capture, samples=samples, design=design)


# each command's arguments but -o (cheap settings: a refused command does no work, an accepted one little)
COMMANDS = {
    "capture": lambda i: [*CAPTURE_ARGS],
    "capture-many": lambda i: ["capture-many", i.samples, "--no-progress"],
    "reconstruct": lambda i: ["reconstruct", i.capture, "--no-progress"],
    "reconstruct-many": lambda i: ["reconstruct-many", i.capture.parent, "--no-progress"],
    "rig export --force": lambda i: ["rig", "export", "mini", "--force"],
    "calibrate": lambda i: ["calibrate", "cameras", "--rig", "mini", "--no-progress"],
    "validate": lambda i: ["validate", "--resolution", "16", "--frames", "1", "--no-progress"],
    "validate --suite": lambda i: ["validate", "--suite", "ramps", "--resolution", "16", "--frames", "1"],
    "design evaluate": lambda i: ["design", "evaluate", i.design, "--no-progress"],
    "design optimise": lambda i: ["design", "optimise", i.design, "--steps", "1", "--no-progress"],
    "train": lambda i: ["train", "--rig", "mini", "--steps", "1", "--no-progress"],
}


def _users_folder(tmp_path: Path) -> Path:
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"not ours")
    return out


def _file(tmp_path: Path) -> Path:
    out = tmp_path / "notes.txt"
    out.write_text("keep me")
    return out


FOREIGN = {  # an output that is none of the command's: (make it, what the message says)
    "a user's folder": (_users_folder, "exists and is not a"),
    "a file": (_file, "exists and is not a folder"),
    "a path below a file": (lambda tmp_path: _file(tmp_path) / "out", "notes.txt is not a folder"),
}


@pytest.mark.parametrize("case", FOREIGN)
@pytest.mark.parametrize("command", COMMANDS)
def test_what_is_not_the_commands_is_refused(command, case, inputs, tmp_path, cli):
    make, message = FOREIGN[case]
    out = make(tmp_path)
    _refused(cli, [*COMMANDS[command](inputs), "-o", out], out, message, inputs.samples.parent)


# the output is an input, lies inside one or holds one: (arguments but -o, the output, the input, the message),
# from the capture's copy `c` (its rig and its ground-truth maps are a rig folder and a sample) and `i`, inputs
INPUTS = {
    "capture: inside --rig": lambda c, i: (
        ["capture", "--rig", c / "rig", "--frames", "1", "--sample-resolution", "16"], c / "rig" / "x", c / "rig",
        "would lie inside the rig folder"),
    "capture: holding --sample": lambda c, i: (
        ["capture", "--rig", "mini", "--sample", c / "ground_truth" / "maps"], c / "ground_truth",
        c / "ground_truth" / "maps", "would hold the sample's maps"),
    "capture-many: holding the samples file": lambda c, i: (
        ["capture-many", i.samples], i.samples.parent, i.samples, "would hold the samples file"),
    "reconstruct-many: a capture of its captures": lambda c, i: (
        ["reconstruct-many", c.parent], c, c.parent, "would lie inside the captures folder"),
    "reconstruct-many: inside its captures": lambda c, i: (
        ["reconstruct-many", c.parent], c.parent / "recon", c.parent, "would lie inside the captures folder"),
    "rig export: the rig itself": lambda c, i: (
        ["rig", "export", c / "rig", "--force"], c / "rig", c / "rig", "would be the rig being exported"),
    "rig export: holding the rig": lambda c, i: (
        ["rig", "export", c / "rig", "--force"], c, c / "rig", "would hold the rig being exported"),
    "calibrate: holding --rig": lambda c, i: (
        ["calibrate", "cameras", "--rig", c / "rig"], c, c / "rig", "would hold the nominal rig's folder"),
    "validate: inside --rig": lambda c, i: (
        ["validate", "--rig", c / "rig"], c / "rig" / "v", c / "rig", "would lie inside the rig folder"),
    "validate --suite: inside a sample": lambda c, i: (
        ["validate", "--suite", c / "ground_truth" / "maps"], c / "ground_truth" / "maps" / "v",
        c / "ground_truth" / "maps", "would lie inside the maps of sample"),
    "design evaluate: holding the design": lambda c, i: (
        ["design", "evaluate", i.design], i.design.parent, i.design, "would hold the design file"),
    "design optimise: the design itself": lambda c, i: (
        ["design", "optimise", i.design], i.design, i.design, "would be the design file"),
    "train: the rig itself": lambda c, i: (
        ["train", "--rig", c / "rig"], c / "rig", c / "rig", "would be the rig folder"),
}


@pytest.mark.parametrize("case", INPUTS)
def test_an_input_or_what_holds_it_is_refused(case, capture_copy, inputs, cli):
    args, out, source, message = INPUTS[case](capture_copy, inputs)
    _refused(cli, [*args, "-o", out], out, message, source)


def _folder_with(tmp_path: Path, name: str, files: dict) -> Path:
    out = tmp_path / name
    for rel, text in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(text)
    return out


RIG = {"rig.toml": "format = 'hemicube-rig'\n"}
CAPTURE_MANY = {"batch.json": json.dumps({"samples": "s.toml", "outcomes": []})}
RECONSTRUCT_MANY = {"batch.json": json.dumps({"captures": "caps", "outcomes": []})}
VALIDATE = {"capture/manifest.json": "{}", "report/report.md": "mine"}
SUITE = {"ramps/capture/manifest.json": "{}", "report/report.md": "mine"}

# another command's kind of folder, or its own kind where it replaces it only with --force: (command, files)
OTHER_KINDS = {
    "rig export --force over a capture": ("rig export --force", {"manifest.json": "{}"}, "is not a rig folder"),
    "rig export without --force over a rig": (["rig", "export", "mini"], RIG, "pass --force"),
    "calibrate over a rig folder": ("calibrate", RIG, "is not a calibration folder"),
    "capture-many over reconstruct-many's": ("capture-many", RECONSTRUCT_MANY, "is not a capture-many folder"),
    "reconstruct-many over capture-many's": ("reconstruct-many", CAPTURE_MANY, "is not a reconstruct-many folder"),
    "validate over a suite's": ("validate", SUITE, "is not a validate folder"),
    "validate --suite over a validate folder": ("validate --suite", VALIDATE, "is not a validate --suite folder"),
    "reconstruct over a calibration": ("reconstruct", {"report.json": "{}"}, "is not a reconstruction folder"),
}


@pytest.mark.parametrize("case", OTHER_KINDS)
def test_another_kind_of_folder_is_refused(case, inputs, tmp_path, cli):
    command, files, message = OTHER_KINDS[case]
    out = _folder_with(tmp_path, "out", files)
    args = COMMANDS[command](inputs) if isinstance(command, str) else command
    _refused(cli, [*args, "-o", out], out, message)


@pytest.mark.parametrize("command, files", [("reconstruct", {"reconstruction.json": "{}"}),
                                            ("rig export --force", RIG)])
def test_its_own_kind_holding_a_link_is_refused(command, files, inputs, tmp_path, cli):
    out = _folder_with(tmp_path, "out", files)
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", out / "data")
    _refused(cli, [*COMMANDS[command](inputs), "-o", out], out, "a symbolic link inside")


def test_an_output_that_is_a_link_is_written_where_it_points(tmp_path, cli):
    """A scratch disk's folder reached through a link: written there, the link kept, nothing hidden beside."""
    target = tmp_path / "scratch" / "rig"
    target.mkdir(parents=True)
    link = tmp_path / "rig"
    os.symlink(target, link)
    assert cli("rig", "export", "mini", "-o", link) == (0, [])
    assert cli("rig", "export", "mini", "-o", link, "--force") == (0, [])
    assert link.is_symlink() and (target / "rig.toml").is_file()
    assert sorted(os.listdir(tmp_path)) == ["rig", "scratch"]
    assert os.listdir(target.parent) == ["rig"]
