"""The command line's conventions (README, "Exit codes"): one exit-code table for every command, shown by `--help`;
a device this machine lacks and a suite sample that does not exist refused in one line before any work; suite runs
of different samples in different default folders."""
from __future__ import annotations

import io
import subprocess
import sys
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


def _seed_options(parser, path=()):
    """(command words, the --seed action, its parser) for every sub-command, through nested sub-parsers."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _seed_options(sub, (*path, name))
        elif "--seed" in action.option_strings:
            yield " ".join(path), action, parser


def test_every_seed_option_has_the_one_default():
    """Every command's --seed defaults to DEFAULT_SEED. None only where the seed is inherited, and then its help says
    from what ("default: taken from ..."), or where the bench function's own default applies (cmd_bench_pipeline:
    no option there has a parser default), which must be DEFAULT_SEED and named so in the help."""
    import importlib
    import inspect

    from reconstruction.cli import BENCH_PIPELINE, cmd_bench_pipeline
    from twin.capture.plan import DEFAULT_SEED

    found, wrong = [], []
    for cmd, action, parser in _seed_options(hemicube.cli.build_parser()):
        found.append(cmd)
        if action.default == DEFAULT_SEED:
            continue
        if action.default is None and parser.get_default("func") is cmd_bench_pipeline:
            module, function, _ = BENCH_PIPELINE[cmd.split()[-1]]
            fn = getattr(importlib.import_module(f"reconstruction.bench.{module}"), function)
            if inspect.signature(fn).parameters["seed"].default == DEFAULT_SEED \
                    and f"(default: {DEFAULT_SEED})" in action.help:
                continue
        elif action.default is None and "(default: taken from " in (action.help or ""):
            continue
        wrong.append((cmd, action.default, action.help))
    assert not wrong, wrong
    assert {"capture", "validate", "train", "calibrate", "controller serve", "bench resume", "bench e2e",
            "design optimise"} <= set(found), found


def test_help_imports_neither_torch_nor_warp():
    """`hemicube --help` parses with the front alone (hemicube.cli.overview_parser): a fresh process that prints it has
    imported neither torch nor Warp, and it lists every command the whole parser has, with the same help."""
    code = ("import sys, hemicube.cli as c\ntry:\n    c.main(['--help'])\nexcept SystemExit as e:\n    assert e.code == 0\n"
            "print(sorted(m for m in ('torch', 'warp') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip().splitlines()[-1] == "[]", r.stdout[-2000:] + r.stderr[-2000:]

    def commands(parser):
        sub = next(a for a in parser._actions if a.dest == "command")
        return [(c.dest, c.help) for c in sub._choices_actions]

    assert commands(hemicube.cli.overview_parser()) == commands(hemicube.cli.build_parser())


@pytest.mark.parametrize("argv", [["rig", "info", "mini"], ["samples", "list"], ["show", "rig", "--rig", "mini",
                                                                              "--html", "rig.html"]])
def test_commands_that_need_neither_import_neither_torch_nor_warp(argv, tmp_path):
    """A command parses with its own package's options alone (hemicube.cli.owner): in a fresh process, the rig's,
    the samples' and the page's commands run without importing torch or Warp."""
    code = (f"import sys, hemicube.cli as c\nassert c.main({argv!r}) == 0\n"
            "print(sorted(m for m in ('torch', 'warp') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.strip().splitlines()[-1] == "[]", r.stdout[-2000:] + r.stderr[-2000:]


def test_each_command_parses_alike_with_its_own_package_or_all():
    """The parser built for one command (owner) gives the same namespace as the whole parser, for a command of each
    package, the front's own and the benches; an unknown name gets the whole parser, so its error lists every
    command."""
    cases = [["rig", "info", "mini"], ["reconstruct", "cap", "-o", "r"], ["calibrate", "cameras", "-o", "c"],
             ["design", "evaluate", "a.toml", "-o", "o"], ["validate", "--sample", "paper"],
             ["bench", "lumitexel", "--points", "4"], ["bench", "e2e", "--tiny"]]
    whole = hemicube.cli.build_parser()
    for argv in cases:
        own = vars(hemicube.cli.build_parser(argv[0]).parse_args(argv))
        full = vars(whole.parse_args(argv))
        assert own.keys() == full.keys() and all(own[k] == full[k] for k in own if k != "func"), argv
        assert getattr(own["func"], "__qualname__", None) == getattr(full["func"], "__qualname__", None), argv
    assert hemicube.cli.owner("nosuch") == hemicube.cli.PACKAGES


def test_junit_reads_back_with_a_junit_reader(tmp_path):
    """hemicube.junit's document, read by junitparser as a CI system reads it: a case per check and threshold, a
    missed one a failure with its message, a sample that did not finish an error."""
    from junitparser import Error, Failure, JUnitXml

    from hemicube.junit import write_junit

    cases = [{"name": "maps.alpha_x_pct.median", "passed": True, "message": "4.1 <= 10"},
             {"name": "novel.ssim.worst", "passed": False, "message": "0.80 >= 0.9 (goal)"}]
    path = write_junit(tmp_path / "r.xml", [("hemicube validate mini/metal", cases),
                                            ("hemicube validate mini/x", [{"name": "run", "passed": False,
                                                                           "error": "ValueError: no"}])])
    suites = list(JUnitXml.fromfile(str(path)))
    assert [(s.name, s.tests, s.failures, s.errors) for s in suites] == [
        ("hemicube validate mini/metal", 2, 1, 0), ("hemicube validate mini/x", 1, 0, 1)]
    results = {c.name: c.result for s in suites for c in s}
    assert results["maps.alpha_x_pct.median"] == []
    assert isinstance(results["novel.ssim.worst"][0], Failure) and "0.80" in results["novel.ssim.worst"][0].message
    assert isinstance(results["run"][0], Error)


@pytest.mark.parametrize("where", ["missing/r.xml", "."])
def test_a_junit_file_that_cannot_be_written_is_refused_before_any_work(where, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = hemicube.cli.main(["validate", "--junit", str(tmp_path / where), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == EXIT_USAGE and len(err) == 1 and err[0].startswith("hemicube: error: --junit"), err
    assert list(tmp_path.iterdir()) == []


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_is_drawn_on_a_terminal_and_quiet_in_a_log():
    """twin.progress.progress_bar: a log (a stream that is no terminal) gets nothing, where a bar updated per photo
    would add a line each; a terminal gets the bar; --no-progress (enabled=False) silences both."""
    from twin.progress import progress_bar

    def drawn(stream, enabled=True) -> str:
        for _ in progress_bar(range(5), enabled=enabled, file=stream, desc="capture", mininterval=0):
            pass
        return stream.getvalue()

    assert drawn(io.StringIO()) == ""
    assert "capture" in drawn(_Terminal()) and "5/5" in drawn(_Terminal())
    assert drawn(_Terminal(), enabled=False) == ""


def test_the_readme_tours_show_pattern_reads_its_capture(validate_dir, tmp_path):
    """README's tour shows a pattern file that exists on a fresh clone: the one its own capture wrote (a capture
    folder holds its pattern set), after that capture's line. Here the session's capture stands for the tour's."""
    import shlex

    lines = [line.split("#")[0].strip() for line in README.read_text().splitlines()]
    show = next(k for k, line in enumerate(lines) if line.startswith(".venv/bin/hemicube show pattern"))
    capture = next(k for k, line in enumerate(lines) if line.startswith(".venv/bin/hemicube capture "))
    argv = shlex.split(lines[show])[1:]
    tour_capture = shlex.split(lines[capture])
    session = tour_capture[tour_capture.index("-o") + 1]
    assert capture < show and argv[2] == f"{session}/patterns.npz", (lines[capture], lines[show])
    argv[2] = str(validate_dir / "capture" / "patterns.npz")
    argv[argv.index("-o") + 1] = str(tmp_path / "cross.png")
    assert hemicube.cli.main(argv) == 0
    assert list(tmp_path.glob("cross*.png")), list(tmp_path.iterdir())


