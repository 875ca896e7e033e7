"""The material suite (docs/accuracy.md): `hemicube validate --suite` on the suite and its held-back samples, run once,
two at a time, each held to the mini rig's goals. A file of its own: the test processes (pytest-xdist) take a
file each, and the suite is the longest, so the main job's tests run beside it rather than after it.
"""
from __future__ import annotations

import json

import pytest

from reconstruction.evaluation.validation import thresholds_for
from tests.unseen_materials import UNSEEN, write_unseen
from twin.materials.samples import SUITE

# --- the material suite -----------------------------------------------------------------------------------
# The held-back samples: other seeds, i.e. other compositions of every other suite category,
# chosen before any of them was run; the tuning never looked at them.
HELD_BACK = tuple(f"{name}@{9001 + k}" for k, name in enumerate(SUITE) if k % 2 == 0)
# Samples that miss the goals today, and why (docs/accuracy.md, "Open"), by their full name: (reason, strict).
# Strict: one that starts passing fails here until it is taken off this list.
_MIXED_TEXELS = ("novel views: texels that straddle two grains or a weave's threads hold two lobes, which no single "
                 "GGX lobe a texel renders (the worst pair's error lies on the boundaries; the truth's own maps "
                 "box-filtered reach only 0.66 on woven)")
KNOWN_OPEN: dict = {"metal": (_MIXED_TEXELS, True), "woven": (_MIXED_TEXELS, True),
                    "woven@9007": (_MIXED_TEXELS, True)}


@pytest.fixture(scope="module")
def suite_run(tmp_path_factory):
    """`hemicube validate --suite` on the suite and the held-back samples: one run, two workers (CI's cores)."""
    from hemicube.validate import suite_results

    maps = tmp_path_factory.mktemp("unseen")
    folders = [write_unseen(kind, seed, maps / f"{kind}@{seed}") for kind, seed in UNSEEN]
    run = suite_results(list(SUITE) + list(HELD_BACK) + folders, output=tmp_path_factory.mktemp("suite"), jobs=2)
    for r in run["samples"]:  # a map folder's result is named by its path: by its folder's name here
        r["sample"] = r["sample"].rsplit("/", 1)[-1]
    return run


def _open(name: str):
    known = KNOWN_OPEN.get(name)
    return pytest.param(name, marks=pytest.mark.xfail(strict=known[1], reason=known[0])) if known else name


UNSEEN_NAMES = tuple(f"{kind}@{seed}" for kind, seed in UNSEEN)


@pytest.mark.parametrize("name", [_open(n) for n in SUITE + HELD_BACK + UNSEEN_NAMES])
def test_suite_sample_meets_the_goals(suite_run, name):
    """Every suite and held-back sample, and every unseen map folder (tests/unseen_materials.py, run through
    `--sample DIR` as a user would), at the mini rig's goals (reconstruction.evaluation.validation.GOALS), never at
    thresholds measured on itself; none has its alignment flagged by the check without ground truth (a flag stops
    the reconstruction: it would be an error here)."""
    r = next(r for r in suite_run["samples"] if r["sample"] == name)
    assert "error" not in r, r.get("error")
    assert [row["metric"] for row in r["rows"]] == [g.metric for g in thresholds_for("mini", None, name)]
    assert not r["metrics"]["alignment"]["check"]["flagged"]
    missed = {row["metric"]: row["value"] for row in r["rows"] if not row["passed"]}
    assert r["passed"] and not missed, missed


def test_suite_report_and_table(suite_run, tmp_path):
    from junitparser import JUnitXml

    from hemicube.junit import write_junit
    from hemicube.validate import suite_junit, suite_table

    assert all(c.passed for c in suite_run["checks"])
    table = suite_table(suite_run["samples"])
    assert all(name in table for name in SUITE + HELD_BACK)
    report = suite_run["report"]  # OUTPUT/report/report.md
    assert report.name == "report.md" and all(name in report.read_text() for name in SUITE + HELD_BACK)
    assert len(list(report.parent.rglob("*.png"))) >= len(SUITE + HELD_BACK)
    # every sample's novel views, with its worst view and light, in the report (the pairs stay in its own folder)
    names = SUITE + HELD_BACK + UNSEEN_NAMES
    assert report.read_text().count("novel views: SSIM mean") == len(names)
    assert all("pairs" not in r["metrics"]["novel"] for r in json.loads((report.parent / "metrics.json").read_text())
               ["samples"])
    # --junit: the checks, then a test suite a sample with a test case a threshold, as a CI system reads them
    suites = list(JUnitXml.fromfile(str(write_junit(tmp_path / "suite.xml", suite_junit(suite_run)))))
    assert [s.tests for s in suites] == [len(suite_run["checks"])] + [len(r["rows"]) for r in suite_run["samples"]]
    assert [s.failures for s in suites[1:]] == [sum(not row["passed"] for row in r["rows"]) for r in suite_run["samples"]]
