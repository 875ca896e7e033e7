"""The twin's sub-commands of `hemicube` (registered by the front, hemicube.cli): rig, show, capture,
capture-many, controller, samples, patterns, and the twin's benchmarks (bench lumitexel, capture, led-link,
resume, camera-faults, metering-faults). Options and printing only: the work is in the modules each command calls."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from twin.exitcodes import EXIT_IO

RIG_HELP = "built-in rig (paper, mini) or rig folder (default: %(default)s)"


def _rig_arg(value: str):
    import twin

    return twin.load_rig(value)


def cmd_rig_info(args) -> int:
    rig = _rig_arg(args.rig)
    info = rig.summary()
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"rig {info['name']}: {info['num_leds']} LEDs ({info['num_upper_leds']} upper, "
          f"{info['num_bottom_leds']} bottom), unit {info['length_unit']}")
    for b in info["boards"]:
        print(f"  board {b['name']:<8} face {b['face']:<6} grid {b['grid'][0]}x{b['grid'][1]}: {b['leds']} LEDs")
    print(f"  bounding box min {info['bounding_box']['min']} max {info['bounding_box']['max']} mm")
    for name, c in info["cameras"].items():
        print(f"  camera {name}: centre {c['centre']} mm, {c['resolution'][0]}x{c['resolution'][1]} px, "
              f"fx {c['fx']:.2f} fy {c['fy']:.2f} cx {c['cx']:.2f} cy {c['cy']:.2f}"
              + (" (ASSUMED)" if c["assumed"] else ""))
    print(f"  digest {info['digest']}")
    return 0


def cmd_rig_import(args) -> int:
    from twin.outputs import claim_output
    from twin.rig.format import RIG_FOLDER, save_rig
    from twin.rig.opensvbrdf_import import import_opensvbrdf

    replace = claim_output(args.output, RIG_FOLDER, [("the folder being imported", args.dir)], force=args.force)
    rig = import_opensvbrdf(args.dir)
    out = save_rig(rig, args.output, overwrite=replace)
    print(f"imported {rig.num_leds} LEDs and {len(rig.cameras)} camera(s) from {args.dir} -> {out}")
    return 0


def cmd_rig_export(args) -> int:
    from twin.outputs import claim_output
    from twin.rig.format import RIG_FOLDER, save_rig

    if args.gltf is not None:
        from twin.view.gltf import export_gltf

        _refuse_existing("--gltf", args.gltf, args.force)
        rig = _rig_arg(args.rig)
        out = export_gltf(rig, args.gltf)
        print(f"wrote rig {rig.name!r} ({rig.num_leds} LEDs, {len(rig.cameras)} cameras) as glTF to {out}")
        return 0
    replace = claim_output(args.output, RIG_FOLDER, [("the rig being exported", args.rig)], force=args.force)
    rig = _rig_arg(args.rig)
    out = save_rig(rig, args.output, overwrite=replace)
    print(f"wrote rig {rig.name!r} ({rig.num_leds} LEDs) to {out}")
    return 0


def _refuse_existing(option: str, path: str, force: bool) -> None:
    """An output file given to `option` that exists is replaced only with --force."""
    if Path(path).exists() and not force:
        raise ValueError(f"{option} {path}: the file exists; --force replaces it")


def _frame_index(path: str, index: int, count: int) -> int:
    """`index`, checked against a pattern file's `count` frames."""
    if not 0 <= index < count:
        raise ValueError(f"{path}: frame {index} out of range 0..{count - 1}")
    return index


def load_led_frames(path: str, rig) -> tuple[np.ndarray, list[str] | None]:
    """Per-LED values from a .npy file ((L,) or (L, 3), never unpickled; names None) or every frame of a pattern file
    ((N, L, 3) drive weights and the frames' names)."""
    p = Path(path)
    if p.suffix == ".npy":
        try:
            v = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise ValueError(f"{p}: not a readable .npy array ({e})") from None
        if v.ndim not in (1, 2) or v.shape[0] != rig.num_leds or (v.ndim == 2 and v.shape[1] != 3):
            raise ValueError(f"{p}: expected ({rig.num_leds},) or ({rig.num_leds}, 3) values, got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{p}: values contain NaN or Inf")
        return v, None
    from twin.capture.patterns import load_patterns

    ps = load_patterns(p)
    ps.check_rig(rig)
    return ps.weights, list(ps.names)


