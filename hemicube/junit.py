"""`hemicube validate --junit FILE`: the run's checks and thresholds as JUnit XML, the report format CI systems read
natively (GitHub Actions' test reporters, GitLab's `artifacts:reports:junit`, Jenkins' JUnit plugin; docs/ci.md).

    write_junit(path, [("hemicube validate mini/ramps", cases)])

One <testsuite> per (name, cases); one <testcase> per case {"name", "passed", "message"}: a missed check or threshold
is a <failure> with its message, a case with "error" (a suite sample that did not finish) an <error>. Written
atomically (twin.atomic), so a CI step never reads half a file.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from twin.atomic import write_bytes_atomic


def check_cases(checks) -> list[dict]:
    """The rig and forward-model checks (twin.checks.Check) as cases."""
    return [{"name": f"check: {c.name}", "passed": c.passed,
             "message": f"worst {c.worst:.3g} {c.unit} (threshold {c.threshold:g}): {c.compared}"} for c in checks]


def threshold_cases(rows) -> list[dict]:
    """A sample's threshold rows (reconstruction.evaluation.metrics.check) as cases."""
    return [{"name": r["metric"], "passed": r["passed"],
             "message": f"{r['value']} {r['op']} {r['threshold']:g} ({r.get('why', '')})"} for r in rows]


def junit_xml(suites: list[tuple[str, list[dict]]]) -> bytes:
    """The JUnit XML document (module docstring) of `suites`."""
    root = ET.Element("testsuites", name="hemicube validate")
    for name, cases in suites:
        failures = sum(1 for c in cases if not c["passed"] and "error" not in c)
        errors = sum(1 for c in cases if "error" in c)
        suite = ET.SubElement(root, "testsuite", name=name, tests=str(len(cases)), failures=str(failures),
                              errors=str(errors))
        for c in cases:
            case = ET.SubElement(suite, "testcase", classname=name, name=c["name"])
            if "error" in c:
                ET.SubElement(case, "error", message=c["error"]).text = c["error"]
            elif not c["passed"]:
                ET.SubElement(case, "failure", message=c["message"]).text = c["message"]
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True) + b"\n"


def check_junit_path(path) -> None:
    """A ValueError naming `path` unless a file can be written there (its folder exists, it is no folder): checked
    before any work, so a bad --junit costs no run."""
    path = Path(path)
    if path.is_dir() or not path.parent.is_dir():
        raise ValueError(f"--junit {path}: " + ("is a folder; name a file" if path.is_dir() else
                                                f"its folder {path.parent} does not exist"))


def write_junit(path, suites: list[tuple[str, list[dict]]]) -> Path:
    """Write junit_xml(suites) to `path` atomically; returns the path."""
    return write_bytes_atomic(Path(path), junit_xml(suites))
