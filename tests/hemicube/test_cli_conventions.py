"""The command line's conventions (README, "Exit codes"): one exit-code table for every command, shown by `--help`;
a device this machine lacks and a suite sample that does not exist refused in one line before any work; suite runs
of different samples in different default folders."""
from __future__ import annotations

from pathlib import Path

import pytest

import hemicube.cli
from hemicube.validate import suite_folder_name
from twin.exitcodes import EXIT_CODES, EXIT_USAGE
from twin.materials.samples import SUITE

README = Path(__file__).resolve().parents[2] / "README.md"


def test_exit_codes_are_one_table_in_help_and_readme(capsys):
    assert sorted(EXIT_CODES) == [0, 1, 2, 3]
    with pytest.raises(SystemExit) as e:
        hemicube.cli.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    readme = README.read_text()
    for code, meaning in EXIT_CODES.items():
        assert f"  {code}  {meaning}" in out
        assert f"| {code} | {meaning} |" in readme, f"README's exit-code table lacks code {code} as --help says it"


@pytest.mark.parametrize("argv", [["validate"], ["validate", "--suite", "wood"], ["capture", "--sample", "ramps"]])
def test_a_device_this_machine_lacks_is_one_line_before_any_work(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = hemicube.cli.main(argv + ["--device", "cuda:99", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == EXIT_USAGE and len(err) == 1 and err[0].startswith("hemicube: error: unknown device 'cuda:99'"), err
    assert list(tmp_path.iterdir()) == []  # nothing written, not even the output folder


def test_an_unknown_suite_sample_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = hemicube.cli.main(["validate", "--suite", "wood", "nosuch", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == EXIT_USAGE and len(err) == 1 and "'nosuch' is neither a built-in sample" in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_suite_runs_of_different_samples_never_share_a_default_folder():
    whole = suite_folder_name("mini", SUITE, 1, 4)
    assert whole == "suite_mini_seed1_x4"  # the whole suite's folder, as before
    names = {suite_folder_name("mini", n, 1, 4) for n in (["wood"], ["nosuch"], ["wood", "paper"], ["paper", "wood"],
                                                          [f"wood@{k}" for k in range(30)],
                                                          [f"wood@{k}" for k in range(1, 31)])}
    assert len(names) == 6 and whole not in names
    assert suite_folder_name("mini", ["wood"], 1, 4) == "suite_mini_seed1_x4_wood"


def test_one_seed_default_for_every_capture():
    """`capture`, `capture-many` (a samples file without seed) and `validate` capture with the same seed unless told
    otherwise (twin.capture.plan.DEFAULT_SEED: validate's, which the documented figures use)."""
    from twin.capture.many import DEFAULTS
    from twin.capture.plan import DEFAULT_SEED

    parser = hemicube.cli.build_parser()
    seeds = {cmd: parser.parse_args([cmd] + extra).seed for cmd, extra in (("capture", ["-o", "x"]), ("validate", []))}
    assert seeds == {"capture": DEFAULT_SEED, "validate": DEFAULT_SEED} and DEFAULTS["seed"] == DEFAULT_SEED == 1
