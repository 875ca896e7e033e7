"""`hemicube calibrate WHAT... -o OUT`: the command's options and its printed summary. The calibration itself,
each procedure's capture in the twin, its calibration from those photos and its scores against the twin's truth,
run in a lab's order, is calibration.lab's (the procedures: calibration.cameras, vignetting, colour, leds)."""
from __future__ import annotations

from pathlib import Path

from .lab import CALIBRATION_FOLDER, STAGES, calibrate, report_doc, stage, write


def cmd_calibrate(args) -> int:
    import twin
    from twin.outputs import claim_output

    claim_output(args.output, CALIBRATION_FOLDER, [("the nominal rig's folder", args.rig)])
    nominal = twin.load_rig(args.rig)
    if "all" in args.what and len(args.what) > 1 or len(set(args.what)) < len(args.what):
        raise ValueError(f"calibrate {' '.join(args.what)}: name each procedure once, or 'all' alone")
    whats = STAGES if args.what == ["all"] else tuple(w for w in STAGES if w in args.what)  # in the lab's order
    single = len(whats) == 1
    stages = {w: stage(w, nominal, frames=args.frames, led_step=args.led_step, binning=args.binning,
                       views=args.views, board_scale=args.board_scale, seed=args.seed, perturb=args.perturb,
                       progress=not args.no_progress) for w in whats}
    rig, truth, reports = calibrate(nominal, stages, args.perturb)
    write(Path(args.output), rig, truth, report_doc(nominal, stages, reports, args.perturb, args.seed))
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


# the sub-commands this package adds and their one-line help: what `hemicube --help` lists without importing
# the package's heavy modules (hemicube.cli.build_parser)
COMMANDS = {
    "calibrate": "calibrate from photographs of targets in the twin; write a calibrated rig folder and a report"
                 " scored against the truth (built: cameras, vignetting, LEDs, colour)",
}


def register(sub) -> None:
    from twin.capture.plan import DEFAULT_SEED

    s = sub.add_parser("calibrate", help=COMMANDS["calibrate"])
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
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the board poses and the photos' noise "
                   "(default: %(default)s)")
    s.add_argument("--frames", type=int, default=None, help="frames averaged per photo (vignetting: flat-field "
                   "and acrylic photos, default 32; leds and colour: plate and chart photos, default 16)")
    s.add_argument("--led-step", type=int, default=1, help="leds, bottom: calibrate every N-th upper (bottom) LED, "
                   "the others keep their nominal values; colour: light every N-th upper LED (default: %(default)s, "
                   "all)")
    s.add_argument("--binning", type=int, default=1, help="leds, bottom, colour: bin the cameras' pixels B x B for "
                   "the photos (default: %(default)s; the paper rig's 2664 x 2304 photos at 12 give 222 x 192)")
    s.add_argument("-o", "--output", required=True, help="folder for rig/, truth/ and report.json (a "
                   "calibration folder there is replaced whole; any other existing path is refused)")
    s.add_argument("--validate", action="store_true", help="exit 1 when a calibration misses a goal against the "
                   "twin's truth (the scores are in the report and printed either way)")
    s.add_argument("--no-progress", action="store_true", help="no progress lines on stderr")
    s.set_defaults(func=cmd_calibrate)