def load_led_values(path: str, rig, index: int = 0) -> tuple[np.ndarray, str]:
    """A per-LED vector from a .npy file or one frame of a pattern file (load_led_frames), and what it is (the file,
    and the frame's index and name)."""
    v, names = load_led_frames(path, rig)
    if names is None:
        return v, Path(path).name
    index = _frame_index(path, index, len(names))
    return v[index], f"{Path(path).name}, frame {index}: {names[index]}"


def cmd_show_rig(args) -> int:
    rig = _rig_arg(args.rig)
    if args.html is not None:
        from twin.view.rig_page import write_rig_page

        _refuse_existing("--html", args.html, args.force)
        values, names = load_led_frames(args.values, rig) if args.values else (None, None)
        start = _frame_index(args.values, args.index, len(names)) if names is not None else 0
        out = write_rig_page(rig, args.html, values, names, title=Path(args.values).name if args.values else "",
                             start=start)
        print(f"wrote {out}")
        return 0
    from twin.view.rig_view import show_rig

    values, what = load_led_values(args.values, rig, args.index) if args.values else (None, "")
    out = show_rig(rig, values=values, output=args.output, window_size=tuple(args.size), title=what)
    if out is not None:
        print(f"wrote {out}")
    return 0


def cmd_show_pattern(args) -> int:
    from twin.capture.patterns import load_patterns
    from twin.view.cross_plot import save_pattern_image

    ps = load_patterns(args.file)
    rig = _rig_arg(args.rig or ps.rig)
    ps.check_rig(rig)
    out = save_pattern_image(ps, rig, args.output, index=args.index)
    print(f"wrote {out}")
    return 0


def cmd_capture(args) -> int:
    from twin.capture.runner import capture
    from twin.capture.session import CAPTURE_FOLDER, verify
    from twin.outputs import claim_output

    claim_output(args.output, CAPTURE_FOLDER, [("the rig folder", args.rig), ("the true rig's folder", args.truth),
                                               ("the sample's maps", args.sample), ("the pattern file", args.patterns)])
    learned = None
    if args.patterns:
        from twin.capture.patterns import load_patterns

        learned = load_patterns(args.patterns)
    rig = _rig_arg(args.rig)
    if learned is not None:
        learned.check_rig(rig)
    devices = {"led": args.led, "led_baud": args.led_baud, "cameras": args.cameras,
               "camera_serials": args.camera_serials.split(",") if args.camera_serials else None,
               "camera_faults": args.camera_faults,
               "prompt": input if args.backend == "hardware" and args.cameras == "basler" else None}
    devices = {k: v for k, v in devices.items() if v is not None}  # the simulator refuses any
    out = capture(rig, args.sample, args.output, seed=args.seed, backend=args.backend, device=args.device,
                  resolution=args.resolution, learned=learned, progress=not args.no_progress, devices=devices,
                  truth=_rig_arg(args.truth) if args.truth else None, frames=args.frames,
                  break_lock=args.break_lock, raw=args.raw)
    bad = verify(out)
    if bad:
        print(f"hemicube: error: {len(bad)} file(s) fail their checksum: {bad[:5]}", file=sys.stderr)
        return EXIT_IO
    print(f"capture complete: {out} (manifest verified)")
    return 0


def cmd_capture_many(args) -> int:
    from twin.batch import RECORD_FILE, options_from, report
    from twin.capture.many import capture_many, table

    outcomes = capture_many(args.samples, args.output, args.device, options_from(args, args.device))
    return report(outcomes, table(outcomes), f"{args.output}/{RECORD_FILE}")


def cmd_controller_info(args) -> int:
    from twin.capture.backends.led_host import LedController

    with LedController(args.led, baudrate=args.baud) as ctl:
        state = ctl.query()
        print(json.dumps({"url": args.led, "firmware": ctl.info.firmware, "protocol": ctl.info.version,
                          "leds": ctl.info.num_leds, "slots": ctl.info.slots, "max_payload": ctl.info.max_payload,
                          "boot_id": f"{state.boot_id:08x}", "displayed_slot": state.displayed_slot,
                          "displayed_crc": f"{state.displayed_crc:08x}", "rejected_frames": state.rejected,
                          "stored_patterns": len(ctl.stored())}, indent=2))
    return 0


