"""`hemicube calibrate` (issue #16): calibration captures in the twin, the procedures of this package on their
photos, a calibrated rig folder and a report scored against the twin's truth. Built so far: the cameras
(`calibration.cameras`), the vignetting / flat field (`calibration.vignetting`), the upper LEDs' positions,
normals, profiles and intensities (`calibration.leds`) and each camera's crosstalk and colour matrix
(`calibration.colour`)."""
from __future__ import annotations

import itertools
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

from .cameras import (CalibrationError, calibrate_intrinsics, calibrated_camera, detect, locate, score)

# issue #16's goals (anchors in ../shared/notes/anchors-devices-calibration-design.md): the cameras', and the flat
# field "within 0.5%", read as: 95% of the pixels within 0.5% of the true falloff (up to one factor)
CAMERA_GOALS = {"rms_px": 0.3, "focal_pct": 0.1}
FLAT_FIELD_GOAL_PCT = 0.5


def calibrate_cameras(nominal, truth, views: int, seed: int, supersample: int = 2, board_scale: int = 1,
                      progress: bool = True) -> tuple:
    """Photograph a ChArUco board with every camera of the TRUE rig (twin), calibrate each camera from those
    photos alone, and return (the nominal rig with the calibrated cameras, a report per camera scoring it
    against the truth, with the nominal camera's own errors beside it for comparison). board_scale s: the board
    is photographed by each camera's lens on a sensor of s x s times its pixels (Camera.resized) and the
    result scaled back: the issue's way for the mini rig, whose 222 x 192 px cameras are too small for corner
    detection (the paper rig's cameras are the mini rig's at s = 12); rms_px is then in those finer pixels."""
    import numpy as np

    from twin.targets.charuco import CharucoTarget, calibration_poses, flat_pose

    target = CharucoTarget()
    rng = np.random.default_rng([int(seed), 18])
    size = nominal.sample.max_size * 0.8
    cams, report = {}, {}
    for name, true_cam in truth.cameras.items():
        cam = true_cam.resized(board_scale)
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
        cams[name] = calibrated_camera(nominal.cameras[name].resized(board_scale), intr, R, t).resized(1 / board_scale)
        s = score(true_cam, cams[name], truth.sample, size)
        goals = {"rms_px": intr.rms_px <= CAMERA_GOALS["rms_px"], "focal_pct": s["focal_pct"] <= CAMERA_GOALS["focal_pct"]}
        report[name] = {"views": intr.views, "corners": intr.corners, "rms_px": intr.rms_px, **s,
                        "nominal_error": score(true_cam, nominal.cameras[name], truth.sample, size),
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


LED_GOALS = {"position_mm_median": 0.5, "profile_shape_pct_median": 2.0}  # issue #16: 0.5 mm, Psi within 2%
PLATE_HEIGHTS_MM = (0.0, 40.0)  # the diffuse plate on the sample plane, then on 40 mm spacers
LED_BATCH = 64  # LEDs rendered at once (the radiance of a batch: 64 x H x W x 3 float64)


def _binned(rig, b: int):
    """The rig with its cameras binned b x b (Camera.resized; the flat-field maps averaged over the bins)."""
    import numpy as np

    if b == 1:
        return rig

    def down(m, cam):
        H, W = (cam.height // b) * b, (cam.width // b) * b
        return np.asarray(m)[:H, :W].reshape(H // b, b, W // b, b).mean(axis=(1, 3)).astype(np.float32)

    cams = {n: c.resized(1.0 / b) for n, c in rig.cameras.items()}
    return replace(rig, cameras=cams, flat_fields={n: down(m, rig.cameras[n]) for n, m in rig.flat_fields.items()})


def calibrate_leds_from_plate(nominal, truth, frames: int, seed: int, step: int = 1, binning: int = 1,
                              progress: bool = True, bottom: bool = False) -> tuple:
    """Photograph a diffuse plate (twin.targets.diffuse) with both cameras of the TRUE rig, at the two heights
    PLATE_HEIGHTS_MM, each upper LED alone (every `step`-th: a quicker run; the others keep their nominal
    values), `frames` frames per photo, with the cameras binned `binning` x `binning` (the LEDs' light over the
    plate is smooth; the paper rig's 6 MP photos need not be read whole), and calibrate the LEDs from those photos
    alone (calibration.leds; the cameras, their flat fields and colour matrices as the nominal rig has them:
    calibrated beforehand). bottom: the bottom LEDs instead, each alone, through the empty holder's acrylic
    (one height); those whose light's crest the photos do not see (calibration.leds.crest_seen) keep their
    nominal values. Returns (the nominal rig with the calibrated LEDs, a report scored against the truth, with
    the nominal rig's own errors beside it)."""
    import numpy as np

    from twin.camera.hdr import still_photo
    from twin.targets.diffuse import DiffusePlate

    from .leds import calibrate_leds, crest_seen, plate_samples, plate_view, score_leds

    chosen = np.flatnonzero(truth.is_bottom if bottom else ~truth.is_bottom)[::step]
    plates = [DiffusePlate(transparency=1.0)] if bottom else [DiffusePlate(height_mm=h) for h in PLATE_HEIGHTS_MM]
    beyond = []
    if bottom:
        seen_crest = crest_seen(nominal, chosen, plates[0].size_mm / 2)
        chosen, beyond = chosen[seen_crest], chosen[~seen_crest].tolist()
    samples = {int(led): [] for led in chosen}
    shot = 0
    seen, known = _binned(truth, binning), _binned(nominal, binning)
    for cam_name in truth.cameras:
        cam, cal_cam = seen.camera(cam_name), known.camera(cam_name)
        for plate in plates:
            view = plate_view(cal_cam, known, plate)  # the same for every photo of this plate by this camera
            what = "the acrylic" if bottom else f"plate at {plate.height_mm:g} mm"
            for i in range(0, len(chosen), LED_BATCH):
                batch = chosen[i:i + LED_BATCH]
                for led, rad in zip(batch, plate.radiance(seen, cam_name, batch)):
                    if not rad.max() > 0:
                        continue  # the LED does not reach the plate at this height (a side LED below it)
                    photo, sat = still_photo(rad, cam, seed=seed, frames=frames, first_frame=shot * frames,
                                             camera_key=cam_name, flat_field=seen.flat_fields.get(cam_name))
                    shot += 1
                    samples[int(led)].append(plate_samples(photo, sat, cal_cam, known, plate, view=view,
                                                           label=f"{cam_name}, {what}, LED {led}"))
            if progress:
                print(f"[calibrate] {cam_name}: {what}, {len(chosen)} LEDs", file=sys.stderr, flush=True)
    albedo = nominal.bottom.acrylic_transmission if bottom else plates[0].albedo
    fit = calibrate_leds(nominal, samples, albedo, bottom=bottom)
    rig = fit.apply(nominal)
    s = score_leds(rig, truth, fit.index)
    goals = {"position_mm_median": s["position_mm"]["median"] <= LED_GOALS["position_mm_median"],
             "profile_shape_pct_median": s["profile_shape_pct"]["median"] <= LED_GOALS["profile_shape_pct_median"]}
    target = ({"target": "the empty holder's acrylic, lit from below", "crest_not_seen": beyond} if bottom else
              {"plate_heights_mm": list(PLATE_HEIGHTS_MM)})
    report = {"photos": shot, "frames_per_photo": frames, "led_step": step, "binning": binning,
              "camera_pixels": {n: [c.width, c.height] for n, c in seen.cameras.items()}, **target,
              "calibrated": int(fit.index.size), "skipped": fit.skipped, "fit_rms_log": float(np.median(fit.rms_log)),
              **s, "nominal_error": score_leds(nominal, truth, fit.index), "goals": goals,
              "passed": all(goals.values())}
    return rig, {"bottom" if bottom else "leds": report}


COLOUR_GOALS = {"delta_e2000_median": 1.0, "crosstalk_max": 0.005}  # issue #16: ΔE2000 <= 1 median; ours: 0.5%


def calibrate_colour(nominal, truth, spectra, frames: int, seed: int, step: int = 1, binning: int = 1,
                     progress: bool = True) -> tuple:
    """Photograph the white plate (each LED channel alone, then white) and a ColorChecker (white) with every
    camera of the TRUE rig, whose colour is `spectra`'s (twin.camera.spectral), and calibrate each camera's
    crosstalk and colour matrix to XYZ from those photos alone (calibration.colour; the cameras and flat fields
    as the nominal rig has them: calibrated beforehand). The light is every `step`-th upper LED (the white need
    not be uniform: each patch is divided by the plate at the same pixels), the cameras binned `binning` x
    `binning`. Returns (the nominal rig with the calibrated crosstalks, a report per camera scored against the
    truth, with the nominal crosstalk's own error beside it)."""
    import numpy as np

    from twin.camera.hdr import still_photo
    from twin.camera.spectral import chart_radiance
    from twin.targets.colorchecker import ColorChecker
    from twin.targets.diffuse import DiffusePlate

    from .colour import chart_patches, crosstalk_from_photos, delta_e2000, matrix_to_xyz

    upper = np.flatnonzero(~truth.is_bottom)[::step]
    plate, chart = DiffusePlate(), ColorChecker()
    names, rho = chart.names_and_spectra()
    cams, report = {}, {}
    seen, binned = _binned(truth, binning), _binned(nominal, binning)
    for name, cam in seen.cameras.items():
        known = binned.camera(name)
        shots = itertools.count(0, frames)  # each photo its own noise draws

        def photo(radiance, camera_rgb=False):
            return still_photo(radiance, cam, seed=seed, frames=frames, first_frame=next(shots), camera_key=name,
                               flat_field=seen.flat_fields.get(name), camera_rgb=camera_rgb)

        light = plate.lit_radiance(seen, name, upper, batch=LED_BATCH)  # LED RGB: every upper LED at full drive
        channel = [photo(light * np.eye(3)[c]) for c in range(3)]
        M = crosstalk_from_photos([p for p, _ in channel], [m for _, m in channel], known, binned, plate,
                                  label=f"{name}, white plate")
        white = chart_patches(*photo(light), known, binned, chart, label=f"{name}, white plate")
        # the chart lies where the plate lay (140 mm, the chart 82.5 mm): the plate's light over its albedo is
        # what a perfect white there receives, no second evaluation of the LEDs
        r = chart_patches(*photo(chart_radiance(chart, seen, spectra, name, light / plate.albedo), camera_rgb=True),
                          known, binned, chart, label=f"{name}, ColorChecker") / white * plate.albedo
        # the LEDs' white as a spectroradiometer reads it off the plate where the chart lies: its LED-RGB mix
        weights = light[chart.patch_map(seen, cam) >= 0].mean(axis=0)
        ref = spectra.xyz(rho, weights)
        A = matrix_to_xyz(r, ref)
        dE = delta_e2000(r @ A.T, ref, spectra.xyz(np.ones(rho.shape[1]), weights))
        Mt = np.asarray(cam.sensor.crosstalk, np.float64)
        residual = lambda Mc: float(np.abs(np.linalg.solve(Mc, Mt) - np.eye(3)).max())  # noqa: E731
        nom = nominal.camera(name)  # unbinned
        cams[name] = replace(nom, sensor=replace(nom.sensor, crosstalk=tuple(map(tuple, M.tolist()))))
        goals = {"delta_e2000_median": float(np.median(dE)) <= COLOUR_GOALS["delta_e2000_median"],
                 "crosstalk_max": residual(M) <= COLOUR_GOALS["crosstalk_max"]}
        report[name] = {"photos": 6, "frames_per_photo": frames, "leds_lit": len(upper), "binning": binning,
                        "camera_pixels": [cam.width, cam.height], "crosstalk": M.tolist(), "true_crosstalk": Mt.tolist(),
                        "crosstalk_residual_max": residual(M),
                        "nominal_error": {"crosstalk_residual_max": residual(np.asarray(known.sensor.crosstalk))},
                        "to_xyz_from_camera_rgb": A.tolist(), "to_xyz_from_led_rgb": (A @ M).tolist(),
                        "white_led_rgb": (weights / weights.max()).tolist(),
                        "delta_e2000": {"median": float(np.median(dE)), "p90": float(np.percentile(dE, 90)),
                                        "max": float(dE.max()), "per_patch": dict(zip(names, dE.round(3).tolist()))},
                        "goals": goals, "passed": all(goals.values())}
        if progress:
            print(f"[calibrate] {name}: crosstalk from 3 plate photos, colour matrix from the ColorChecker",
                  file=sys.stderr, flush=True)
    return replace(nominal, cameras=cams), report


# a lab's order: each procedure takes the rig the ones before it calibrated (the colour and the LEDs photograph
# the plate through the calibrated cameras and flat fields; the LEDs' intensities are in the calibrated colour)
STAGES = ("cameras", "vignetting", "colour", "leds", "bottom")


@dataclass(frozen=True)
class _Stage:
    perturb: Callable  # (rig, seed or None) -> the true device with this stage's errors
    errors: type       # the procedure's own error: named photos, no rig written
    run: Callable      # (the rig calibrated so far, truth) -> (rig, report per camera)
    doc: dict          # the settings, for report.json
    line: Callable     # a camera's report -> its summary line


def _stage(what: str, args, nominal, progress: bool) -> _Stage:
    from twin.rig.perturb import perturb_cameras, perturb_leds, perturb_vignetting

    from .vignetting import FlatFieldError

    frames = args.frames if args.frames is not None else (16 if what in ("leds", "colour") else 32)
    seeded = lambda f: (lambda rig, seed: rig if seed is None else f(rig, seed))  # noqa: E731
    if min(frames, args.led_step, args.binning) < 1:
        raise ValueError(f"--frames {frames}, --led-step {args.led_step}, --binning {args.binning}: each must be at "
                         "least 1")
    if what in ("leds", "bottom"):
        from .leds import LEDCalibrationError

        def line(r):
            p, f, n = r["position_mm"], r["profile_shape_pct"], r["nominal_error"]["position_mm"]
            return (f"{r['calibrated']} LEDs: position median {p['median']:.2f} mm (p90 {p['p90']:.2f}, nominal "
                    f"{n['median']:.2f})  normal {r['normal_deg']['median']:.2f} deg  profile {f['median']:.2f}% "
                    f"(p90 {f['p90']:.2f}%)  emission {r['emission_pct']['median']:.2f}%")
        bottom = what == "bottom"
        if bottom and (nominal.bottom is None or not nominal.is_bottom.any()):
            raise ValueError(f"calibrate bottom: rig {nominal.name!r} has no bottom LEDs")
        return _Stage(seeded(lambda rig, seed: perturb_leds(rig, seed, bottom=bottom)), LEDCalibrationError,
                      lambda known, truth: calibrate_leds_from_plate(known, truth, frames, args.seed, args.led_step,
                                                                     args.binning, progress, bottom=bottom),
                      {"frames": frames, "led_step": args.led_step, "binning": args.binning, "goals": LED_GOALS}, line)
    if what == "colour":
        from twin.camera.spectral import device_spectra, with_crosstalk

        from .colour import ColourCalibrationError

        spectra = device_spectra(nominal.cameras, args.perturb)

        def line(r):
            d = r["delta_e2000"]
            return (f"ColorChecker ΔE2000 median {d['median']:.2f} (p90 {d['p90']:.2f}, max {d['max']:.2f})  crosstalk "
                    f"residual {100 * r['crosstalk_residual_max']:.3f}% (nominal rig: "
                    f"{100 * r['nominal_error']['crosstalk_residual_max']:.1f}%)")
        # the truth's colour is always its spectra's (without --perturb, the nominal spectra's crosstalk: the
        # nominal rigs' identity is an idealised sensor that no real colour filter has)
        return _Stage(lambda rig, seed: with_crosstalk(rig, spectra), ColourCalibrationError,
                      lambda known, truth: calibrate_colour(known, truth, spectra, frames, args.seed, args.led_step,
                                                            args.binning, progress),
                      {"frames": frames, "led_step": args.led_step, "binning": args.binning, "goals": COLOUR_GOALS,
                       "spectra": spectra.to_dict()}, line)
    if what == "vignetting":
        def line(r):
            f, m = r["flat_field_pct"], r["radial_model_pct"]
            return (f"flat field: median {f['median']:.3f}%  p95 {f['p95']:.3f}%  max {f['max']:.2f}%   radial model "
                    f"alone: p95 {m['p95']:.3f}%  max {m['max']:.2f}%")
        return _Stage(seeded(perturb_vignetting), FlatFieldError,
                      lambda known, truth: calibrate_vignetting(known, truth, frames, args.seed, progress),
                      {"frames": frames, "goal": {"flat_field_pct_p95": FLAT_FIELD_GOAL_PCT}}, line)
    if args.views < 4 or args.board_scale < 1:
        raise ValueError(f"--views {args.views}, --board-scale {args.board_scale}: the intrinsics need >= 4 views of "
                         "the board, and the scale is at least 1")

    def line(r):
        return (f"RMS {r['rms_px']:.3f} px  focal {r['focal_pct']:.4f}%  principal {r['principal_px']:.2f} px  "
                f"centre {r['centre_mm']:.2f} mm  rotation {r['rotation_deg']:.3f} deg  sample "
                f"{r['sample_px_median']:.3f} px median (nominal rig: {r['nominal_error']['sample_px_median']:.2f})")
    return _Stage(seeded(perturb_cameras), CalibrationError,
                  lambda known, truth: calibrate_cameras(known, truth, args.views, args.seed,
                                                         board_scale=args.board_scale, progress=progress),
                  {"views": args.views, "board_scale": args.board_scale, "goals": CAMERA_GOALS}, line)


def cmd_calibrate(args) -> int:
    import twin

    nominal = twin.load_rig(args.rig)
    if "all" in args.what and len(args.what) > 1 or len(set(args.what)) < len(args.what):
        raise ValueError(f"calibrate {' '.join(args.what)}: name each procedure once, or 'all' alone")
    whats = STAGES if args.what == ["all"] else tuple(w for w in STAGES if w in args.what)  # in the lab's order
    single = len(whats) == 1
    stages = {w: _stage(w, args, nominal, not args.no_progress) for w in whats}
    truth = nominal
    for st in stages.values():  # the true device has every stage's errors at once
        truth = st.perturb(truth, args.perturb)
    rig, reports = nominal, {}
    for what, st in stages.items():
        try:
            rig, reports[what] = st.run(rig, truth)
        except st.errors as e:
            raise ValueError(f"calibration failed ({what}), no rig written: {e}") from None
    head = {"rig": nominal.name, "perturb_seed": args.perturb, "seed": args.seed}
    doc = ({**head, **stages[whats[0]].doc, "cameras": reports[whats[0]]} if single else
           {**head, "stages": {w: {**st.doc, "cameras": reports[w]} for w, st in stages.items()}})
    _write(Path(args.output), rig, truth, doc)
    w = max(len(n) for r in reports.values() for n in r)
    for what, report in reports.items():
        for name, r in report.items():
            tag = "" if single else f"{what:<10}  "
            print(f"{tag}{name:<{w}}  {stages[what].line(r)}  {'pass' if r['passed'] else 'FAIL'}")
    print(f"calibrated rig: {args.output}/rig (truth: {args.output}/truth, report: {args.output}/report.json)")
    # --validate: the goals are the exit status (as `hemicube validate`'s); without it a calibration that ran is a
    # success, its scores reported beside it
    missed = not all(r["passed"] for report in reports.values() for r in report.values())
    return 1 if missed and args.validate else 0


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
                       "folder and a report scored against the truth (built: cameras, vignetting, LEDs, colour)")
    s.add_argument("what", nargs="+", choices=(*STAGES, "all"), help="what to calibrate. Several (or all): each "
                   "in the order cameras, vignetting, colour, leds, on the rig the ones before it calibrated, against "
                   "one true device with all their errors")
    s.add_argument("--rig", default="paper", help="built-in rig or rig folder: the nominal values (default: %(default)s)")
    s.add_argument("--perturb", type=int, metavar="SEED", help="the true device is the nominal rig with seeded "
                   "errors (twin.rig.perturb); default: the nominal rig itself")
    s.add_argument("--views", type=int, default=8, help="board poses per camera (default: %(default)s)")
    s.add_argument("--board-scale", type=int, default=1, help="cameras: photograph the board on a sensor of S x S "
                   "times the camera's pixels, the same lens, and scale the result back (default: %(default)s; the "
                   "mini rig's cameras need 12, the paper rig's size)")
    s.add_argument("--seed", type=int, default=0, help="seed of the board poses and the photos' noise (default: "
                   "%(default)s)")
    s.add_argument("--frames", type=int, default=None, help="frames averaged per photo (vignetting: flat-field "
                   "and acrylic photos, default 32; leds and colour: plate and chart photos, default 16)")
    s.add_argument("--led-step", type=int, default=1, help="leds, bottom: calibrate every N-th upper (bottom) LED, "
                   "the others keep their nominal values; colour: light every N-th upper LED (default: %(default)s, "
                   "all)")
    s.add_argument("--binning", type=int, default=1, help="leds, bottom, colour: bin the cameras' pixels B x B for "
                   "the photos (default: %(default)s; the paper rig's 2664 x 2304 photos at 12 give 222 x 192)")
    s.add_argument("-o", "--output", required=True, help="folder for rig/, truth/ and report.json (replaced)")
    s.add_argument("--validate", action="store_true", help="exit 1 when a calibration misses a goal against the "
                   "twin's truth (the scores are in the report and printed either way)")
    s.add_argument("--no-progress", action="store_true", help="no progress lines on stderr")
    s.set_defaults(func=cmd_calibrate)
