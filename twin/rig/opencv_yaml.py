"""Reader for OpenCV FileStorage YAML files (`%YAML:1.0`, `!!opencv-matrix`), without OpenCV.

Covers what calibration files use: top-level scalars (numbers, quoted strings) and `!!opencv-matrix`
mappings with rows, cols, dt and a flow-sequence `data` that may span lines (reference §1.7).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

_DT = {"d": np.float64, "f": np.float32, "i": np.int32, "s": np.int16, "w": np.uint16, "u": np.uint8, "c": np.int8}
_KEY = re.compile(r"^([A-Za-z_][\w]*)\s*:\s*(.*)$")


class OpenCVYamlError(ValueError):
    pass


def read_opencv_yaml(path: str | Path) -> dict:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise OpenCVYamlError(f"{path}: cannot read ({e})") from None
    lines = text.splitlines()
    if not lines or not lines[0].startswith("%YAML"):
        raise OpenCVYamlError(f"{path}: not an OpenCV YAML file (no %YAML header)")
    out: dict = {}
    i = 1
    while i < len(lines):
        line = lines[i]
        i += 1
        if not line.strip() or line.startswith("---") or line.lstrip().startswith("#"):
            continue
        if line[0].isspace():
            raise OpenCVYamlError(f"{path}:{i}: unexpected indented line {line.strip()!r}")
        m = _KEY.match(line)
        if not m:
            raise OpenCVYamlError(f"{path}:{i}: cannot parse {line!r}")
        key, value = m.group(1), m.group(2).strip()
        if value.startswith("!!opencv-matrix"):
            fields, i = _read_block(lines, i, path)
            out[key] = _matrix(fields, path, key)
        else:
            out[key] = _scalar(value)
    return out


def _read_block(lines, i, path):
    """Indented `name: value` lines; a `data: [` value continues until its closing bracket."""
    fields = {}
    while i < len(lines) and lines[i][:1].isspace():
        m = _KEY.match(lines[i].strip())
        if not m:
            raise OpenCVYamlError(f"{path}:{i + 1}: cannot parse {lines[i]!r}")
        key, value = m.group(1), m.group(2)
        i += 1
        if value.lstrip().startswith("[") and "]" not in value:
            while i < len(lines) and "]" not in value:
                value += " " + lines[i].strip()
                i += 1
        fields[key] = value.strip()
    return fields, i


def _matrix(fields, path, key):
    try:
        rows, cols, dt = int(fields["rows"]), int(fields["cols"]), fields["dt"].strip()
        body = fields["data"].strip()
    except KeyError as e:
        raise OpenCVYamlError(f"{path}: matrix {key!r} lacks {e}") from None
    if not (body.startswith("[") and body.endswith("]")):
        raise OpenCVYamlError(f"{path}: matrix {key!r} data is not a [ ... ] sequence")
    if dt not in _DT:
        raise OpenCVYamlError(f"{path}: matrix {key!r} has unsupported dt {dt!r}")
    items = [s for s in body[1:-1].replace("\n", " ").split(",") if s.strip()]
    try:
        data = np.array([float(s) for s in items], dtype=np.float64)
    except ValueError as e:
        raise OpenCVYamlError(f"{path}: matrix {key!r} has a non-numeric entry ({e})") from None
    if data.size != rows * cols:
        raise OpenCVYamlError(f"{path}: matrix {key!r} has {data.size} values, expected {rows}x{cols}")
    return data.astype(_DT[dt]).reshape(rows, cols)


def _scalar(value: str):
    if value.startswith('"') and value.endswith('"'):
        return value[1:-1]
    for conv in (int, float):
        try:
            return conv(value)
        except ValueError:
            pass
    return value
