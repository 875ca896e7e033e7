"""One photo sampled at a 1024^2 texel grid's points, bilinearly: the taps computed with it (reconstruction.alignment
.bilinear, the extraction before 2026-11-27) against taps computed once per view (bilinear_taps, then bilinear_at
per photo; issue #12). Exits 1 when the two differ in a bit.

    python docs/bench/extraction_taps_2026-11-27.py [REPEATS]

A 2664 x 2304 float32 RGB image (the paper rig's cameras) of seeded noise, 1,048,576 seeded points inside it. A record
of how the numbers were measured, not part of the pipeline.
"""
import json
import sys
import time

import numpy as np

from reconstruction.alignment import bilinear, bilinear_at, bilinear_taps

repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 3
rng = np.random.default_rng(0)
img = rng.random((2304, 2664, 3), dtype=np.float32)
x, y = rng.uniform(100, 2500, 1 << 20), rng.uniform(100, 2200, 1 << 20)
taps = bilinear_taps(img.shape, x, y)
rec = {}
for name, fn in (("taps_each_photo", lambda: bilinear(img, x, y)), ("taps_once_per_view", lambda: bilinear_at(img, taps))):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    rec[name] = {"seconds_min": min(times), "seconds": times}
    rec[name + "_result"] = out
same = np.array_equal(rec.pop("taps_each_photo_result"), rec.pop("taps_once_per_view_result"), equal_nan=True)
rec.update(same_bits=bool(same), points=int(x.size), image=list(img.shape))
print(json.dumps(rec, indent=1))
sys.exit(0 if same else 1)