def cmd_bench(args) -> int:
    from twin.bench import bench_capture, bench_exit, bench_lumitexel
    from twin.capture import reliability

    if args.bench_command in ("led-link", "resume", "camera-faults", "metering-faults"):
        import tempfile

        work = args.workdir or tempfile.mkdtemp(prefix=f"hemicube-bench-{args.bench_command}-")
        if args.bench_command == "led-link":
            res = reliability.bench_led_link(args.uploads, args.leds, args.rate, args.flip, tuple(args.kinds),
                                             args.timeout, args.delay, args.link, args.seed, work)
        elif args.bench_command == "resume":
            res = reliability.bench_resume(args.kills, args.seed, work)
        elif args.bench_command == "metering-faults":
            res = reliability.bench_metering_faults(args.injections, args.rate, args.seed, work, args.scale)
        else:
            res = reliability.bench_camera_faults(args.faults, args.seed, work)
        print(json.dumps({**res, "workdir": str(work)}, indent=2))
        return 0
    if args.bench_command == "lumitexel":
        res = bench_lumitexel(args.rig, args.device, args.leds, args.points, args.patterns, args.repeats,
                              not args.no_compile)
    else:
        res = bench_capture(args.rig, args.device, args.sample, args.resolution, args.seed, args.scale,
                            output=args.output, frames=args.frames)
    print(json.dumps(res, indent=2))
    return bench_exit(res)


def _pattern_image_args(s) -> None:
    """`show pattern` and `patterns show`: the same command under both names."""
    s.add_argument("file", help="a pattern file (.npz, twin.capture.patterns format)")
    s.add_argument("-o", "--output", required=True, help="PNG path to write")
    s.add_argument("--rig", help="rig the frames are drawn on (default: the one the pattern file names)")
    s.add_argument("--index", type=int, help="only this frame, 0-based (default: every frame)")
    s.set_defaults(func=cmd_show_pattern)


# the sub-commands this package adds and their one-line help: what `hemicube --help` lists without importing
# the package's heavy modules (hemicube.cli.build_parser)
COMMANDS = {
    "rig": "inspect, import and export rigs",
    "show": "pictures of the rig and of patterns",
    "capture": "run the capture plan (193+ HDR photos) into a session folder",
    "capture-many": "simulated database construction: one capture per sample of a SAMPLES.toml, on Ray (skips "
                    "finished captures, retries failures)",
    "controller": "the LED controller: its firmware emulator, and a status query",
    "samples": "the built-in material samples",
    "patterns": "pattern files",
}


