"""Where a capture's alignment and extraction spend their time (issue #12: capture + reconstruction of 1024^2 in
10 minutes; the two took 23-25 s and 37-44 s of the 1024^2 runs, docs/performance.md 2026-11-27).

    python docs/bench/extraction_profile_2026-11-27.py OUT.json -- reconstruct S --device cuda --resolution 1024 -o R

Runs `hemicube` with the arguments after `--` until the extraction has finished (the network's loading then stops
it), every function named below wrapped with a synchronised timer (calls and seconds summed over the threads that
call it: the photos are read by a pool). A record of how the numbers were measured, not part of the pipeline.
"""
import json
import sys
import time

import torch

import reconstruction.alignment as A
import reconstruction.extraction as E
import reconstruction.output as O
import reconstruction.pipeline as P
from bench_setup import timers
from hemicube.cli import main
from twin.capture.session import CaptureSession

out_path, args = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
stats, timed = timers()
for module, names in ((E, ("extract", "texture_grid", "capture_patterns", "corrected", "_sample", "_pixel_steps",
                           "secondary_pixels", "plan_indices", "calibration_of")),
                      (A, ("align_views", "_coarse", "_dense", "_refit", "_binned_level"))):
    for name in names:
        setattr(module, name, timed(name, getattr(module, name)))
CaptureSession.photo = timed("CaptureSession.photo", CaptureSession.photo)
O.ReconstructionFolder.write_measurements = timed("write_measurements", O.ReconstructionFolder.write_measurements)


class Stop(Exception):
    pass


def stop(*a, **k):
    raise Stop


P.load_network = stop
t = time.perf_counter()
try:
    main(args)
except Stop:
    pass
rec = {"argv": args, "seconds": time.perf_counter() - t,
       "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
       "functions": {k: {"calls": v[0], "seconds": round(v[1], 3)}
                     for k, v in sorted(stats.items(), key=lambda kv: -kv[1][1])}}
print(json.dumps(rec, indent=1))
with open(out_path, "w") as f:
    json.dump(rec, f, indent=1)
