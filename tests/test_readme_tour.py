"""The README's untagged command lines, run as written, in order, in one folder, on the CPU: what a new user pastes
(tests/test_readme.py checks that every other line is tagged with why it is not run here). Each line must exit 0;
the files the tour names must then exist. The README's Python example runs too."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from tests.test_readme import README, readme_commands

BIN = Path(sys.executable).parent  # the environment running the tests: its `hemicube` is the README's .venv/bin one


def test_every_untagged_readme_command_runs(tmp_path):
    commands = [c for c in readme_commands() if c.tag is None]
    assert commands
    for c in commands:
        text = c.text.replace(".venv/bin/", f"{BIN}/")
        r = subprocess.run(["bash", "-c", text], cwd=tmp_path, capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, f"README.md:{c.line}: {c.text}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
    # what the tour says it writes
    for name in ("mini_rig/rig.toml", "rig.glb", "rig.png", "session/manifest.json", "cross.png", "rig.html",
                 "recon", "run/patterns.npz", "learned.png"):
        assert (tmp_path / name).exists(), name


def test_the_readme_python_example_runs(tmp_path):
    text = README.read_text(encoding="utf-8")
    (code,) = re.findall(r"```python\n(.*?)```", text, re.S)
    code += "\nassert m.shape == (1, rig.num_leds, 3) and B.shape == (1, 64, 3), (m.shape, B.shape)\n"
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
