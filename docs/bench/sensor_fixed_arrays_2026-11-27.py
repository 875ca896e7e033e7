"""The sensor's fixed patterns drawn once per camera (twin.camera.sensor.fixed_pattern_arrays, what the capture's sim
backend does) against drawn again for every frame (raw_frame without `fixed`: the same work as the raw kernel's
former inline draw), on one camera's frames of a seeded radiance; the same bytes checked (exit 1 if not).

    python docs/bench/sensor_fixed_arrays_2026-11-27.py OUT.json RIG DEVICE [FRAMES]

A record of how the figure was measured, not part of the pipeline.
"""
import json
import sys
import time

import numpy as np
import warp as wp

import twin
from twin.camera.sensor import fixed_pattern_arrays, raw_frame, saturation_radiance, sensor_consts

out_path, rig_name, device = sys.argv[1], sys.argv[2], sys.argv[3]
frames = int(sys.argv[4]) if len(sys.argv) > 4 else 200
rig = twin.load_rig(rig_name)
name, cam = next(iter(rig.cameras.items()))
t = 0.01
rng = np.random.default_rng(0)  # radiance up to 1.5 x saturation: shot noise over the whole range, some clipped
rad = rng.uniform(0, 1.5 * saturation_radiance(cam.sensor, t), (cam.height, cam.width, 3)).astype(np.float32)
rad_wp = wp.array(rad, dtype=wp.vec3f, device=device)
consts = [sensor_consts(cam.sensor, exposure_s=t, seed=1, frame=f, camera_key=f"{rig.digest()}/{name}")
          for f in range(frames)]
fixed = fixed_pattern_arrays(consts[0], cam.height, cam.width, device)
outs = {m: [wp.empty((cam.height, cam.width), dtype=wp.uint16, device=device) for _ in range(frames)]
        for m in ("per_frame", "once")}


def run(mode):
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for k, o in zip(consts, outs[mode]):
        raw_frame(rad_wp, k, o, fixed=None if mode == "per_frame" else fixed)
    wp.synchronize_device(device)
    return time.perf_counter() - t0


run("per_frame"), run("once")  # compile and warm up
times = {m: [] for m in outs}
for _ in range(3):
    for m in outs:
        times[m].append(run(m))
same = all(np.array_equal(a.numpy(), b.numpy()) for a, b in zip(outs["per_frame"], outs["once"]))
dev = wp.get_device(device)
res = {"device": dev.name if dev.is_cuda else "cpu", "rig": rig.name, "camera": [cam.width, cam.height],
       "frames": frames, "ms_a_frame": {m: 1e3 * min(v) / frames for m, v in times.items()},
       "checks": [{"check": "same_bytes_every_frame", "passed": same}], "passed": same}
print(json.dumps(res, indent=1))
with open(out_path, "w") as f:
    json.dump(res, f, indent=1)
sys.exit(0 if same else 1)