class _Deprecated(argparse.Action):
    """An option's old name, kept for one version: it still works, with one line on stderr naming the new one."""

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string in self.const:
            print(f"{parser.prog}: {option_string} is deprecated: {self.const[option_string]}", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_sample_resolution(parser, default: int, what: str) -> None:
    """--sample-resolution: the sample's maps, texels per side. Its old name --resolution is kept for one version:
    elsewhere --resolution is the texture grid (reconstruct, validate), one name with two meanings."""
    parser.add_argument("--sample-resolution", "--resolution", dest="resolution", type=int, default=default,
                        action=_Deprecated, metavar="N", help=f"{what} (default: %(default)s; --resolution, its old "
                        "name, is deprecated: elsewhere it is the texture grid)",
                        const={"--resolution": "use --sample-resolution (the sample's maps; --resolution is the "
                               "texture grid in reconstruct and validate)"})


def register(sub) -> None:
    """Add the twin's sub-commands to the front's parser."""
    from twin.capture.plan import DEFAULT_FRAMES, DEFAULT_SEED, FRAMES_HELP
    from twin.lock import BREAK_LOCK_HELP

    rig = sub.add_parser("rig", help=COMMANDS["rig"]).add_subparsers(dest="rig_command", required=True)
    s = rig.add_parser("info", help="LED counts per board, bounding box, cameras")
    s.add_argument("rig", help="built-in rig name (paper, mini) or rig folder")
    s.add_argument("--json", action="store_true", help="print JSON (digest, intrinsics, centres) instead of text")
    s.set_defaults(func=cmd_rig_info)
    s = rig.add_parser("import-opensvbrdf", help="import the released OpenSVBRDF configuration files")
    s.add_argument("dir", help="folder with lights.bin, intrinsic.yml, extrinsic.yml, ...")
    s.add_argument("-o", "--output", required=True, help="rig folder to write")
    s.add_argument("--force", action="store_true", help="replace an existing rig folder (never another kind of "
                   "folder, nor a file)")
    s.set_defaults(func=cmd_rig_import)
    s = rig.add_parser("export", help="write a rig (e.g. a built-in one) as a rig folder, or as a glTF scene")
    s.add_argument("rig", help="built-in rig name (paper, mini) or rig folder")
    to = s.add_mutually_exclusive_group(required=True)
    to.add_argument("-o", "--output", help="rig folder to write")
    to.add_argument("--gltf", metavar="FILE", help="write the rig as glTF 2.0 instead (.glb, or .gltf with its data "
                    "embedded): boards, an instanced LED node each, camera nodes; in metres, +Y up (twin.view.gltf)")
    s.add_argument("--force", action="store_true", help="replace an existing rig folder (never another kind of "
                   "folder, nor a file), or an existing --gltf file")
    s.set_defaults(func=cmd_rig_export)

    show = sub.add_parser("show", help=COMMANDS["show"]).add_subparsers(dest="show_command", required=True)
    s = show.add_parser("rig", help="3-D view of the rig: a PNG (pyvista, off-screen), a window, or an interactive web page (--html)")
    s.add_argument("--rig", default="paper", help=RIG_HELP)
    s.add_argument("--values", help="per-LED values to colour the LEDs: .npy (L,) or (L, 3), or a pattern file "
                   "(default: LEDs coloured by board)")
    s.add_argument("--index", type=int, default=0, help="frame of the pattern file given to --values, 0-based "
                   "(default: %(default)s)")
    where = s.add_mutually_exclusive_group()
    where.add_argument("-o", "--output", help="PNG path; without it (and without --html) an interactive window opens")
    where.add_argument("--html", metavar="OUT.html", help="write a self-contained interactive page instead: turn it "
                       "in any browser, no network; with a pattern file, a selector for every frame (--index first)")
    s.add_argument("--force", action="store_true", help="replace an existing --html file")
    s.add_argument("--size", type=int, nargs=2, default=(1200, 900), metavar=("W", "H"),
                   help="image size in pixels (default: %(default)s)")
    s.set_defaults(func=cmd_show_rig)
    _pattern_image_args(show.add_parser("pattern", help="a pattern set as unfolded-cube (cross) images"))

    s = sub.add_parser("capture", help=COMMANDS["capture"])
    s.add_argument("--backend", default="sim", help="device backend: sim (the simulator) or hardware (the LED "
                   "controller and pypylon cameras) (default: %(default)s)")
    s.add_argument("--led", help="hardware: the LED controller's pyserial URL (/dev/ttyACM0, socket://HOST:PORT "
                   "of `hemicube controller serve`, a pty path); a token it asks for: $HEMICUBE_LED_TOKEN")
    s.add_argument("--led-baud", type=int, help="hardware: baud rate of a UART link (USB CDC and sockets ignore "
                   "it; default 2000000)")
    s.add_argument("--cameras", choices=("emulated", "basler"), help="hardware: pylon's camera emulation fed by "
                   "the twin, or the rig's a2A5328-15ucPRO cameras")
    s.add_argument("--camera-serials", help="hardware, basler: serial numbers in the rig's camera order, "
                   "comma-separated (default: the cameras whose DeviceUserID is the rig camera's name)")
    s.add_argument("--camera-faults", help="hardware, emulated: faults injected before triggers, e.g. "
                   "failed=0.02,disconnect=0.005,stray=0.01,seed=1 (docs/reliability.md)")
    s.add_argument("--rig", default="mini", help=RIG_HELP)
    s.add_argument("--truth", help="sim: the rig the twin renders with (a true device, e.g. `hemicube calibrate "
                   "--perturb`'s truth/), while the capture records --rig (its calibration)")
    s.add_argument("--sample", default="ramps", help="built-in sample (`hemicube samples list`) or a folder of "
                   "OpenSVBRDF maps (default: %(default)s)")
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the sensor noise and of seeded samples "
                   "(default: %(default)s)")
    add_sample_resolution(s, 128, "texels per side of a built-in sample's maps")
    s.add_argument("--frames", type=int, default=DEFAULT_FRAMES, help=FRAMES_HELP)
    s.add_argument("--raw", action="store_true", help="also write every photo's raw sensor frames (BayerRG12p, "
                   "12-bit packed), which reconstruction does not read: three times the bytes at four frames an "
                   "exposure (the paper rig: 43 GB against 14 GB); a folder resumes only with the choice it was made "
                   "with")
    s.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:N (default: %(default)s)")
    s.add_argument("--patterns", help="pattern file with the learned frames, K (+, -) pairs (a `hemicube train` "
                   "run's patterns.npz; default: the rig's own 64, else a seeded placeholder)")
    s.add_argument("-o", "--output", required=True, help="capture folder (re-run to resume; any other existing "
                   "path is refused)")
    s.add_argument("--break-lock", action="store_true", help=BREAK_LOCK_HELP)
    s.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    s.set_defaults(func=cmd_capture)

    from twin.batch import add_arguments

    s = sub.add_parser("capture-many", help=COMMANDS["capture-many"])
    s.add_argument("samples", help="SAMPLES.toml: defaults and [[sample]] entries (twin/capture/many.py)")
    s.add_argument("-o", "--output", required=True, help="folder for one capture folder per sample and batch.json")
    s.add_argument("--device", default="cpu", help="cpu or cuda: with cuda, one GPU per task (default: %(default)s)")
    add_arguments(s)
    s.set_defaults(func=cmd_capture_many, device_here=False)  # --device: the Ray workers' (twin.batch)

    ctl = sub.add_parser("controller", help=COMMANDS["controller"])
    ctl = ctl.add_subparsers(dest="controller_command", required=True)
    from twin.capture.backends import led_emulator

    s = ctl.add_parser("serve", help="run the controller's firmware emulator (docs/led-protocol.md) until "
                       "SIGTERM/Ctrl-C; prints `serving URL` first")
    led_emulator.add_arguments(s)
    s.set_defaults(func=led_emulator.run)
    s = ctl.add_parser("info", help="what a controller reports: LEDs, slots, boot id, displayed pattern (JSON)")
    s.add_argument("--led", required=True, help="the controller's pyserial URL: /dev/ttyACM0, socket://HOST:PORT, "
                   "a pty path; a token it asks for: $HEMICUBE_LED_TOKEN")
    s.add_argument("--baud", type=int, default=2_000_000, help="baud rate of a UART link (ignored by USB CDC and "
                   "sockets) (default: %(default)s)")
    s.set_defaults(func=cmd_controller_info)

    s = sub.add_parser("samples", help=COMMANDS["samples"]).add_subparsers(dest="samples_command", required=True)
    s = s.add_parser("list", help="built-in samples with their parameter ranges")
    s.add_argument("--json", action="store_true", help="print JSON instead of a table")
    s.set_defaults(func=cmd_samples_list)

    pats = sub.add_parser("patterns", help=COMMANDS["patterns"]).add_subparsers(dest="patterns_command", required=True)
    _pattern_image_args(pats.add_parser("show", help="a pattern set as unfolded-cube (cross) images"))