def test_the_long_stages_show_progress_on_a_terminal_and_none_in_a_log(validate_dir, tmp_path):
    """`hemicube reconstruct` in a terminal (a pseudo-terminal of 120 columns here) draws a bar for the photos'
    extraction, fine-tuning and fitting (a log gets none: test_progress_is_drawn_on_a_terminal_and_quiet_in_a_log)."""
    import fcntl
    import os
    import pty
    import struct
    import termios
    import threading

    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    seen = bytearray()

    def drain():  # read as the command writes: a full terminal buffer would stop it
        while True:
            try:
                chunk = os.read(leader, 1 << 16)
            except OSError:  # the terminal closed
                return
            if not chunk:
                return
            seen.extend(chunk)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        argv = ["reconstruct", str(validate_dir / "capture"), "-o", str(tmp_path / "out"), "--resolution", "12"]
        assert subprocess.run([sys.executable, "-m", "hemicube.cli", *argv], stdout=subprocess.DEVNULL,
                              stderr=follower, timeout=900).returncode == 0
    finally:
        os.close(follower)
        reader.join(timeout=10)
        os.close(leader)
    for bar in (b"extract:", b"fine-tuning:", b"fitting:"):
        assert bar in seen, bytes(seen[-2000:])


def test_one_meaning_per_option_name_with_the_old_name_kept_a_version(capsys):
    """--resolution is the texture grid (reconstruct, validate); the sample's maps are --sample-resolution (capture,
    bench capture). Capture's old --resolution still works for one version, with one line saying so."""
    parser = hemicube.cli.build_parser()
    assert parser.parse_args(["capture", "-o", "x", "--sample-resolution", "32"]).resolution == 32
    assert capsys.readouterr().err == ""
    assert parser.parse_args(["capture", "-o", "x", "--resolution", "32"]).resolution == 32
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--resolution is deprecated: use --sample-resolution" in err[0], err
    assert parser.parse_args(["bench", "capture", "--sample-resolution", "64"]).resolution == 64
    assert parser.parse_args(["reconstruct", "c", "-o", "x", "--resolution", "12"]).resolution == 12
    assert capsys.readouterr().err == ""


