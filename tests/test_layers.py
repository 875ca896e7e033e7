"""The layout's rules, checked: layers and cycles (import-linter contracts in pyproject.toml, and a planted
violation that they catch), one owner per folder format, runtime imports declared as dependencies, a
help string for every command-line option, and `ruff check` clean ([tool.ruff] in pyproject.toml)."""
from __future__ import annotations

import argparse
import ast
import re
import shutil
import subprocess
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hemicube", "twin", "calibration", "reconstruction")
LINT = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or "lint-imports"
RUFF = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([LINT, "--no-cache", "--config", str(cwd / "pyproject.toml")], cwd=cwd,
                          env={"PYTHONPATH": str(cwd), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True)


def _sources():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            yield path


def test_import_contracts_hold():
    r = _lint(ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


@pytest.mark.parametrize("module,planted", [
    ("twin/rig/bad.py", "import reconstruction.pipeline\n"),           # the bottom package reaching up
    ("twin/optics/bad.py", "import twin.capture.runner\n"),            # a lower layer of twin reaching up
    ("reconstruction/bad.py", "import calibration\n"),                  # the two side-by-side packages
])
def test_a_planted_violation_fails(tmp_path, module, planted):
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "pretrained"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    (tmp_path / module).write_text(planted)
    r = _lint(tmp_path)
    assert r.returncode != 0 and "BROKEN" in r.stdout, r.stdout
    assert module.replace("/", ".")[:-3] in r.stdout


def test_no_import_cycles():
    """No module imports itself through others (strongly connected components of the import graph)."""
    import grimp

    g = grimp.build_graph(*PACKAGES, cache_dir=None)
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in g.find_modules_directly_imported_by(v):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while not comp or comp[-1] != v:
                comp.append(stack.pop())
                on.discard(comp[-1])
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for m in sorted(g.modules):
        if m not in index:
            visit(m)
    assert cycles == []


# every file name of the capture folder and of the reconstruction folder, and the one module that owns it
FOLDER_NAMES = {
    "manifest.json": "twin/capture/session.py", "ground_truth/": "twin/capture/session.py",
    "pixel_texel_cam": "twin/capture/session.py", "_e{j}.BayerRG12p": "twin/capture/session.py",
    "raw/": "twin/capture/session.py", "_cam{": "twin/capture/session.py",
    "reconstruction.json": "reconstruction/output.py", "alignment.npz": "reconstruction/output.py",
    "measurements.npz": "reconstruction/output.py", "latent.exr": "reconstruction/output.py",
    "latent_passes.npz": "reconstruction/output.py",
}


@pytest.mark.parametrize("name", sorted(FOLDER_NAMES))
def test_one_owner_per_folder_file_name(name):
    holders = [str(p.relative_to(ROOT)) for p in _sources() if name in p.read_text()]
    assert holders == [FOLDER_NAMES[name]]


def _third_party_imports() -> dict[str, set[str]]:
    """Top-level names of non-project, non-stdlib modules imported by the packages -> importing files."""
    found: dict[str, set[str]] = {}
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for n in names:
                top = n.split(".")[0]
                if top not in sys.stdlib_module_names and top not in PACKAGES:
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def _requirement_names(reqs) -> set[str]:
    return {re.split(r"[<>=!\[; ]", r, maxsplit=1)[0].lower().replace("_", "-") for r in reqs}


def test_runtime_imports_are_declared():
    """`pip install .` must bring what the code imports: each imported distribution is a dependency, or an
    extra (pyvista: [view]) whose absence the code reports by name."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    runtime = _requirement_names(project["dependencies"])
    extras = {name: _requirement_names(reqs) for name, reqs in project["optional-dependencies"].items()}
    dists = packages_distributions()
    missing = {}
    for top, files in _third_party_imports().items():
        names = {d.lower().replace("_", "-") for d in dists.get(top, [top])}
        if names & runtime:
            continue
        extra = [e for e, reqs in extras.items() if e != "dev" and names & reqs]
        if extra and all(f"hemicube-twin[{extra[0]}]" in (ROOT / f).read_text() for f in files):
            continue  # an optional part that names its extra where it is imported
        missing[top] = sorted(files)
    assert missing == {}


def _options(parser: argparse.ArgumentParser, prefix=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, prefix + (name,))
        elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            yield " ".join(prefix), action


def test_every_option_has_help():
    from hemicube.cli import build_parser

    bare = [f"{cmd}: {'/'.join(a.option_strings) or a.dest}" for cmd, a in _options(build_parser()) if not a.help]
    assert bare == []
    # options with a default say it
    quiet = [f"{cmd}: {'/'.join(a.option_strings)}" for cmd, a in _options(build_parser())
             if a.option_strings and a.default not in (None, False) and "default" not in a.help]
    assert quiet == []


@pytest.mark.skipif(RUFF is None, reason="ruff is not installed (it is in the dev extra: pip install -e '.[dev]')")
def test_ruff_check_is_clean():
    """`ruff check` on the whole repository, with pyproject.toml's rules (lint only: nothing is reformatted)."""
    r = subprocess.run([RUFF, "check", "--no-cache", "--output-format", "concise", str(ROOT)], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
