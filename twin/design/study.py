"""A design study's record: one JSON file per study (docs/designs/NAME.json), the numbers `hemicube design evaluate`
wrote to designs.json with where they came from (the command, the commit, the versions, the device, the time), and
no date in its name: a study run again replaces its record.

    record = study_record(designs_json, name=..., command=..., software=..., device=..., seconds=...)
    study = load_study(path)            # checked: the format, the rows a verdict needs
    lines = study_lines(study)          # the summary and the verdicts, computed again from the rows

The verdicts a reader sees are regenerated from the per-seed losses and curves the record holds
(twin.design.verdict.compare_all), never copied from text written at the time, so a record and its verdicts cannot
disagree.
"""
from __future__ import annotations

import json
from pathlib import Path

STUDY_FORMAT, STUDY_VERSION = "hemicube-design-study", 1
_ROW_KEYS = ("design", "heldout_eq3", "heldout_eq3_per_seed", "blind_eq3", "blind_ratio_min", "tail_change_max",
             "heldout_curve_per_seed", "steps")


def study_record(designs_json: dict, *, name: str, command: str, software: dict, device: str,
                 seconds: float) -> dict:
    """The record of a study: designs.json's content (`designs`, `verdicts`, `how`, ...) under its provenance."""
    return {"format": STUDY_FORMAT, "version": STUDY_VERSION, "study": name, "command": command,
            "software": software, "device": device, "seconds": round(float(seconds), 1), **designs_json}


def is_study(path) -> bool:
    """Whether `path` is a file holding a study record (what `evaluate --study` may replace)."""
    try:
        return json.loads(Path(path).read_text()).get("format") == STUDY_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def load_study(path) -> dict:
    """A study record, checked: one line naming the file and what is wrong otherwise."""
    p = Path(path)
    try:
        study = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{p}: not a readable study record ({e})") from None
    if not isinstance(study, dict) or study.get("format") != STUDY_FORMAT:
        raise ValueError(f"{p}: not a design study record (format {STUDY_FORMAT!r})")
    if study.get("version") != STUDY_VERSION:
        raise ValueError(f"{p}: study record version {study.get('version')!r}, this code reads {STUDY_VERSION}")
    rows = study.get("designs")
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"{p}: a study record needs its designs' rows")
    for r in rows:
        missing = [k for k in _ROW_KEYS if k not in r]
        if missing:
            raise ValueError(f"{p}: design {r.get('design')!r} lacks {missing}")
    return study


def study_lines(study: dict) -> list[str]:
    """What a reader is shown: where the numbers come from, one line a design, and every pair's verdict, computed
    again from the rows."""
    from twin.design.verdict import compare_all

    sw = study.get("software") or {}
    lines = [f"study {study['study']}: {study['command']}",
             f"  commit {sw.get('git_commit') or 'unknown'}, torch {sw.get('torch', '?')}, device {study['device']}, "
             f"{study['seconds'] / 60:.1f} min"]
    for r in study["designs"]:  # the columns evaluate computed from these rows (blind_ratio_min, tail_change_max)
        change = r["tail_change_max"]
        lines.append(f"  {r['design']}: test loss {r['heldout_eq3']:.4g} over {len(r['heldout_eq3_per_seed'])} seed(s) "
                     f"of {r['steps']} steps, worst {r['blind_ratio_min']:.2f}x below the blind predictor, held-out curve "
                     + ("too coarse to tell" if change is None else f"moved {100 * change:.1f} %")
                     + " over its last 20 % of steps")
    lines += [f"  {v['text']}" for v in compare_all(study["designs"])]
    return lines
