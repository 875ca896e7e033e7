"""`hemicube calibrate` (issue #16): calibration captures in the twin, the procedures of this package on their
photos, a calibrated rig folder and a report scored against the twin's truth. Built so far: the cameras
(`calibration.cameras`) and the vignetting / flat field (`calibration.vignetting`)."""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

from .cameras import (CalibrationError, calibrate_intrinsics, calibrated_camera, detect, locate, score)

# issue #16's goals (anchors in ../shared/notes/anchors-devices-calibration-design.md): the cameras', and the flat
# field "within 0.5%", read as: 95% of the pixels within 0.5% of the true falloff (up to one factor)
CAMERA_GOALS = {"rms_px": 0.3, "focal_pct": 0.1}
FLAT_FIELD_GOAL_PCT = 0.5


def calibrate_cameras(nominal, truth, views: int, seed: int, supersample: int = 2, progress: bool = True) -> tuple:
    """Photograph a ChArUco board with every camera of the TRUE rig (twin), calibrate each camera from those
    photos alone, and return (the nominal rig with the calibrated cameras, a report per camera scoring it
    against the truth, with the nominal camera's own errors beside it for comparison)."""
    import numpy as np

    from twin.targets.charuco import CharucoTarget, calibration_poses, flat_pose

    target = CharucoTarget()
    rng = np.random.default_rng([int(seed), 18])
    size = nominal.sample.max_size * 0.8
    cams, report = {}, {}
    for name, cam in truth.cameras.items():
        dets = []
        for k, (R, t) in enumerate(calibration_poses(cam, target, truth.sample, views, seed)):
            label = f"{name} view {k}"
            dets.append(detect(target.photo(cam, R, t, rng, supersample=supersample), target, label))
            if progress:
                print(f"[calibrate] {label}: {len(dets[-1].ids)} corners", file=sys.stderr, flush=True)
        intr = calibrate_intrinsics(dets, target, (cam.width, cam.height))
        Rf, tf = flat_pose(target, truth.sample)
        R, t = locate(detect(target.photo(cam, Rf, tf, rng, supersample=supersample), target, f"{name} flat"),
                      target, intr.K, intr.dist, Rf, tf)
        cams[name] = calibrated_camera(nominal.cameras[name], intr, R, t)
        s = score(cam, cams[name], truth.sample, size)
        goals = {"rms_px": intr.rms_px <= CAMERA_GOALS["rms_px"], "focal_pct": s["focal_pct"] <= CAMERA_GOALS["focal_pct"]}
        report[name] = {"views": intr.views, "corners": intr.corners, "rms_px": intr.rms_px, **s,
                        "nominal_error": score(cam, nominal.cameras[name], truth.sample, size),
                        "goals": goals, "passed": all(goals.values())}
    return replace(nominal, cameras=cams), report


def calibrate_vignetting(nominal, truth, frames: int, seed: int, progress: bool = True) -> tuple:
    """Photograph a flat-field source with every camera of the TRUE rig (its radial falloff and its per-pixel
    maps, twin.rig.perturb.perturb_vignetting) at 0 and 180 degrees, `frames` frames each, and calibrate each
    camera's flat field from those photos alone. Returns (the nominal rig with the fitted radial coefficients
    and the per-pixel maps beyond them, a report per camera scored against the truth)."""
    from twin.camera.hdr import still_photo
    from twin.camera.imaging import optics_gain
    from twin.targets.flatfield import FlatFieldSource

    from .vignetting import calibrate_flat_field, score_flat_field

    source = FlatFieldSource()
    cams, maps, report = {}, {}, {}
    for name, cam in truth.cameras.items():
        shots = [still_photo(source.radiance(cam, angle), cam, seed=seed, frames=frames, first_frame=i * frames,
                             camera_key=name, flat_field=truth.flat_fields.get(name))
                 for i, angle in enumerate((0, 180))]
        ff = calibrate_flat_field([p for p, _ in shots], cam, saturated=[m for _, m in shots])
        nom = nominal.cameras[name]
        cams[name] = replace(nom, sensor=replace(nom.sensor, vignetting=ff.radial))
        maps[name] = ff.beyond_radial(cam)
        s = score_flat_field(ff, optics_gain(cam, truth.flat_fields.get(name)), cam)
        report[name] = {"photos": ff.photos, "frames_per_photo": frames, "radial": list(ff.radial),
                        "true_radial": list(cam.sensor.vignetting), "map_about_radial_rms_pct": ff.fit_rms_pct, **s,
                        "passed": s["flat_field_pct"]["p95"] <= FLAT_FIELD_GOAL_PCT}
        if progress:
            print(f"[calibrate] {name}: flat field from 2 x {frames} frames", file=sys.stderr, flush=True)
    return replace(nominal, cameras=cams, flat_fields=maps), report