def register_bench(bench) -> None:
    """Add the twin's benchmarks to the front's `bench` group."""
    from twin.capture.plan import DEFAULT_FRAMES, DEFAULT_SEED, FRAMES_HELP

    s = bench.add_parser("lumitexel", help="LED-BRDF evaluations per second vs a plain torch baseline")
    s.add_argument("--rig", default="paper", help=RIG_HELP)
    s.add_argument("--device", default="cpu", help="Warp/torch device: cpu, cuda (default: %(default)s)")
    s.add_argument("--leds", type=int, help="use the first N LEDs of the rig (default: all)")
    s.add_argument("--points", type=int, default=4096, help="surface points (default: %(default)s)")
    s.add_argument("--patterns", type=int, default=64, help="patterns projected onto (default: %(default)s)")
    s.add_argument("--repeats", type=int, default=5, help="timed repeats, the best is kept (default: %(default)s)")
    s.add_argument("--no-compile", action="store_true", help="skip the torch.compile baseline")
    s.set_defaults(func=cmd_bench)
    s = bench.add_parser("capture", help="seconds for the full capture plan's simulation, by stage")
    s.add_argument("--rig", default="paper", help=RIG_HELP)
    s.add_argument("--device", default="cpu", help="Warp device: cpu, cuda (default: %(default)s)")
    s.add_argument("--sample", default="ramps", help="built-in sample (default: %(default)s)")
    add_sample_resolution(s, 1024, "texels per side of the sample's maps")
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="the capture's seed (default: %(default)s)")
    s.add_argument("--scale", type=float, default=1.0, help="resize the cameras by this factor, e.g. 0.5 for a "
                   "quick run (default: %(default)s)")
    s.add_argument("--frames", type=int, default=DEFAULT_FRAMES, help=FRAMES_HELP)
    s.add_argument("-o", "--output", help="also run `hemicube capture` into this folder, files written, and time it")
    s.set_defaults(func=cmd_bench)

    from twin.capture.backends.faults import FAULT_KINDS

    s = bench.add_parser("led-link", help="pattern uploads through the LED controller emulator, one fault kind "
                         "at a time, then random bit errors (docs/reliability.md)")
    s.add_argument("--uploads", type=int, default=10_000, help="uploads per fault kind (default: %(default)s)")
    s.add_argument("--leds", type=int, default=16_384, help="LEDs per pattern (default: %(default)s, the paper rig)")
    s.add_argument("--rate", type=float, default=0.01, help="share of frames hit by the fault (default: %(default)s)")
    s.add_argument("--flip", type=float, default=1e-5, help="bit-error probability per byte of the last run; 0: "
                   "no such run (default: %(default)s)")
    s.add_argument("--kinds", nargs="*", default=list(FAULT_KINDS), choices=list(FAULT_KINDS),
                   help="fault kinds, one run each (default: all)")
    s.add_argument("--timeout", type=float, default=0.03, help="the host's reply timeout, s, beyond the frame's "
                   "time on the wire (default: %(default)s)")
    s.add_argument("--delay", type=float, default=0.06, help="how long a delayed frame is held, s: longer than "
                   "the host waits, so that every delay ends in a timeout (default: %(default)s)")
    s.add_argument("--link", choices=("pty", "socket"), default="pty", help="the emulator's link (default: "
                   "%(default)s)")
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the patterns and the faults (default: "
                   "%(default)s)")
    s.add_argument("-o", "--workdir", help="folder for the emulator logs (default: a new temporary folder)")
    s.set_defaults(func=cmd_bench)
    s = bench.add_parser("resume", help="a mini capture over the emulated devices SIGKILLed at random points and "
                         "resumed, checked against the simulator's (docs/reliability.md)")
    s.add_argument("--kills", type=int, default=20, help="kill points (default: %(default)s)")
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the kill points and faults (default: "
                   "%(default)s)")
    s.add_argument("-o", "--workdir", help="folder for the captures (default: a new temporary folder)")
    s.set_defaults(func=cmd_bench)
    s = bench.add_parser("camera-faults", help="a mini capture with camera faults injected, checked against the "
                         "simulator's (docs/reliability.md)")
    s.add_argument("--faults", default="failed=0.02,disconnect=0.005,stray=0.02", help="camera faults per trigger "
                   "(default: %(default)s)")
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the faults (default: %(default)s)")
    s.add_argument("-o", "--workdir", help="folder for the captures (default: a new temporary folder)")
    s.set_defaults(func=cmd_bench)
    s = bench.add_parser("metering-faults", help="mini-rig photos with the LED controller reset before their "
                         "metering, each checked against the simulator's (docs/reliability.md)")
    s.add_argument("--injections", type=int, default=100, help="photos the fault must hit (default: %(default)s)")
    s.add_argument("--rate", type=float, default=0.25, help="share of pattern latches after which the controller "
                   "browns out (default: %(default)s)")
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the faults (default: %(default)s)")
    s.add_argument("--scale", type=float, default=1.0, help="resize the cameras by this factor, e.g. 0.5 for a "
                   "quick run (default: %(default)s)")
    s.add_argument("-o", "--workdir", help="folder for the emulator's log (default: a new temporary folder)")
    s.set_defaults(func=cmd_bench)


def cmd_samples_list(args) -> int:
    from twin.materials.samples import BUILTIN_SAMPLES, sample_ranges

    rows = {name: sample_ranges(name) for name in BUILTIN_SAMPLES}
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'sample':<14} {'rho_d':>13} {'rho_s':>13} {'alpha_x':>13} {'alpha_y':>13} {'ax/ay':>9} {'tilt':>6}"
          "  character")
    for name, r in rows.items():
        ax, ay, an = r["alpha_x"], r["alpha_y"], r["anisotropy"]
        print(f"{name:<14} {r['rho_d'][0]:5.3f}-{r['rho_d'][1]:<6.3f} {r['rho_s'][0]:5.2f}-{r['rho_s'][1]:<6.2f} "
              f"{ax[0]:5.3f}-{ax[1]:<6.3f} {ay[0]:5.3f}-{ay[1]:<6.3f} {an[0]:3.1f}-{an[1]:<4.1f} "
              f"{r['tilt_deg'][1]:5.1f}°  {r['description']}")
    return 0
