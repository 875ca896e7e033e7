"""Camera.undistort in blocks with settled points leaving the loop, against every point through every iteration (its
form before 2026-11-27), on both paper-rig views' full pixel grids: best-of-N seconds each, and the same bits checked
(exit 1 if not).

    python docs/bench/undistort_blocks_2026-11-27.py OUT.json [REPEATS]

A record of how the figure in docs/performance.md was measured, not part of the pipeline.
"""
import json
import os
import sys
import time

import numpy as np

import twin

out_path, repeats = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 3


def best(fn):
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


rig = twin.load_rig("paper")
rec = {"cpus": os.cpu_count(), "repeats": repeats, "views": {}}
same = True
for name in rig.cameras:
    cam = rig.camera(name)
    yy, xx = np.mgrid[0:cam.height, 0:cam.width]
    uv = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
    xy = (uv - cam.K[:2, 2]) @ np.linalg.inv(cam.K)[:2, :2].T
    t_old, a = best(lambda: cam.undistort_reference(xy))
    t_new, b = best(lambda: cam.undistort(xy))
    equal = bool(np.array_equal(a, b, equal_nan=True))
    same &= equal
    rec["views"][name] = {"pixels": int(len(xy)), "every_iteration_s": t_old, "blocks_s": t_new, "same_bits": equal}
rec["passed"] = same
print(json.dumps(rec, indent=1))
with open(out_path, "w") as f:
    json.dump(rec, f, indent=1)
sys.exit(0 if same else 1)
