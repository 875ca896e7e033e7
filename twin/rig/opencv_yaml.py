"""OpenCV FileStorage YAML files (`%YAML:1.0`, `!!opencv-matrix`: the released calibration files, reference §1.7), read
by OpenCV's own reader, cv2.FileStorage, into plain Python and numpy values."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np


class OpenCVYamlError(ValueError):
    pass


def read_opencv_yaml(path: str | Path) -> dict:
    """{key: value} of the file's top-level nodes: a matrix as a numpy array of its dt and shape, an integer, a real
    or a string as Python's. An OpenCVYamlError names the file and the cause in one line otherwise."""
    import cv2

    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(5)
    except OSError as e:
        raise OpenCVYamlError(f"{path}: cannot read ({e.strerror})") from None
    if head != b"%YAML":
        raise OpenCVYamlError(f"{path}: not an OpenCV YAML file (no %YAML header)")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        try:
            return {key: _value(fs.getNode(key), path, key) for key in fs.root().keys()}
        finally:
            fs.release()
    except (cv2.error, SystemError) as e:  # a parse error inside the constructor arrives as a SystemError
        raise OpenCVYamlError(f"{path}: not a valid OpenCV YAML file ({_reason(e)})") from None


def _value(node, path: Path, key: str):
    if node.isMap():
        m = node.mat()
        if m is None:
            raise OpenCVYamlError(f"{path}: {key!r} is a mapping, not an !!opencv-matrix")
        return np.asarray(m)
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    if node.isString():
        return node.string()
    raise OpenCVYamlError(f"{path}: {key!r} is neither a matrix, a number nor a string")


def _reason(e: Exception) -> str:
    """OpenCV's message without its source location: `(-212:Parsing error) ... Incorrect indentation`."""
    text = str(e.__cause__ or e).strip().splitlines()
    line = text[-1] if text else type(e).__name__
    return re.sub(r"^OpenCV\([^)]*\) \S+: error: ", "", line)
