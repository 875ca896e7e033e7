"""What a user or a packager reads first: `hemicube --version`, LICENSE and CITATION.cff, each agreeing with
pyproject.toml."""
from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

import hemicube.cli

ROOT = Path(__file__).resolve().parents[2]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def test_version_prints_the_packages_version(capsys):
    with pytest.raises(SystemExit) as e:
        hemicube.cli.main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"hemicube {PROJECT['version']}"


def test_license_and_citation_agree_with_the_package():
    yaml = pytest.importorskip("yaml")
    assert PROJECT["license"] == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT License")
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["license"] == "MIT" and cff["version"] == PROJECT["version"]
    assert cff["title"] and cff["authors"] and cff["message"]
    paper = cff["references"][0]
    assert paper["title"].startswith("OpenSVBRDF") and paper["year"] == 2023 and paper["volume"] == 42
