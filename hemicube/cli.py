"""`hemicube`: the one command-line front for the twin, calibration and reconstruction."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


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
    from .opensvbrdf_import import import_opensvbrdf
    from .rig_format import save_rig

    rig = import_opensvbrdf(args.dir)
    out = save_rig(rig, args.output, overwrite=args.force)
    print(f"imported {rig.num_leds} LEDs and {len(rig.cameras)} camera(s) from {args.dir} -> {out}")
    return 0


def cmd_rig_export(args) -> int:
    from .rig_format import save_rig

    rig = _rig_arg(args.rig)
    out = save_rig(rig, args.output, overwrite=args.force)
    print(f"wrote rig {rig.name!r} ({rig.num_leds} LEDs) to {out}")
    return 0


def load_led_values(path: str, rig, index: int = 0) -> np.ndarray:
    """A per-LED vector from a .npy file ((L,) or (L, 3), never unpickled) or one frame of a pattern file."""
    p = Path(path)
    if p.suffix == ".npy":
        try:
            v = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise ValueError(f"{p}: not a readable .npy array ({e})") from None
    else:
        from .patterns import load_patterns

        ps = load_patterns(p)
        ps.check_rig(rig)
        if not 0 <= index < ps.num_patterns:
            raise ValueError(f"{p}: frame {index} out of range 0..{ps.num_patterns - 1}")
        v = ps.weights[index]
    if v.shape[0] != rig.num_leds or v.ndim not in (1, 2):
        raise ValueError(f"{p}: expected ({rig.num_leds},) or ({rig.num_leds}, 3) values, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{p}: values contain NaN or Inf")
    return v


def cmd_show_rig(args) -> int:
    from .view import show_rig

    rig = _rig_arg(args.rig)
    values = load_led_values(args.values, rig, args.index) if args.values else None
    out = show_rig(rig, values=values, output=args.output, window_size=tuple(args.size))
    if out is not None:
        print(f"wrote {out}")
    return 0


def cmd_show_pattern(args) -> int:
    from .cross_plot import save_pattern_image
    from .patterns import load_patterns

    ps = load_patterns(args.file)
    rig = _rig_arg(args.rig or ps.rig)
    ps.check_rig(rig)
    out = save_pattern_image(ps, rig, args.output, index=args.index)
    print(f"wrote {out}")
    return 0


def cmd_capture(args) -> int:
    from .capture import capture, verify

    learned = None
    if args.patterns:
        from .patterns import load_patterns

        learned = load_patterns(args.patterns)
    rig = _rig_arg(args.rig)
    if learned is not None:
        learned.check_rig(rig)
    out = capture(rig, args.sample, args.output, seed=args.seed, backend=args.backend, device=args.device,
                  resolution=args.resolution, learned=learned, progress=not args.no_progress)
    bad = verify(out)
    if bad:
        print(f"hemicube: error: {len(bad)} file(s) fail their checksum: {bad[:5]}", file=sys.stderr)
        return 1
    print(f"capture complete: {out} (manifest verified)")
    return 0


def cmd_validate(args) -> int:
    from .validate import run_validation

    return run_validation(rig=args.rig, sample=args.sample, device=args.device, as_json=args.json,
                          output=args.output, resolution=args.resolution, seed=args.seed,
                          progress=not args.no_progress)


def cmd_reconstruct(args) -> int:
    from dataclasses import replace

    from reconstruction.pipeline import ReconstructConfig, reconstruct

    over = {k: v for k, v in (("resolution", args.resolution), ("size_mm", args.size_mm),
                              ("holdout_line", args.holdout_line), ("network", args.network),
                              ("device", args.device)) if v is not None}
    r = reconstruct(args.capture, args.output, replace(ReconstructConfig(), **over), progress=not args.no_progress)
    print(f"reconstruction: {r.directory} ({r.grid.resolution}^2 texels over {r.grid.size_mm:.1f} mm; "
          + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in r.timings.items()) + ")")
    return 0


def cmd_bench(args) -> int:
    from .bench import run_bench

    print(json.dumps(run_bench(args), indent=2))
    return 0


def cmd_train(args) -> int:
    from dataclasses import replace

    from reconstruction.train import TrainConfig, train

    cfg = TrainConfig(rig=args.rig)
    over = {k: v for k, v in (("steps", args.steps), ("batch", args.batch), ("lr", args.lr), ("seed", args.seed),
                              ("device", args.device), ("eval_every", args.eval_every),
                              ("checkpoint_every", args.checkpoint_every),
                              ("pair_fraction", args.pair_fraction), ("dropout", args.dropout))
            if v is not None}
    cfg = replace(cfg, **over)
    m = train(cfg, args.output, progress=not args.no_progress, time_limit=args.time_limit)
    ips = m["iterations_per_s"]
    print(f"trained {m['steps']} steps in {args.output}: final held-out loss (Eq. 3) {m['final_heldout_loss']:.6g}"
          + (f", {ips:.2f} it/s, {m['lumitexels_per_s']:.0f} lumitexels/s" if ips else ""))
    if m["stopped_on_time_limit"]:
        print(f"stopped on the time limit ({args.time_limit:g} s) at step {m['steps']} of {cfg.steps}; "
              "run the same command again to resume")
    return 0


def _pattern_image_args(s) -> None:
    """`show pattern` and `patterns show`: the same command under both names."""
    s.add_argument("file")
    s.add_argument("-o", "--output", required=True)
    s.add_argument("--rig", help="rig (default: the one the pattern file names)")
    s.add_argument("--index", type=int, help="only this frame")
    s.set_defaults(func=cmd_show_pattern)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hemicube", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    rig = sub.add_parser("rig", help="inspect, import and export rigs").add_subparsers(dest="rig_command", required=True)
    s = rig.add_parser("info", help="LED counts per board, bounding box, cameras")
    s.add_argument("rig", help="built-in rig name (paper, mini) or rig folder")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_rig_info)
    s = rig.add_parser("import-opensvbrdf", help="import the released OpenSVBRDF configuration files")
    s.add_argument("dir")
    s.add_argument("-o", "--output", required=True)
    s.add_argument("--force", action="store_true", help="replace an existing output folder")
    s.set_defaults(func=cmd_rig_import)
    s = rig.add_parser("export", help="write a rig (e.g. a built-in one) as a rig folder")
    s.add_argument("rig")
    s.add_argument("-o", "--output", required=True)
    s.add_argument("--force", action="store_true")
    s.set_defaults(func=cmd_rig_export)

    show = sub.add_parser("show", help="pictures of the rig and of patterns").add_subparsers(dest="show_command", required=True)
    s = show.add_parser("rig", help="3-D view of the rig (pyvista); PNG off-screen, a window otherwise")
    s.add_argument("--rig", default="paper")
    s.add_argument("--values", help="per-LED values: .npy (L,) or (L, 3), or a pattern file")
    s.add_argument("--index", type=int, default=0, help="frame of the pattern file given to --values")
    s.add_argument("-o", "--output", help="PNG path; without it an interactive window opens")
    s.add_argument("--size", type=int, nargs=2, default=(1200, 900), metavar=("W", "H"))
    s.set_defaults(func=cmd_show_rig)
    _pattern_image_args(show.add_parser("pattern", help="a pattern set as unfolded-cube (cross) images"))

    s = sub.add_parser("capture", help="run the capture plan (193+ HDR photos) into a session folder")
    s.add_argument("--backend", default="sim", help="device backend (sim; real hardware backends later)")
    s.add_argument("--rig", default="mini", help="built-in rig (paper, mini) or rig folder")
    s.add_argument("--sample", default="ramps", help="built-in sample (ramps, brushed_metal, satin_weave) or a "
                   "folder of OpenSVBRDF maps")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--resolution", type=int, default=128, help="texture resolution of a built-in sample")
    s.add_argument("--device", default="cpu")
    s.add_argument("--patterns", help="pattern file with the 64 learned frames (default: the shipped network's patterns for the rig, else a seeded placeholder)")
    s.add_argument("-o", "--output", required=True, help="session folder (re-run to resume)")
    s.add_argument("--no-progress", action="store_true")
    s.set_defaults(func=cmd_capture)

    s = sub.add_parser("validate", help="the main job: check the twin end to end and report")
    s.add_argument("--rig", default="mini")
    s.add_argument("--sample", default="ramps")
    s.add_argument("--device", default="cpu")
    s.add_argument("--json", action="store_true")
    s.add_argument("-o", "--output", default="hemicube-validate",
                   help="folder for the capture, the reconstruction and the report (default ./hemicube-validate)")
    s.add_argument("--resolution", type=int, help="texture grid texels per side (default: the pipeline's, 48)")
    s.add_argument("--seed", type=int, default=1, help="the virtual capture's seed")
    s.add_argument("--no-progress", action="store_true")
    s.set_defaults(func=cmd_validate)

    s = sub.add_parser("reconstruct", help="capture folder -> latents and OpenSVBRDF maps")
    s.add_argument("capture", help="a capture folder (hemicube capture, or the real device's)")
    s.add_argument("-o", "--output", required=True)
    s.add_argument("--resolution", type=int, help="texture grid texels per side (default 48)")
    s.add_argument("--size-mm", type=float, help="texture grid side in mm (default: detected, reference §6.1)")
    s.add_argument("--holdout-line", type=int, help="line photo left out of fine-tuning (default: the brightest)")
    s.add_argument("--network", help="'pretrained' (default) or a `hemicube train` run folder")
    s.add_argument("--device", help="cpu (default) or cuda")
    s.add_argument("--no-progress", action="store_true")
    s.set_defaults(func=cmd_reconstruct)

    s = sub.add_parser("train", help="train the acquisition network (resumable); writes learned patterns")
    s.add_argument("--rig", default="mini", help="built-in rig (paper, mini) or rig folder")
    s.add_argument("--steps", type=int)
    s.add_argument("--batch", type=int)
    s.add_argument("--lr", type=float)
    s.add_argument("--seed", type=int)
    s.add_argument("--device", help="cpu (default) or cuda")
    s.add_argument("--eval-every", type=int)
    s.add_argument("--checkpoint-every", type=int)
    s.add_argument("--pair-fraction", type=float, help="fraction of albedo-swap steps (default 0.5)")
    s.add_argument("--dropout", type=float, help="dropout on every layer but the last (default 0.3, paper §6)")
    s.add_argument("--time-limit", type=float, metavar="SECONDS",
                   help="checkpoint and stop after this many seconds (re-run to resume): chunks for lent machines")
    s.add_argument("-o", "--output", required=True, help="run folder (re-run to resume)")
    s.add_argument("--no-progress", action="store_true")
    s.set_defaults(func=cmd_train)

    pats = sub.add_parser("patterns", help="pattern files").add_subparsers(dest="patterns_command", required=True)
    _pattern_image_args(pats.add_parser("show", help="a pattern set as unfolded-cube (cross) images"))

    bench = sub.add_parser("bench", help="benchmarks; print JSON").add_subparsers(dest="bench_command", required=True)
    s = bench.add_parser("lumitexel", help="LED-BRDF evaluations per second vs a plain torch baseline")
    s.add_argument("--rig", default="paper")
    s.add_argument("--device", default="cpu")
    s.add_argument("--leds", type=int, help="use the first N LEDs of the rig")
    s.add_argument("--points", type=int, default=4096)
    s.add_argument("--patterns", type=int, default=64)
    s.add_argument("--repeats", type=int, default=5)
    s.add_argument("--no-compile", action="store_true", help="skip the torch.compile baseline")
    s.set_defaults(func=cmd_bench)
    s = bench.add_parser("capture", help="seconds for the full capture plan's simulation, by stage")
    s.add_argument("--rig", default="paper")
    s.add_argument("--device", default="cpu")
    s.add_argument("--sample", default="ramps")
    s.add_argument("--resolution", type=int, default=1024)
    s.add_argument("--hdr-photos", type=int, default=4, help="photos whose HDR merge is timed")
    s.set_defaults(func=cmd_bench)
    s = bench.add_parser("reconstruct", help="seconds of decode, fine-tuning and fitting, extrapolated to 1024^2")
    s.add_argument("--rig", default="paper")
    s.add_argument("--device", default="cpu")
    s.add_argument("--texels", type=int, default=16384)
    s.add_argument("--network", help="a `hemicube train` run folder (default: shipped, else untrained)")
    s.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .patterns import PatternError
    from .rig import RigError

    try:
        return args.func(args)
    except (RigError, PatternError, ValueError, FileExistsError, FileNotFoundError, KeyError) as e:
        print(f"hemicube: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
