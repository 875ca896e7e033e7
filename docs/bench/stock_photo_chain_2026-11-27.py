"""Issue #14 (docs/accuracy.md, "Open", sixteenth session): does any step of the photo's formation put a signed,
lobe-shaped error into paper@9003's stock? Each step on its own, against the exact forward model at the texel centre
(paper_edges.Edges.exact), read as extraction reads a photo (corrected, bilinear at the texel's primary pixel).

    python docs/bench/stock_photo_chain_2026-11-27.py DUMP CAPTURE MODE [ARGS]

DUMP and CAPTURE as in docs/bench/edge_breakdown_2026-11-27.py. MODE:
  measured                 the capture's own photos (primary lines, primary learned, secondary learned);
  render GROUP             the twin's camera render of the photos (twin.camera.imaging, no sensor), GROUP lines or
                           learned (their LED weights from the dump);
  chain GROUP SENSOR SEEDS that render through the sensor and the HDR merge (the plan's bracket, four frames an
                           exposure) for each seed (comma-separated), then their mean; SENSOR: full (the mini
                           camera), noprnu (no fixed patterns), bigwell (100x the electrons: 1/10 the shot noise);
  bracket                  no render: the capture's raw frames of the primary photos at the stock's photosites: their
                           fill of saturation per exposure and the electrons the merge keeps;
  hdr                      no sample: the HDR merge's relative bias on uniform grey scenes at levels across a bracket.
Per distance class, the median over texels of each texel's least-squares coefficients of its photo errors (static
gain out) on d(photo)/d(log alpha) and on its specular part (d/d(log rho_s)), beside the photo itself; for chain, also
the per-photo mean error over the open stock (d5+) per seed, against what noise alone leaves in the seeds' mean.
A record of how the numbers were measured, not part of the pipeline.
"""
import sys
from dataclasses import replace

import numpy as np

from reconstruction.validation import _map_params

mode, args = sys.argv[3], sys.argv[4:]

if mode == "hdr":
    import twin
    from twin.camera.hdr import merge_hdr
    from twin.camera.sensor import simulate_raw
    from twin.capture.plan import photo_exposures

    rig = twin.load_rig("mini")
    sensor = rig.camera(list(rig.cameras)[0]).sensor
    ts = photo_exposures(1.0, sensor)
    for f in (1.0, 0.5, 0.25, 0.12, 0.05, 0.02, 0.01, 0.005, 0.002):
        errs = [merge_hdr([simulate_raw(np.full((256, 256, 3), f), sensor=sensor, exposure_s=t, seed=seed, frame=j,
                                        camera_key="bias") for j, t in enumerate(ts)], ts, sensor).radiance.mean() / f - 1
                for seed in range(4)]
        print(f"level/max {f:6.3f}  bias {np.mean(errs) * 100:+.4f}%  (sd over 4 seeds {np.std(errs) * 100:.4f}%)")
    sys.exit()

from paper_edges import Edges  # noqa: E402

from reconstruction.extraction import _sample, _taps, corrected  # noqa: E402
from twin.capture.session import CaptureSession  # noqa: E402

E = Edges(sys.argv[1], sys.argv[2])
d, rig = E.d, E.rig
session = CaptureSession.open(sys.argv[2])
NL = 63  # the line photos come first in the primary group
open_stock = E.classes["d5+"].reshape(-1)

if mode == "bracket":
    from twin.camera.sensor import saturation_electrons

    cam = rig.camera(E.cams[0])
    sensor = cam.sensor
    uv, _ = cam.project(d["positions"])
    ij = np.round(uv[open_stock]).astype(int)
    sat = saturation_electrons(sensor) / sensor.gain_e_per_dn
    kept, rows = [], []
    for stem, rec in sorted(session.photos.items()):
        if rec["camera"] != E.cams[0] or rec["sample"] != "sample":
            continue
        k, c = int(stem[3:8]), int(stem[-2:])  # twin.capture.session.photo_stem: imgKKKKK_camCC
        dn = np.array([r[ij[:, 1], ij[:, 0]] for r in session.raw_frames(k, c)], float) - sensor.black_level_dn
        fill = dn / sat
        e = np.where(fill < 0.9, dn * sensor.gain_e_per_dn, 0).sum(0)
        kept.append(np.median(e))
        rows.append(f"{rec['pattern']}: median fill per exposure {np.round(np.median(fill, 1)[::4], 3).tolist()}, "
                    f"kept {np.median(e):.0f} e-")
    kept = np.array(kept)
    p10, p50, p90 = np.percentile(kept, [10, 50, 90])
    print(f"{len(kept)} primary photos: the open stock keeps {p50:.0f} e- a photosite (10-90%: {p10:.0f}-{p90:.0f}), "
          f"shot noise {100 / np.sqrt(p90):.2f}-{100 / np.sqrt(p10):.2f}%")
    print("\n".join(rows[::12]))
    sys.exit()

p = _map_params(E.truth)
GROUPS = {"lines": (slice(0, NL), 0), "learned": (slice(NL, None), 0), "secondary": (slice(None), 1)}


