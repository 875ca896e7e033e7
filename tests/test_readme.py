"""Every command line in the README is run by a CPU test (tests/test_readme_tour.py runs the untagged ones, in order)
or tagged with why not (`# [cuda]`, `[hardware]`, `[reference]`, `[long]`); every `hemicube` line, tagged or not,
parses with the command's own parser, so a renamed option in the README fails here, not in a user's shell."""
from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TAGS = {"cuda": "needs an NVIDIA GPU", "hardware": "needs the real device",
        "reference": "needs the released reference data", "long": "minutes on two cores, or a file of your own"}
TAG = re.compile(r"#\s*\[(\w+)\]")


@dataclass(frozen=True)
class Command:
    line: int  # 1-based, in README.md
    text: str  # the command, continuation lines joined, without its comment
    tag: str | None


def readme_commands(path: Path = README) -> list[Command]:
    """The command lines of the README's ```bash blocks, in order: backslash continuations joined, comments split off
    (a tag is the comment's first word in brackets), blank and comment-only lines skipped."""
    out, block, pending, start = [], False, "", 0
    for k, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if raw.startswith("```"):
            block = raw.strip() == "```bash"
            continue
        if not block or (not pending and (not raw.strip() or raw.lstrip().startswith("#"))):
            continue
        start = start or k
        code, hash_, comment = raw.partition(" #")
        if code.rstrip().endswith("\\"):
            pending += code.rstrip()[:-1] + " "
            continue
        m = TAG.match("#" + comment) if hash_ else None
        out.append(Command(start, " ".join((pending + code).split()), m.group(1) if m else None))
        pending, start = "", 0
    return out


def hemicube_argv(text: str) -> list[list[str]]:
    """The argument lists of the `hemicube` invocations in a command line (several where `;` joins them; that of
    `python -m hemicube.cli` under torchrun too)."""
    out = []
    for part in text.rstrip("&").split(";"):
        words = shlex.split(part)
        for k, w in enumerate(words):
            if Path(w).name == "hemicube":
                out.append(words[k + 1:])
                break
            if w == "hemicube.cli" and k and words[k - 1] == "-m":
                out.append(words[k + 1:])
                break
    return out


COMMANDS = readme_commands()


def test_the_readme_has_commands_and_every_tag_is_known():
    assert len(COMMANDS) > 30 and sum(c.tag is None for c in COMMANDS) >= 8
    unknown = [f"README.md:{c.line}: [{c.tag}]" for c in COMMANDS if c.tag is not None and c.tag not in TAGS]
    assert not unknown, f"tags are {sorted(TAGS)}: {unknown}"


def test_a_line_neither_run_nor_tagged_fails(tmp_path):
    """The parser sees what the tour would run: an untagged line is run (and fails there if it cannot run on a CPU);
    a tagged one is left to its tag."""
    readme = tmp_path / "README.md"
    readme.write_text("```bash\nhemicube bench lumitexel --device cuda   # JSON\nhemicube rig info mini   # [long]\n"
                      "hemicube capture --rig mini \\\n    --seed 1 -o s   # [cuda] x\n```\n")
    got = readme_commands(readme)
    assert [(c.text, c.tag) for c in got] == [("hemicube bench lumitexel --device cuda", None),
                                              ("hemicube rig info mini", "long"),
                                              ("hemicube capture --rig mini --seed 1 -o s", "cuda")]
    assert got[2].line == 4


def test_a_cuda_command_is_tagged_so():
    untagged = [f"README.md:{c.line}: {c.text}" for c in COMMANDS if "--device cuda" in c.text and c.tag is None]
    assert not untagged, untagged


@pytest.mark.parametrize("command", [c for c in COMMANDS if hemicube_argv(c.text)],
                         ids=lambda c: f"README.md:{c.line}")
def test_every_hemicube_line_parses(command, capsys):
    from hemicube.cli import build_parser

    parser = build_parser()
    for argv in hemicube_argv(command.text):
        try:
            parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"README.md:{command.line}: {' '.join(argv)}: {capsys.readouterr().err.strip()}")


def test_every_make_target_exists():
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))
    for c in COMMANDS:
        if c.text.startswith("make "):
            assert c.text.split()[1] in targets, f"README.md:{c.line}: {c.text}"
