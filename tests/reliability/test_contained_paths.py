"""Contained paths (twin.paths): a manifest's paths are relative, normalised and inside the folder, checked before
any open; a symbolic link inside a capture or reconstruction folder is refused by name, in one line, and never
followed on read or write; the start-up clean-up removes only what twin.atomic left. An output path that is itself a
link (a folder on a scratch disk) is written where it points."""
from __future__ import annotations

import hashlib
import os
import types

import pytest

from reconstruction.output import ReconstructionFolder, stages_folder

from tests.reliability.conftest import CAPTURE_ARGS, digest, rewrite_manifest


def test_a_raw_folder_that_is_a_link_is_refused_not_written_through(capture_copy, tmp_path, cli):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    os.rename(capture_copy / "raw", tmp_path / "raw_kept")
    (capture_copy / "raw").symlink_to(elsewhere)
    before = digest(capture_copy)
    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy)
    assert rc == 2 and len(err) == 1 and f"{capture_copy / 'raw'}: a symbolic link" in err[0], err
    assert list(elsewhere.iterdir()) == [] and digest(capture_copy) == before


@pytest.mark.parametrize("where", ["beside", "absolute", "through rig/"])
def test_manifest_paths_outside_the_folder_are_refused_before_any_open(capture_copy, tmp_path, cli, where):
    outside = tmp_path / "outside.bin"
    outside.write_bytes(b"not the capture's")
    rel = {"beside": "../outside.bin", "absolute": str(outside), "through rig/": "rig/../../outside.bin"}[where]
    rewrite_manifest(capture_copy,
                     lambda doc: doc["files"].update({rel: hashlib.sha256(outside.read_bytes()).hexdigest()}))
    before = digest(capture_copy)
    # a re-run of the capture verifies every listed file; reconstruct reads the rig/ files
    argv = (*CAPTURE_ARGS, "-o", capture_copy) if where != "through rig/" else \
        ("reconstruct", capture_copy, "-o", tmp_path / "recon", "--no-progress")
    rc, err = cli(*argv)
    assert rc == 2 and len(err) == 1 and f"{rel!r} is not a relative path inside the folder" in err[0], err
    assert digest(capture_copy) == before and not (tmp_path / "recon").exists()


@pytest.mark.parametrize("name", ["img00000_cam00.exr", "rig"])
def test_a_photo_or_rig_that_is_a_link_out_of_the_folder_is_not_read(capture_copy, tmp_path, cli, name):
    os.rename(capture_copy / name, tmp_path / name)
    (capture_copy / name).symlink_to(tmp_path / name)  # the same bytes: only the link is wrong
    out = tmp_path / "recon"
    rc, err = cli("reconstruct", capture_copy, "-o", out, "--no-progress")
    assert rc == 2 and len(err) == 1 and f"{capture_copy / name}: a symbolic link" in err[0], err
    assert not out.exists() and not stages_folder(out).exists()


def test_links_in_a_reconstruction_or_its_stage_folder_are_refused_by_name(capture, tmp_path, cli, monkeypatch):
    import reconstruction.pipeline as pipeline

    monkeypatch.setattr(pipeline, "_reconstruct_into", _summary_only)
    elsewhere, out = tmp_path / "elsewhere", tmp_path / "recon"
    elsewhere.mkdir()
    stages = stages_folder(out)
    for link, target in ((stages, elsewhere), (stages / "measurements.npz", elsewhere / "m.npz")):
        link.parent.mkdir(exist_ok=True)
        link.symlink_to(target)
        rc, err = cli("reconstruct", capture, "-o", out, "--no-progress")
        assert rc == 2 and len(err) == 1 and f"{link}: a symbolic link" in err[0], err
        assert list(elsewhere.iterdir()) == [] and not out.exists()
        link.unlink()
    stages.rmdir()
    rc, err = cli("reconstruct", capture, "-o", out, "--no-progress")
    assert rc == 0, err
    (out / "notes.txt").symlink_to(elsewhere / "notes.txt")  # what a reader of the finished folder must not follow
    with pytest.raises(ValueError, match="notes.txt: a symbolic link"):
        ReconstructionFolder(out).verify()


def test_a_hidden_link_is_refused_by_name_and_kept(capture_copy, tmp_path, cli):
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "keep.txt").write_text("mine")
    (capture_copy / ".cache").symlink_to(cache)
    before = digest(capture_copy)
    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy)
    assert rc == 2 and len(err) == 1 and f"{capture_copy / '.cache'}: a symbolic link" in err[0], err
    assert digest(capture_copy) == before and (cache / "keep.txt").read_text() == "mine"


def test_the_start_up_clean_up_removes_only_what_a_killed_writer_left(capture_copy, tmp_path, cli, monkeypatch):
    left = [capture_copy / ".img00001_cam00.exr.k2j4h5g6.exr",  # twin.atomic's names, as a SIGKILL leaves them
            capture_copy / "raw" / ".img00001_cam00_e0.BayerRG12p.a1b2c3d4.BayerRG12p"]
    for p in left:
        p.write_bytes(b"half")
    (capture_copy / ".rig.q1w2e3r4").mkdir()
    (capture_copy / ".notes").write_text("the user's")
    (capture_copy / "raw" / ".keep").write_text("the user's")
    rc, err = cli(*CAPTURE_ARGS, "-o", capture_copy)
    assert rc == 0, err
    assert sorted(p.name for p in capture_copy.rglob(".*")) == [".keep", ".notes"]

    import reconstruction.pipeline as pipeline

    out = tmp_path / "recon"
    theirs = tmp_path / ".recon.abcdefgh"  # a folder named like a temporary, beside OUT: not this program's
    theirs.mkdir()
    (theirs / "data").write_text("the user's")

    def past_the_clean_up(*a, **k):
        raise RuntimeError("past the clean-up")

    monkeypatch.setattr(pipeline, "_reconstruct_into", past_the_clean_up)
    with pytest.raises(RuntimeError, match="past the clean-up"):
        cli("reconstruct", capture_copy, "-o", out, "--no-progress")
    assert (theirs / "data").read_text() == "the user's"


def _summary_only(out, stages, session, rig, config, progress):
    """A reconstruction in name only: its summary (the paths are what is tested)."""
    out.write_summary({"capture": str(session.dir)})
    return types.SimpleNamespace(directory=out.dir, grid=types.SimpleNamespace(resolution=1, size_mm=1.0), timings={})


def test_an_output_that_is_a_link_is_written_where_it_points(capture, capture_copy, tmp_path, cli, monkeypatch):
    import reconstruction.pipeline as pipeline

    link = tmp_path / "link"
    link.symlink_to(capture_copy)
    rc, err = cli(*CAPTURE_ARGS, "-o", link)  # a capture resumed through a link to its folder
    assert rc == 0, err

    scratch, home = tmp_path / "scratch", tmp_path / "home"
    (scratch / "recon").mkdir(parents=True)  # an empty folder on the scratch disk, linked from home
    home.mkdir()
    (home / "recon").symlink_to(scratch / "recon")
    monkeypatch.setattr(pipeline, "_reconstruct_into", _summary_only)
    for _ in range(2):  # made, then replaced
        rc, err = cli("reconstruct", capture, "-o", home / "recon", "--no-progress")
        assert rc == 0, err
        assert (home / "recon").is_symlink() and ReconstructionFolder(scratch / "recon").verify() == []
        assert sorted(p.name for p in home.iterdir()) == ["recon"]
        assert sorted(p.name for p in scratch.iterdir()) == ["recon"]
