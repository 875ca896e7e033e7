"""The main job, `hemicube validate`: simulate, reconstruct, score, with the mini rig's thresholds (CI).

The thresholds themselves live in reconstruction.evaluation.validation.THRESHOLDS and docs/accuracy.md; this test runs
docs/ci.md's example job's command, the README's plus --junit (on the session's shared capture, resumed), and checks
that it passes them, prints the table, and writes the report and the JUnit file. A second run on a map folder
(`--sample DIR`) checks that any OpenSVBRDF map folder goes through the same path. The material suite is
tests/hemicube/test_validate_suite.py.
"""
from __future__ import annotations

import json
from pathlib import Path

import hemicube.cli
from reconstruction.stages.fitting import FitConfig
from reconstruction.evaluation.validation import thresholds_for
from twin.capture.plan import DEFAULT_FRAMES
from twin.materials.samples import load_sample, write_maps


CI_DOC = Path(__file__).resolve().parents[2] / "docs" / "ci.md"


def ci_example_command() -> list[str]:
    """docs/ci.md's example job: its `hemicube validate` step as arguments (after `hemicube`); the job sets up with
    the README's `make setup`."""
    import shlex

    import yaml

    block = CI_DOC.read_text().split("```yaml\n", 1)[1].split("```", 1)[0]
    runs = [step["run"] for step in yaml.safe_load(block)["jobs"]["validate"]["steps"] if "run" in step]
    (command,) = [r for r in runs if "hemicube validate" in r]
    assert runs[0] == "make setup", runs
    argv = shlex.split(command)
    assert argv[0] == ".venv/bin/hemicube", argv
    return argv[1:]


def test_main_job_passes_its_thresholds(validate_dir, capsys, tmp_path):
    """The main job as docs/ci.md's example job runs it (its folders moved into the test's): every threshold met, the
    report complete, and its JUnit file read back as a CI system reads it."""
    from junitparser import JUnitXml

    argv = ci_example_command()
    moved = {"-o": str(validate_dir), "--junit": str(tmp_path / "junit.xml")}
    argv = [moved.get(argv[k - 1], a) if k else a for k, a in enumerate(argv)]
    assert set(moved.values()) <= set(argv), argv
    rc = hemicube.cli.main(argv)
    out = capsys.readouterr().out
    (suite,) = JUnitXml.fromfile(moved["--junit"])
    assert suite.failures == 0 and suite.errors == 0 and suite.tests > len(thresholds_for("mini"))
    assert "PASS" in out and "FAIL" not in out, out
    assert rc == 0, out
    doc = json.loads((validate_dir / "report" / "metrics.json").read_text())
    metrics = doc["metrics"]
    assert doc["passed"] is True and len(doc["checks"]) == len(thresholds_for("mini"))
    report = (validate_dir / "report" / "report.md").read_text()
    rows = thresholds_for("mini")
    assert len(rows) >= 6 and all(r.metric.split(".")[0] in metrics for r in rows)
    for r in rows:
        assert r.metric in report
    assert (validate_dir / "reconstruction" / "maps" / "normal_texture.exr").is_file()
    assert (validate_dir / "reconstruction" / "latent.exr").is_file()
    images = {p.name for p in (validate_dir / "report" / "images").iterdir()}
    assert {"novel_views.png", "novel_worst.png"} <= images
    # the novel views (reconstruction.evaluation.novel_views): every pair in metrics.json, the summary printed
    assert len(metrics["novel"]["pairs"]) == 560 and "novel views: SSIM mean" in out
    assert "novel.pairs = 560 rows (metrics.json)" in report
    # the photos' weight in the fit is per frame of an exposure (reconstruction.pipeline: an inverse-variance weight)
    fit = json.loads((validate_dir / "reconstruction" / "reconstruction.json").read_text())["fit"]["config"]
    assert fit["lambda_lines"] == FitConfig().lambda_lines * DEFAULT_FRAMES


def _not_json(token: str):
    raise AssertionError(f"{token} is not JSON")


def test_validate_any_map_folder(tmp_path, capsys):
    """`--sample DIR`: a folder of OpenSVBRDF maps (here brushed_metal written out), at a small grid: it is
    held to the rig's goals (reconstruction.evaluation.validation.GOALS: never to no thresholds), and the exit code says
    whether it met them."""
    from reconstruction.evaluation.validation import GOALS

    maps = write_maps(load_sample("brushed_metal", resolution=64), tmp_path / "maps")
    out = tmp_path / "v"
    rc = hemicube.cli.main(["validate", "--sample", str(maps), "--resolution", "16", "-o", str(out), "--no-progress",
                            "--json", "--junit", str(tmp_path / "junit.xml")])
    doc = json.loads(capsys.readouterr().out, parse_constant=_not_json)  # strict JSON: no NaN, no Infinity
    assert [r["metric"] for r in doc["thresholds"]] == [g.metric for g in GOALS["mini"]]
    assert all(isinstance(v, str) for v in doc["report"]["images"].values())  # paths as strings, not reprs
    assert rc == (0 if doc["passed"] else 1)
    assert doc["metrics"]["maps"]["normal_deg"]["median"] >= 0
    assert (out / "report" / "report.md").is_file()
    # --junit: a test case per check and threshold, read as a CI system reads it (failures where the JSON misses)
    from junitparser import JUnitXml

    (suite,) = JUnitXml.fromfile(str(tmp_path / "junit.xml"))
    cases = {c.name: bool(c.result) for c in suite}
    assert len(cases) == len(doc["checks"]) + len(doc["thresholds"])
    assert {r["metric"]: not r["passed"] for r in doc["thresholds"]}.items() <= cases.items()


def test_paper_rig_goals_are_the_suites_and_the_latent_render():
    """The paper rig is held to the suite's goals and to the paper's SSIM >= 0.98 of the latent render,
    whatever the sample or grid (no paper-rig measurement sets them)."""
    from reconstruction.evaluation.validation import GOALS, thresholds_for

    paper = thresholds_for("paper", 1024, "ramps")
    assert [t.metric for t in paper] == [t.metric for t in GOALS["mini"]] + ["render.latent.ssim"]
    assert paper[-1].op == ">=" and paper[-1].value == 0.98
    assert thresholds_for("no such rig", 64, "satin") == []


def test_paper_rig_on_the_cpu_says_how_long_instead_of_running(tmp_path, capsys):
    """`hemicube validate --rig paper` on the CPU stops at once with a timed estimate (hours)
    and what to do, in one line, and makes no folder."""
    rc = hemicube.cli.main(["validate", "--rig", "paper", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0, err
    hours = float(err.split("would take about ")[1].split(" h")[0])
    assert hours > 1 and "--device cuda" in err and "--anyway" in err
    assert not (tmp_path / "out").exists()

