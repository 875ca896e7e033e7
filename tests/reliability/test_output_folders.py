"""`hemicube reconstruct -o` owns its output folder and never clobbers another (reconstruction.pipeline.check_output):
a user's folder, a file, the capture being read and a folder inside it are refused by name, in one line, before
anything is written, and stay as they were; an empty folder is filled."""
from __future__ import annotations

from pathlib import Path

import hemicube.cli
from twin.capture.session import CaptureSession

from tests.reliability.conftest import digest


def _refused(capsys, capture: Path, out: Path, message: str) -> None:
    before_cap = digest(capture)
    rc = hemicube.cli.main(["reconstruct", str(capture), "-o", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and message in err[0] and str(out) in err[0], err
    assert digest(capture) == before_cap
    assert CaptureSession.open(capture).verify() == []
    # nothing written beside the output either: no stage folder, no temporary or hidden copy
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


def test_a_users_folder_is_refused_and_kept(capture, tmp_path, capsys):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"not ours")
    _refused(capsys, capture, out, "is not a reconstruction folder")
    assert (out / "holiday.jpg").read_bytes() == b"not ours"


def test_a_file_is_refused_and_kept(capture, tmp_path, capsys):
    out = tmp_path / "notes.txt"
    out.write_text("keep me")
    _refused(capsys, capture, out, "is not a folder")
    assert out.read_text() == "keep me"


def test_the_capture_itself_is_refused(capture, capsys):
    _refused(capsys, capture, capture, "the capture being read")


def test_a_folder_inside_the_capture_is_refused(capture, capsys):
    out = capture / "recon"
    _refused(capsys, capture, out, "the capture being read")
    assert not out.exists()


def test_a_folder_holding_the_capture_is_refused(capture, capsys):
    _refused(capsys, capture, capture.parent, "the capture being read")


def test_an_empty_folder_is_accepted(capture, tmp_path):
    from reconstruction.pipeline import check_output

    out = tmp_path / "empty"
    out.mkdir()
    check_output(out, capture)  # no error: an empty folder holds nothing to lose
    check_output(tmp_path / "absent", capture)
