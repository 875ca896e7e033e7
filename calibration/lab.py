"""Calibration in the twin as a lab runs it (`hemicube calibrate`): each procedure photographs a true device
(the nominal rig with seeded errors, twin.rig.perturb), calibrates from those photos alone and is scored against
the truth, one procedure after the other in a lab's order (`STAGES`) on the rig the ones before it calibrated;
then the calibrated rig, the truth and the report are written as one folder.

    stages = {w: stage(w, nominal, frames=None, led_step=1, binning=1, views=8, board_scale=1, seed=0, perturb=3)
              for w in STAGES}
    rig, truth, reports = calibrate(nominal, stages, perturb=3)
    write(out, rig, truth, report_doc(nominal, stages, reports, perturb=3, seed=0))

The procedures are the modules': calibration.cameras.calibrate_cameras, vignetting.calibrate_vignetting,
colour.calibrate_colour, leds.calibrate_leds_from_plate (the LEDs and the bottom LEDs)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from twin.outputs import Kind

from .cameras import CAMERA_GOALS, CalibrationError, calibrate_cameras
from .colour import COLOUR_GOALS, ColourCalibrationError, calibrate_colour
from .leds import LED_GOALS, LEDCalibrationError, calibrate_leds_from_plate
from .vignetting import FLAT_FIELD_GOAL_PCT, FlatFieldError, calibrate_vignetting

__all__ = ["STAGES", "CALIBRATION_FOLDER", "Stage", "stage", "calibrate", "report_doc", "write"]


# a lab's order: each procedure takes the rig the ones before it calibrated (the colour and the LEDs photograph
# the plate through the calibrated cameras and flat fields; the LEDs' intensities are in the calibrated colour)
STAGES = ("cameras", "vignetting", "colour", "leds", "bottom")
REPORT = "report.json"
# OUT, replaced whole by the next calibration (twin.outputs): its report names it
CALIBRATION_FOLDER = Kind("a calibration folder", (REPORT,))


@dataclass(frozen=True)
class Stage:
    perturb: Callable  # (rig, seed or None) -> the true device with this stage's errors
    errors: type       # the procedure's own error: named photos, no rig written
    run: Callable      # (the rig calibrated so far, truth) -> (rig, report per camera)
    doc: dict          # the settings, for report.json
    line: Callable     # a camera's report -> its summary line


def stage(what: str, nominal, *, frames: int | None, led_step: int, binning: int, views: int, board_scale: int,
          seed: int, perturb: int | None, progress: bool = True) -> Stage:
    """Procedure `what` of STAGES on the rig `nominal`, set up: how the true device gets its errors, the procedure
    with these settings (frames None: each procedure's default), its settings for the report and its summary
    line. The settings are `hemicube calibrate`'s options of the same names; a bad one is refused by name.

    what         "cameras", "vignetting", "colour", "leds" or "bottom"
    frames       frames averaged per photo (None: 16 for leds and colour, 32 for the others)
    led_step     every N-th LED (leds, bottom: calibrated; colour: lit); binning: camera pixels binned B x B
    views        board poses per camera (cameras, >= 4); board_scale: the board photographed on S x S times the
                 camera's pixels (cameras)
    seed         the board poses and the photos' noise; perturb: the true device's error seed (None: none)"""
    from twin.rig.perturb import perturb_cameras, perturb_leds, perturb_vignetting

    frames = frames if frames is not None else (16 if what in ("leds", "colour") else 32)
    seeded = lambda f: (lambda rig, seed: rig if seed is None else f(rig, seed))  # noqa: E731
    if min(frames, led_step, binning) < 1:
        raise ValueError(f"--frames {frames}, --led-step {led_step}, --binning {binning}: each must be at "
                         "least 1")
    if what in ("leds", "bottom"):
        def line(r):
            p, f, n = r["position_mm"], r["profile_shape_pct"], r["nominal_error"]["position_mm"]
            return (f"{r['calibrated']} LEDs: position median {p['median']:.2f} mm (p90 {p['p90']:.2f}, nominal "
                    f"{n['median']:.2f})  normal {r['normal_deg']['median']:.2f} deg  profile {f['median']:.2f}% "
                    f"(p90 {f['p90']:.2f}%)  emission {r['emission_pct']['median']:.2f}%")
        bottom = what == "bottom"
        if bottom and (nominal.bottom is None or not nominal.is_bottom.any()):
            raise ValueError(f"calibrate bottom: rig {nominal.name!r} has no bottom LEDs")
        return Stage(seeded(lambda rig, seed: perturb_leds(rig, seed, bottom=bottom)), LEDCalibrationError,
                     lambda known, truth: calibrate_leds_from_plate(known, truth, frames, seed, led_step,
                                                                    binning, progress, bottom=bottom),
                     {"frames": frames, "led_step": led_step, "binning": binning, "goals": LED_GOALS}, line)
    if what == "colour":
        from twin.camera.spectral import device_spectra, with_crosstalk

        spectra = device_spectra(nominal.cameras, perturb)

        def line(r):
            d = r["delta_e2000"]
            return (f"ColorChecker ΔE2000 median {d['median']:.2f} (p90 {d['p90']:.2f}, max {d['max']:.2f})  crosstalk "
                    f"residual {100 * r['crosstalk_residual_max']:.3f}% (nominal rig: "
                    f"{100 * r['nominal_error']['crosstalk_residual_max']:.1f}%)")
        # the truth's colour is always its spectra's (without --perturb, the nominal spectra's crosstalk: the
        # nominal rigs' identity is an idealised sensor that no real colour filter has)
        return Stage(lambda rig, seed: with_crosstalk(rig, spectra), ColourCalibrationError,
                     lambda known, truth: calibrate_colour(known, truth, spectra, frames, seed, led_step,
                                                           binning, progress),
                     {"frames": frames, "led_step": led_step, "binning": binning, "goals": COLOUR_GOALS,
                      "spectra": spectra.to_dict()}, line)
    if what == "vignetting":
        def line(r):
            f, m = r["flat_field_pct"], r["radial_model_pct"]
            return (f"flat field: median {f['median']:.3f}%  p95 {f['p95']:.3f}%  max {f['max']:.2f}%   radial model "
                    f"alone: p95 {m['p95']:.3f}%  max {m['max']:.2f}%")
        return Stage(seeded(perturb_vignetting), FlatFieldError,
                     lambda known, truth: calibrate_vignetting(known, truth, frames, seed, progress),
                     {"frames": frames, "goal": {"flat_field_pct_p95": FLAT_FIELD_GOAL_PCT}}, line)
    if views < 4 or board_scale < 1:
        raise ValueError(f"--views {views}, --board-scale {board_scale}: the intrinsics need >= 4 views of "
                         "the board, and the scale is at least 1")

    def line(r):
        return (f"RMS {r['rms_px']:.3f} px  focal {r['focal_pct']:.4f}%  principal {r['principal_px']:.2f} px  "
                f"centre {r['centre_mm']:.2f} mm  rotation {r['rotation_deg']:.3f} deg  sample "
                f"{r['sample_px_median']:.3f} px median (nominal rig: {r['nominal_error']['sample_px_median']:.2f})")
    return Stage(seeded(perturb_cameras), CalibrationError,
                 lambda known, truth: calibrate_cameras(known, truth, views, seed,
                                                        board_scale=board_scale, progress=progress),
                 {"views": views, "board_scale": board_scale, "goals": CAMERA_GOALS}, line)


def calibrate(nominal, stages: dict, perturb: int | None) -> tuple:
    """Run `stages` ({what: Stage}, in the lab's order) against one true device that has every stage's errors at
    once (perturbation seed `perturb`; None: the nominal rig), each on the rig the ones before it calibrated.
    Returns (the calibrated rig, the truth, {what: report per camera}); a procedure's own error is a ValueError
    naming it, and nothing is written. The rigs are twin Rigs (lengths in mm); each report is its procedure's
    (calibrate_cameras: pixels, %, mm, degrees; calibrate_vignetting and calibrate_colour: % and ΔE2000;
    calibrate_leds_from_plate: mm, degrees, %). `write` saves the rigs and a report.json."""
    truth = nominal
    for st in stages.values():  # the true device has every stage's errors at once
        truth = st.perturb(truth, perturb)
    rig, reports = nominal, {}
    for what, st in stages.items():
        try:
            rig, reports[what] = st.run(rig, truth)
        except st.errors as e:
            raise ValueError(f"calibration failed ({what}), no rig written: {e}") from None
    return rig, truth, reports


def report_doc(nominal, stages: dict, reports: dict, perturb: int | None, seed: int) -> dict:
    """report.json's content: the rig and seeds, then one stage's settings and reports at the top level, or several
    stages' under "stages"."""
    head = {"rig": nominal.name, "perturb_seed": perturb, "seed": seed}
    if len(stages) == 1:
        (what, st), = stages.items()
        return {**head, **st.doc, "cameras": reports[what]}
    return {**head, "stages": {w: {**st.doc, "cameras": reports[w]} for w, st in stages.items()}}


def write(output: Path, rig, truth, doc: dict) -> None:
    """OUT/rig (calibrated), OUT/truth (the true device, for scoring) and OUT/report.json, all or nothing."""
    from twin.atomic import atomic_folder
    from twin.rig.format import save_rig

    with atomic_folder(output, overwrite=True) as tmp:  # nothing is left from a failed run
        save_rig(rig, tmp / "rig")
        save_rig(truth, tmp / "truth")
        (tmp / REPORT).write_text(json.dumps(doc, indent=1) + "\n")
