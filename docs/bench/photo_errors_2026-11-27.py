"""How far a capture's extracted photos are from the exact ones, per texel (issue #13 item 4 and issue #14: the error
that decides paper stock's alpha; docs/bench/fit_limits_2026-11-27.py gives the alpha error a given iid photo noise
costs the fit).

    python docs/bench/photo_errors_2026-11-27.py OUT.json DEVICE RESOLUTION CAPTURE

CAPTURE: a twin capture (`hemicube capture --seed 1 --resolution 128 ...`, as `hemicube validate` takes it). Aligns its
views and extracts a RESOLUTION^2 grid as the pipeline does (point footprint), renders every photo exactly at the
texel centres from the capture's true maps (resampled to the grid as the metrics are), and reports per group (the
lines, the learned-pattern photos of the primary and of the secondary view) the relative deviation
d = extracted / exact - 1 over the values above 5% of the group's median: its median (a bias), its robust spread
(1.4826 x the median absolute deviation from the median: the noise per texel and photo), the 90th percentile of |d|,
and the same over the texels where the sample's rho_s is below 0.35 of its rho_d (paper stock's weak lobes). A record
of how the numbers were measured, not part of the pipeline.
"""
import json
import sys
import time

import numpy as np

import twin
from reconstruction.alignment import AlignConfig, align_views
from reconstruction.data import LUMITEXEL_SCALE
from reconstruction.extraction import extract, texture_grid
from reconstruction.metrics import resample_maps
from reconstruction.validation import _map_params
from twin.capture.plan import indices_of
from twin.capture.session import CaptureSession

out_path, dev, R, capture = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
t0 = time.perf_counter()
session = CaptureSession.open(capture)
rig = session.rig()
uniform = indices_of(session).uniform
alignment = align_views(session.photo(uniform, 0), session.photo(uniform, 1), rig, AlignConfig(device=dev))
grid = texture_grid(session, rig, R)
meas = extract(session, rig, grid, alignment, footprint="point", progress=False)
t1 = time.perf_counter()
truth = resample_maps(session.ground_truth_maps(), grid.size_mm, R)
params = _map_params(truth)
pos = grid.positions(rig).astype(np.float32)
upper = np.flatnonzero(~np.asarray(rig.is_bottom))
cams = list(rig.cameras)[:2]


def exact(weights, camera):
    """(N, K, 3) photos of the true maps at the texel centres under (K, L_upper, 3) patterns, in network units."""
    w = np.zeros((len(weights), rig.num_leds, 3), np.float32)
    w[:, upper] = weights
    return twin.measurements(rig, pos, patterns=w, transparency=np.zeros(len(pos)), convention="physical",
                             camera=camera, visibility=True, device=dev, **params) * np.float32(LUMITEXEL_SCALE)


weak = (truth.rho_s.mean(-1) < 0.35 * truth.rho_d.mean(-1)).reshape(-1)


def stats(d):
    med = float(np.median(d))
    return {"values": int(d.size), "median": med, "robust_sd": float(1.4826 * np.median(np.abs(d - med))),
            "p90_abs": float(np.percentile(np.abs(d), 90))}


groups = {"lines": (meas.lines, exact(meas.line_weights, cams[0])),
          "learned_primary": (meas.learned_photos[:, 0], exact(meas.learned_weights, cams[0])),
          "learned_secondary": (meas.learned_photos[:, 1], exact(meas.learned_weights, cams[1]))}
record = {"device": dev, "rig": rig.name, "sample": session.sample, "resolution": R, "texel_mm": grid.texel_mm,
          "frames_per_exposure": session.frames_per_exposure, "weak_texels": int(weak.sum()),
          "align_extract_seconds": t1 - t0, "groups": {}}
for name, (got, want) in groups.items():
    keep = want > 0.05 * np.median(want)
    d = got / np.where(keep, want, 1.0) - 1.0
    record["groups"][name] = {"all": stats(d[keep]), "weak": stats(d[keep & weak[:, None, None]])}
    print(name, json.dumps(record["groups"][name]), flush=True)
record["seconds"] = time.perf_counter() - t0
with open(out_path, "w") as f:
    json.dump(record, f, indent=1)
