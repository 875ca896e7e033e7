"""What the fsync of every photo costs a paper-rig capture (issue #12), and the capture's final verification with
one thread against several.

    python docs/bench/capture_fsync_2026-11-27.py WORK OUT.json [RIG DEVICE RESOLUTION]   (paper cuda 1024)

Captures `ramps` at a 1024^2 sample on the paper rig on CUDA twice into WORK: first with every file fsynced (the
writes as they were: twin.atomic's durable=True forced), then as the capture writes now (photos unsynced, the
manifest synced); then verifies the second capture with one thread and with CaptureSession.verify. Exits 1 when
the two captures' files differ (the same seed: the same bytes) or a verification fails. A record of how the
numbers were measured, not part of the pipeline.
"""
import json
import shutil
import sys
import time
from pathlib import Path

import torch

import twin
import twin.atomic
import twin.capture.session
import twin.materials.exr
from twin.capture.runner import capture
from twin.capture.session import CaptureSession

work, out_path = Path(sys.argv[1]), sys.argv[2]
rig_name, device, resolution = (sys.argv[3:6] + ["paper", "cuda", "1024"][len(sys.argv[3:6]):])
rig, resolution = twin.load_rig(rig_name), int(resolution)
rec = {"device": torch.cuda.get_device_name(0) if device == "cuda" else "cpu", "rig": rig_name, "sample": "ramps",
       "resolution": resolution}
plain = twin.atomic.atomic_path
users = (twin.atomic, twin.capture.session, twin.materials.exr)  # the modules that call atomic_path


def forced(path, suffix="", durable=True):
    return plain(path, suffix, durable=True)


files = {}
for name, patch in (("every_file_fsynced", True), ("photos_unsynced", False)):
    d = work / name
    shutil.rmtree(d, ignore_errors=True)
    for m in users:
        m.atomic_path = forced if patch else plain
    t = time.perf_counter()
    capture(rig, "ramps", d, device=device, resolution=resolution, progress=False)
    rec[f"capture_{name}_s"] = time.perf_counter() - t
    files[name] = CaptureSession.open(d).files
for m in users:
    m.atomic_path = plain
s = CaptureSession.open(work / "photos_unsynced")
t = time.perf_counter()
one = [rel for rel in s.files if not s.verified(rel)]
rec["verify_one_thread_s"] = time.perf_counter() - t
t = time.perf_counter()
many = s.verify()
rec["verify_threads_s"] = time.perf_counter() - t
rec["files"] = len(s.files)
rec["bytes"] = sum((s.dir / rel).stat().st_size for rel in s.files)
rec["same_files"] = files["every_file_fsynced"] == files["photos_unsynced"]
rec["passed"] = rec["same_files"] and not one and not many
print(json.dumps(rec, indent=1))
Path(out_path).write_text(json.dumps(rec, indent=1))
for name in files:
    shutil.rmtree(work / name, ignore_errors=True)
sys.exit(0 if rec["passed"] else 1)