def weights(group):
    sl, view = GROUPS[group]
    return (d["line_weights"] if view == 0 else d["secondary"][1])[sl], E.cams[view]


def derivatives(W, cam):
    X = E.exact(W, cam)
    Xa = E.exact(W, cam, alpha_x=p["alpha_x"] * 1.05, alpha_y=p["alpha_y"] * 1.05)
    Xs = E.exact(W, cam, rho_d=np.zeros_like(p["rho_d"]))
    return X, (Xa - X) / np.log(1.05), Xs


def coefficients(M, X, Da, Xs, tag):
    g = np.median(M / np.maximum(X, 1e-9), axis=1, keepdims=True)
    R = M / g - X
    for name in ("d2", "d3-4", "d5+"):
        c = np.array([np.linalg.lstsq(np.stack([Da[i].ravel(), Xs[i].ravel(), X[i].ravel()], 1), R[i].ravel(),
                                      rcond=None)[0][:2] for i in np.flatnonzero(E.classes[name].reshape(-1))])
        print(f"{tag} {name}: d/dlog alpha {np.median(c[:, 0]):+.4f}, d/dlog rho_s {np.median(c[:, 1]):+.4f} "
              f"(median over {len(c)} texels; per-texel sd {c[:, 0].std():.3f} / {c[:, 1].std():.3f})", flush=True)


if mode == "measured":
    for group, (sl, view) in GROUPS.items():
        M = (d["lines"] if view == 0 else d["secondary"][0])[:, sl]
        coefficients(M, *derivatives(*weights(group)), f"measured {group}")
    sys.exit()

from twin.camera.hdr import merge_hdr  # noqa: E402
from twin.camera.imaging import render_device, trace_pixels  # noqa: E402
from twin.camera.sensor import apply_optics, simulate_raw  # noqa: E402
from twin.capture.plan import photo_exposures  # noqa: E402

group = args[0]
W, camname = weights(group)
X, Da, Xs = derivatives(W, camname)
cam = rig.camera(camname)
upper = np.flatnonzero(~np.asarray(rig.is_bottom))
drive = np.zeros((len(W), rig.num_leds, 3), np.float32)
drive[:, upper] = W / W.max() * 0.5  # relative drive: the exposure follows each image's brightest value
imgs = render_device(rig, camname, trace_pixels(rig, camname, session.ground_truth_maps(), device="cpu"), drive,
                     device="cpu").numpy()
taps = _taps((cam.height, cam.width), cam.project(d["positions"])[0])


def read(img, camera):
    return _sample(corrected(np.asarray(img, np.float32), camera), taps)


if mode == "render":
    M = np.stack([read(img, cam) for img in imgs], 1)
    rel = M / np.median(M / np.maximum(X, 1e-9), axis=1, keepdims=True) / np.maximum(X, 1e-9) - 1
    print(f"render {group}: relative error RMS over the open stock {np.sqrt(np.mean(rel[open_stock] ** 2)) * 100:.4f}%")
    coefficients(M, X, Da, Xs, f"render {group}")
    sys.exit()

variant, seeds = args[1], [int(s) for s in args[2].split(",")]
sensor = cam.sensor
if variant == "noprnu":
    sensor = replace(sensor, prnu=0.0, dsnu_e=0.0)
elif variant == "bigwell":
    sensor = replace(sensor, full_well_e=sensor.full_well_e * 100, gain_e_per_dn=sensor.gain_e_per_dn * 100,
                     electrons_per_radiance_s=sensor.electrons_per_radiance_s * 100)
cam = replace(cam, sensor=sensor)
runs = []
for seed in seeds:
    M = np.empty(X.shape, np.float32)
    for k, img in enumerate(imgs):
        rad = apply_optics(img.astype(np.float64), cam)
        ts = photo_exposures(float(rad.max()), sensor)
        raws = [simulate_raw(rad, sensor=sensor, exposure_s=t, seed=seed, frame=k * 16 + j, camera_key=camname)
                for j, t in enumerate(ts)]
        M[:, k] = read(merge_hdr(raws, ts, sensor).radiance, cam)
    coefficients(M, X, Da, Xs, f"chain {group} {variant} seed {seed}")
    runs.append(M)
coefficients(np.mean(runs, 0), X, Da, Xs, f"chain {group} {variant} mean of {len(runs)} seeds")
per = []
for M in runs:
    g = np.median(M / np.maximum(X, 1e-9), axis=1, keepdims=True)
    per.append(np.nanmean(np.where(X > 1e-6, M / g / np.maximum(X, 1e-9) - 1, np.nan)[open_stock], axis=(0, 2)))
per = np.array(per)
lobe = (Xs[open_stock] / X[open_stock]).mean(axis=(0, 2))
print(f"per-photo mean error over the open stock, RMS per seed (%): {np.round(np.sqrt((per ** 2).mean(1)) * 100, 4).tolist()}; "
      f"of the seeds' mean {np.sqrt((per.mean(0) ** 2).mean()) * 100:.4f}% against "
      f"{np.sqrt((per ** 2).mean() / len(per)) * 100:.4f}% from noise alone; correlation with the lobe's share "
      f"{np.corrcoef(per.mean(0), lobe)[0, 1]:.2f}")
