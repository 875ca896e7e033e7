"""The main job, `hemicube validate`: simulate, reconstruct, score, with the mini rig's thresholds (CI).

The thresholds themselves live in reconstruction.validation.THRESHOLDS and docs/accuracy.md; this test runs
the README's command (on the session's shared capture, resumed) and checks that it passes them, prints the
table, and writes the report. A second run on a map folder (`--sample DIR`) checks that any OpenSVBRDF map
folder goes through the same path. The material suite and its held-back samples run once, two at a time,
and each is held to the mini rig's goals (issue #14).
"""
from __future__ import annotations

import json

import pytest

import hemicube.cli
from reconstruction.validation import thresholds_for
from twin.materials.samples import SUITE, load_sample, write_maps


def test_main_job_passes_its_thresholds(validate_dir, capsys):
    rc = hemicube.cli.main(["validate", "-o", str(validate_dir), "--no-progress"])
    out = capsys.readouterr().out
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
    assert sorted(p.name for p in (validate_dir / "report" / "images").iterdir())


def test_validate_any_map_folder(tmp_path, capsys):
    """`--sample DIR`: a folder of OpenSVBRDF maps (here brushed_metal written out), at a small grid: it is
    held to the rig's goals (reconstruction.validation.GOALS: never to no thresholds), and the exit code says
    whether it met them."""
    from reconstruction.validation import GOALS

    maps = write_maps(load_sample("brushed_metal", resolution=64), tmp_path / "maps")
    out = tmp_path / "v"
    rc = hemicube.cli.main(["validate", "--sample", str(maps), "--resolution", "16", "-o", str(out), "--no-progress",
                            "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert [r["metric"] for r in doc["thresholds"]] == [g.metric for g in GOALS["mini"]]
    assert rc == (0 if doc["passed"] else 1)
    assert doc["metrics"]["maps"]["normal_deg"]["median"] >= 0
    assert (out / "report" / "report.md").is_file()


# --- the material suite (issue #14) ---------------------------------------------------------------------
# The held-back samples (issue #14 item 3): other seeds, i.e. other compositions of every other suite category,
# chosen before any of them was run; the tuning never looked at them.
HELD_BACK = tuple(f"{name}@{9001 + k}" for k, name in enumerate(SUITE) if k % 2 == 0)
# Samples that miss the goals today, and why (docs/accuracy.md, "Open"): (reason, strict). Strict: one that starts
# passing fails here until it is taken off this list. Fabric sits at the goal's edge (alpha_y 10.2% against 10%),
# where another machine's float rounding may tip it either way, so it is reported (xfail/xpass), not enforced.
KNOWN_OPEN = {
    "paper": ("a rough, weak lobe on bright stock (rho_s/rho_d ~ 0.2/0.85: 0.5% of a photo) whose alpha moves "
              "with 0.05% photometric errors (neighbour spill, noise): alpha 22-52%; docs/accuracy.md", True),
    "fabric": ("a rough, weak, mildly anisotropic lobe (0.5-2% of a photo): alpha_y 10.2% at the 10% goal; "
               "docs/accuracy.md", False),
}


@pytest.fixture(scope="module")
def suite_run(tmp_path_factory):
    """`hemicube validate --suite` on the suite and the held-back samples: one run, two workers (CI's cores)."""
    from hemicube.validate import suite_results

    return suite_results(list(SUITE) + list(HELD_BACK), output=tmp_path_factory.mktemp("suite"), jobs=2)


def _open(name: str):
    known = KNOWN_OPEN.get(name.partition("@")[0])
    return pytest.param(name, marks=pytest.mark.xfail(strict=known[1], reason=known[0])) if known else name


@pytest.mark.parametrize("name", [_open(n) for n in SUITE + HELD_BACK])
def test_suite_sample_meets_the_goals(suite_run, name):
    """Every suite and held-back sample at the mini rig's goals (reconstruction.validation.GOALS), never at
    thresholds measured on itself."""
    r = next(r for r in suite_run["samples"] if r["sample"] == name)
    assert "error" not in r, r.get("error")
    assert [row["metric"] for row in r["rows"]] == [g.metric for g in thresholds_for("mini", None, name)]
    missed = {row["metric"]: row["value"] for row in r["rows"] if not row["passed"]}
    assert r["passed"] and not missed, missed


def test_suite_report_and_table(suite_run):
    from hemicube.validate import suite_table

    assert all(c.passed for c in suite_run["checks"])
    table = suite_table(suite_run["samples"])
    assert all(name in table for name in SUITE + HELD_BACK)
    report = suite_run["report"]  # OUTPUT/report/report.md
    assert report.name == "report.md" and all(name in report.read_text() for name in SUITE + HELD_BACK)
    assert len(list(report.parent.rglob("*.png"))) >= len(SUITE + HELD_BACK)


def test_paper_rig_goals_are_the_suites_and_the_latent_render():
    """The paper rig is held to the suite's goals and to issue #13's SSIM >= 0.98 of the latent render,
    whatever the sample or grid (no paper-rig measurement sets them)."""
    from reconstruction.validation import GOALS, thresholds_for

    paper = thresholds_for("paper", 1024, "ramps")
    assert [t.metric for t in paper] == [t.metric for t in GOALS["mini"]] + ["render.latent.ssim"]
    assert paper[-1].op == ">=" and paper[-1].value == 0.98
    assert thresholds_for("no such rig", 64, "satin") == []


def test_paper_rig_on_the_cpu_says_how_long_instead_of_running(tmp_path, capsys):
    """Issue #13 item 5: `hemicube validate --rig paper` on the CPU stops at once with a timed estimate (hours)
    and what to do, in one line, and makes no folder."""
    rc = hemicube.cli.main(["validate", "--rig", "paper", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0, err
    hours = float(err.split("would take about ")[1].split(" h")[0])
    assert hours > 1 and "--device cuda" in err and "--anyway" in err
    assert not (tmp_path / "out").exists()

