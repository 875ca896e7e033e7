"""Compare the raw frames of two captures of the same plan made on different machines (the CPU here, CUDA
on a lent GPU), when only small files can travel between them.

    python -m twin.capture.raw_compare digest CAPTURE rows.npz        per frame, one 64-bit hash per row
    python -m twin.capture.raw_compare rows CAPTURE rows.npz diff.npz   this capture's rows whose hash differs
    python -m twin.capture.raw_compare report CAPTURE diff.npz          pixel statistics against CAPTURE (JSON)

`digest` runs where the first capture is, `rows` where the second is (its output holds only the rows that
differ, so it stays small when the captures agree), `report` back where the first is. Both captures must keep their
raw frames (`hemicube capture --raw`).
"""
from __future__ import annotations

import hashlib
import json
import sys

import numpy as np


def _frames(capture):
    from twin.capture.session import CaptureSession

    s = CaptureSession.open(capture)
    for p in sorted({(p["index"], p["camera_index"]) for p in s.header["plan"]}):
        for j, raw in enumerate(s.raw_frames(*p)):
            yield f"photo{p[0]}_camera{p[1]}_exposure{j}", raw


def _row_hashes(raw: np.ndarray) -> np.ndarray:
    return np.array([int.from_bytes(hashlib.blake2b(r.tobytes(), digest_size=8).digest(), "little") for r in raw],
                    dtype=np.uint64)


def digest(capture, out) -> None:
    np.savez_compressed(out, **{name: _row_hashes(raw) for name, raw in _frames(capture)})


def rows(capture, digests, out) -> None:
    ref = np.load(digests)
    diff = {}
    names = set()
    for name, raw in _frames(capture):
        names.add(name)
        bad = np.flatnonzero(_row_hashes(raw) != ref[name]) if name in ref.files else np.arange(raw.shape[0])
        if bad.size:
            diff[f"{name}__rows"] = bad
            diff[f"{name}__data"] = raw[bad]
    missing = sorted(set(ref.files) - names)
    np.savez_compressed(out, frames=np.array(len(names)), missing=np.array(missing, dtype=str), **diff)


def report(capture, diff_file) -> dict:
    d = np.load(diff_file)
    frames = pixels = differing = identical_frames = 0
    worst = 0
    hist = {}
    for name, raw in _frames(capture):
        frames += 1
        pixels += raw.size
        key = f"{name}__rows"
        if key not in d.files:
            identical_frames += 1
            continue
        delta = np.abs(d[f"{name}__data"].astype(np.int32) - raw[d[key]].astype(np.int32))
        differing += int(np.count_nonzero(delta))
        worst = max(worst, int(delta.max()))
        for v, n in zip(*np.unique(delta[delta > 0], return_counts=True)):
            hist[int(v)] = hist.get(int(v), 0) + int(n)
    return {"frames": frames, "frames_compared": int(d["frames"]), "missing_frames": d["missing"].tolist(),
            "identical_frames": identical_frames, "pixels": pixels, "differing_pixels": differing,
            "differing_fraction": differing / max(pixels, 1), "max_abs_dn": worst,
            "histogram_abs_dn": {str(k): v for k, v in sorted(hist.items())}}


if __name__ == "__main__":
    from twin.capture.plan import CaptureError

    cmd, *args = sys.argv[1:]
    try:
        if cmd == "digest":
            digest(*args)
        elif cmd == "rows":
            rows(*args)
        elif cmd == "report":
            print(json.dumps(report(*args), indent=2))
        else:
            sys.exit(__doc__)
    except CaptureError as e:  # a capture without raw frames, a file failing its checksum: one line
        sys.exit(f"raw_compare: {e}")