def cmd_calibrate(args) -> int:
    import twin
    from twin.rig.perturb import perturb_cameras, perturb_vignetting

    from .vignetting import FlatFieldError

    nominal = twin.load_rig(args.rig)
    progress = not args.no_progress
    if args.what == "vignetting":
        if args.frames < 1:
            raise ValueError(f"--frames {args.frames}: at least 1 frame per photo")
        perturb, errors = perturb_vignetting, FlatFieldError
        run = lambda truth: calibrate_vignetting(nominal, truth, args.frames, args.seed, progress)  # noqa: E731
        doc = {"frames": args.frames, "goal": {"flat_field_pct_p95": FLAT_FIELD_GOAL_PCT}}

        def line(r):
            f, m = r["flat_field_pct"], r["radial_model_pct"]
            return (f"flat field: median {f['median']:.3f}%  p95 {f['p95']:.3f}%  max {f['max']:.2f}%   radial model "
                    f"alone: p95 {m['p95']:.3f}%  max {m['max']:.2f}%")
    else:
        if args.views < 4:
            raise ValueError(f"--views {args.views}: the intrinsics need >= 4 views of the board")
        perturb, errors = perturb_cameras, CalibrationError
        run = lambda truth: calibrate_cameras(nominal, truth, args.views, args.seed, progress=progress)  # noqa: E731
        doc = {"views": args.views, "goals": CAMERA_GOALS}

        def line(r):
            return (f"RMS {r['rms_px']:.3f} px  focal {r['focal_pct']:.4f}%  principal {r['principal_px']:.2f} px  "
                    f"centre {r['centre_mm']:.2f} mm  rotation {r['rotation_deg']:.3f} deg  sample "
                    f"{r['sample_px_median']:.3f} px median (nominal rig: {r['nominal_error']['sample_px_median']:.2f})")
    truth = perturb(nominal, args.perturb) if args.perturb is not None else nominal
    try:
        rig, report = run(truth)
    except errors as e:
        raise ValueError(f"calibration failed, no rig written: {e}") from None
    _write(Path(args.output), rig, truth, {"rig": nominal.name, "perturb_seed": args.perturb, "seed": args.seed,
                                           **doc, "cameras": report})
    w = max(len(n) for n in report)
    for name, r in report.items():
        print(f"{name:<{w}}  {line(r)}  {'pass' if r['passed'] else 'FAIL'}")
    print(f"calibrated rig: {args.output}/rig (truth: {args.output}/truth, report: {args.output}/report.json)")
    return 0 if all(r["passed"] for r in report.values()) else 1


def _write(output: Path, rig, truth, doc: dict) -> None:
    """OUT/rig (calibrated), OUT/truth (the true device, for scoring) and OUT/report.json, all or nothing."""
    from twin.atomic import atomic_folder
    from twin.rig.format import save_rig

    with atomic_folder(output, overwrite=True) as tmp:  # nothing is left from a failed run
        save_rig(rig, tmp / "rig")
        save_rig(truth, tmp / "truth")
        (tmp / "report.json").write_text(json.dumps(doc, indent=1) + "\n")


def register(sub) -> None:
    s = sub.add_parser("calibrate", help="calibrate from photographs of targets in the twin; write a calibrated rig "
                       "folder and a report scored against the truth (built: cameras, vignetting)")
    s.add_argument("what", choices=("cameras", "vignetting"), help="what to calibrate")
    s.add_argument("--rig", default="paper", help="built-in rig or rig folder: the nominal values (default: %(default)s)")
    s.add_argument("--perturb", type=int, metavar="SEED", help="the true device is the nominal rig with seeded "
                   "errors (twin.rig.perturb); default: the nominal rig itself")
    s.add_argument("--views", type=int, default=8, help="board poses per camera (default: %(default)s)")
    s.add_argument("--seed", type=int, default=0, help="seed of the board poses and the photos' noise (default: "
                   "%(default)s)")
    s.add_argument("--frames", type=int, default=32, help="vignetting: frames averaged per flat-field photo "
                   "(default: %(default)s)")
    s.add_argument("-o", "--output", required=True, help="folder for rig/, truth/ and report.json (replaced)")
    s.add_argument("--no-progress", action="store_true", help="no progress lines on stderr")
    s.set_defaults(func=cmd_calibrate)