def test_capture_many_samples_file_says_sample_resolution_with_the_old_key_kept_a_version(tmp_path, capsys):
    """SAMPLES.toml's `sample_resolution` is `capture --sample-resolution`; its old name `resolution` still reads
    (top level or per sample) with one line on stderr; both names in one table are refused, naming both."""
    from twin.capture.many import read_samples

    def samples(text: str) -> list[dict]:
        (tmp_path / "s.toml").write_text(text)
        return read_samples(tmp_path / "s.toml")

    body = '[[sample]]\nname = "ramps"\n[[sample]]\nname = "satin@5"\n'
    new = samples("sample_resolution = 32\n" + body)
    assert [s["sample_resolution"] for s in new] == [32, 32] and capsys.readouterr().err == ""
    assert samples("resolution = 32\n" + body) == new
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'resolution' is deprecated: use 'sample_resolution'" in err[0], err
    assert [s["sample_resolution"] for s in samples(body + "resolution = 16\n")] == [128, 16]
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    for text in ("resolution = 32\nsample_resolution = 32\n" + body,
                 body + "resolution = 16\nsample_resolution = 16\n"):
        with pytest.raises(ValueError, match="both 'resolution' and 'sample_resolution'"):
            samples(text)
    with pytest.raises(ValueError, match="sample_resolution must be a positive integer"):
        samples("sample_resolution = 0\n" + body)


def test_raw_frames_are_written_on_request(tmp_path):
    """`capture --raw` and SAMPLES.toml's `raw = true` (per sample or for all) keep the raw frames; off by default;
    a `raw` that is not a boolean, like an unknown key, is refused in one line."""
    from twin.capture.many import read_samples

    parser = hemicube.cli.build_parser()
    assert parser.parse_args(["capture", "-o", "x"]).raw is False
    assert parser.parse_args(["capture", "-o", "x", "--raw"]).raw is True

    def samples(text: str) -> list[dict]:
        (tmp_path / "s.toml").write_text(text)
        return read_samples(tmp_path / "s.toml")

    body = '[[sample]]\nname = "ramps"\n[[sample]]\nname = "satin@5"\nraw = true\n'
    assert [s["raw"] for s in samples(body)] == [False, True]
    assert [s["raw"] for s in samples("raw = true\n" + body)] == [True, True]
    with pytest.raises(ValueError, match=r"\[\[sample\]\] 1 \(ramps\): raw must be true or false"):
        samples('[[sample]]\nname = "ramps"\nraw = "yes"\n')
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['raws'\]"):
        samples('[[sample]]\nname = "ramps"\nraws = true\n')


def test_a_missing_device_is_one_line_in_a_fresh_process(tmp_path):
    """As a user meets it: a new process, where Warp looks for CUDA for the first time and says so on its own; the
    command's stderr is still the one line (the Ray batch commands' --device is the cluster's: not checked here)."""
    r = subprocess.run([sys.executable, "-m", "hemicube.cli", "validate", "--device", "cuda:99", "-o",
                        str(tmp_path / "out")], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    err = r.stderr.strip().splitlines()
    assert r.returncode == EXIT_USAGE and len(err) == 1 and "unknown device 'cuda:99'" in err[0], r.stderr
    assert list(tmp_path.iterdir()) == []
