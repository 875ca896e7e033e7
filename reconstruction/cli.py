"""The reconstruction's sub-commands of `hemicube` (registered by the front, hemicube.cli): reconstruct,
reconstruct-many, train, network, and the reconstruction's benchmarks (bench reconstruct and the others
register_bench adds). Options and printing only: the work is in the modules each command calls."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path


def _ratio(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise SystemExit(f"hemicube reconstruct: --spill-ratio takes a number > 1 or 'none', got {text!r}") from None


def cmd_reconstruct(args) -> int:
    from reconstruction.pipeline import ReconstructConfig, reconstruct

    over = {k: v for k, v in (("resolution", args.resolution), ("size_mm", args.size_mm),
                              ("holdout_line", args.holdout_line), ("network", args.network),
                              ("device", args.device), ("footprint", args.footprint),
                              ("finetune_photos", args.finetune_photos)) if v is not None}
    config = replace(ReconstructConfig(), **over)
    if args.spill_ratio is not None:
        config = replace(config, spill_ratio=None if args.spill_ratio.lower() == "none" else _ratio(args.spill_ratio))
    if args.finetune_precision is not None:
        config = replace(config, finetune=replace(config.finetune, precision=args.finetune_precision))
    config = replace(config, accept_alignment=args.accept_alignment)
    r = reconstruct(args.capture, args.output, config, progress=not args.no_progress, break_lock=args.break_lock)
    print(f"reconstruction: {r.directory} ({r.grid.resolution}^2 texels over {r.grid.size_mm:.1f} mm; "
          + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in r.timings.items()) + ")")
    return 0


def cmd_compare(args) -> int:
    """`hemicube compare TRUTH RECON`: the novel views' scoring (reconstruction.evaluation.novel_views) of any two
    map folders, the truth's radiance box-filtered onto the second's grid; exit 1 when a goal is missed."""
    import json

    import twin
    from twin.materials.samples import read_maps
    from twin.optics.inputs import check_device

    from reconstruction.evaluation.metrics import check, format_table, to_jsonable, truth_coverage
    from reconstruction.evaluation.novel_views import novel_view_scores, summary_line, validation_set
    from reconstruction.evaluation.validation import NOVEL_GOALS

    device = check_device(args.device)
    rig = twin.load_rig(args.rig)
    truth, recon = read_maps(args.truth), read_maps(args.recon)
    if recon.shape[0] != recon.shape[1]:
        raise ValueError(f"{args.recon}: the maps to score must be square, got {recon.shape[0]} x {recon.shape[1]}")
    scores = novel_view_scores(validation_set(rig), truth, recon, device=device,
                               mask=truth_coverage(truth, recon.size_mm, recon.shape[0]))
    rows = check({"novel": scores}, NOVEL_GOALS)
    ok = all(r["passed"] for r in rows)
    if args.json:
        print(json.dumps(to_jsonable({"rig": rig.name, "truth": args.truth, "recon": args.recon, "passed": ok,
                                      "thresholds": rows, "novel": scores}), indent=2))
    else:
        print(f"hemicube compare: {args.recon} against {args.truth} on rig {rig.name!r} ({recon.shape[0]}^2 texels "
              f"over {recon.size_mm:g} mm)")
        print(format_table(rows))
        print("  " + summary_line(scores))
        print("result:", "all goals met" if ok else "FAILED")
    return 0 if ok else 1


def cmd_train(args) -> int:
    from reconstruction.network.train import TrainConfig, train

    cfg = TrainConfig(rig=args.rig)
    over = {k: v for k, v in (("steps", args.steps), ("batch", args.batch), ("lr", args.lr), ("seed", args.seed),
                              ("device", args.device), ("eval_every", args.eval_every),
                              ("checkpoint_every", args.checkpoint_every),
                              ("pair_fraction", args.pair_fraction), ("dropout", args.dropout),
                              ("measurement_noise", args.measurement_noise),
                              ("architecture", args.architecture), ("patterns_per_view", args.patterns_per_view),
                              ("peak_term", args.peak_term))
            if v is not None}
    if args.materials is not None:
        over["sampling"] = replace(cfg.sampling, materials=args.materials)
    cfg = replace(cfg, **over)
    try:
        m = train(cfg, args.output, progress=not args.no_progress, time_limit=args.time_limit)
    finally:
        import torch.distributed as dist

        if dist.is_initialized():  # under torchrun (reconstruction.network.distributed)
            dist.destroy_process_group()
    if not m:  # a rank other than 0: rank 0 reports
        return 0
    ips = m["iterations_per_s"]
    print(f"trained {m['steps']} steps in {args.output}: final held-out loss (Eq. 3) {m['final_heldout_loss']:.6g}"
          + (f", {ips:.2f} it/s, {m['lumitexels_per_s']:.0f} lumitexels/s" if ips else ""))
    if m["stopped_on_time_limit"]:
        print(f"stopped on the time limit ({args.time_limit:g} s) at step {m['steps']} of {cfg.steps}; "
              "run the same command again to resume")
    return 0


def cmd_network(args) -> int:
    """`hemicube network score RUN`: score_network's figures of a run's network (JSON); `hemicube network ship
    RUN`: make the shipped files from it (reconstruction.network.shipped)."""
    import torch

    import twin

    from reconstruction.network.shipped import score_network, ship_network
    from reconstruction.network.train import CHECKPOINT_JSON, TrainConfig, load_run_model

    if args.network_command == "ship":
        info = ship_network(args.run, args.output, args.device, args.commit)
        print(json.dumps({k: info[k] for k in ("rig", "architecture", "num_parameters", "heldout_loss", "scores")},
                         indent=2))
        return 0
    model = load_run_model(args.run, args.device)  # first: a folder that is no run says so
    config = TrainConfig.from_json(json.loads((Path(args.run) / CHECKPOINT_JSON).read_text())["config"])
    print(json.dumps(score_network(model, twin.load_rig(config.rig), config, torch.device(args.device)), indent=2))
    return 0


def cmd_reconstruct_many(args) -> int:
    from twin.batch import RECORD_FILE, options_from, report

    from reconstruction.many import reconstruct_many, table
    from reconstruction.pipeline import ReconstructConfig

    over = {k: v for k, v in (("resolution", args.resolution), ("size_mm", args.size_mm), ("network", args.network),
                              ("device", args.device)) if v is not None}
    config = replace(ReconstructConfig(), **over)
    outcomes = reconstruct_many(args.captures, args.output, config, options_from(args, config.device))
    return report(outcomes, table(outcomes), f"{args.output}/{RECORD_FILE}")


def cmd_bench(args) -> int:
    from reconstruction.bench.fit import bench_fit_forward, bench_fit_jacobian
    from reconstruction.bench.reconstruct import bench_reconstruct

    from twin.bench import bench_exit

    if args.bench_command == "fit-forward":
        res = bench_fit_forward(args.rig, args.device, args.texels, args.repeats)
    elif args.bench_command == "fit-jacobian":
        res = bench_fit_jacobian(args.rig, args.device, args.texels, args.repeats)
    else:
        res = bench_reconstruct(args.rig, args.device, args.texels, args.network)
    print(json.dumps(res, indent=2))
    return bench_exit(res)


def cmd_bench_pipeline(args) -> int:
    """The benches of the pipeline's limits and of whole runs (reconstruction.bench.latent, limits, e2e, scaling):
    the arguments given, over --tiny's sizes, over the function's defaults."""
    import importlib

    from twin.bench import bench_exit

    module, function, names = BENCH_PIPELINE[args.bench_command]
    mod = importlib.import_module(f"reconstruction.bench.{module}")
    kwargs = {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}
    if "rig" in kwargs:
        kwargs["rig_name"] = kwargs.pop("rig")
    for key in ("samples", "processes", "finetune_iterations"):
        if key in kwargs:
            kwargs[key] = tuple(kwargs[key])
    res = getattr(mod, function)(**({**mod.TINY, **kwargs} if args.tiny else kwargs))
    print(json.dumps(res, indent=2))
    return bench_exit(res)


# sub-command -> (module of reconstruction.bench, its function, the arguments it takes from the command line)
BENCH_PIPELINE = {
    "latent-ceiling": ("latent", "bench_latent_ceiling", ("rig", "device", "samples", "resolution", "size_mm",
                                                          "steps", "lr", "network", "finetune_iterations")),
    "fit-limits": ("limits", "bench_fit_limits", ("rig", "device", "samples", "resolution", "size_mm", "noise",
                                                  "seed", "frames", "capture", "finetune_iterations",
                                                  "fit_iterations")),
    "e2e": ("e2e", "bench_e2e", ("rig", "device", "sample", "resolution", "seed", "frames", "network", "workdir",
                                 "twice")),
    "train-scaling": ("scaling", "bench_train_scaling", ("rig", "device", "processes", "steps", "batch",
                                                         "eval_every", "dropout", "measurement_noise", "loss_rtol",
                                                         "workdir")),
}


# the sub-commands this package adds and their one-line help: what `hemicube --help` lists without importing
# the package's heavy modules (hemicube.cli.build_parser)
COMMANDS = {
    "reconstruct": "capture folder -> latents and OpenSVBRDF maps",
    "compare": "score two map folders against each other under the 560 novel views and lights (the truth's "
               "radiance box-filtered onto the second's grid)",
    "reconstruct-many": "reconstruct every capture folder under a folder, on Ray (skips finished ones, retries "
                        "failures, scores against ground truth where there is one)",
    "train": "train the acquisition network (resumable); writes learned patterns; under torchrun, data-parallel"
             " over the processes (--batch is the global batch)",
    "network": "score a trained network, or make the shipped files from it",
}


def register(sub) -> None:
    """Add the reconstruction's sub-commands to the front's parser."""
    from reconstruction.stages.extraction import FOOTPRINTS
    from reconstruction.stages.finetune import PRECISIONS
    from reconstruction.pipeline import FINETUNE_PHOTOS, ReconstructConfig
    from reconstruction.network.train import TrainConfig
    from twin.lock import BREAK_LOCK_HELP

    rc, tc = ReconstructConfig(), TrainConfig()
    s = sub.add_parser("reconstruct", help=COMMANDS["reconstruct"])
    s.add_argument("capture", help="a capture folder (hemicube capture, or the real device's)")
    s.add_argument("-o", "--output", required=True, help="reconstruction folder, replaced whole when done; any other "
                   "existing path, or one inside the capture, is refused")
    s.add_argument("--resolution", type=int, help=f"texture grid texels per side (default: {rc.resolution})")
    s.add_argument("--size-mm", type=float, help="texture grid side in mm (default: detected from the bottom-lit "
                   "photos, shrunk 6.5%% a side, reference §6.1)")
    s.add_argument("--holdout-line", type=int, help="line photo (0-63) left out of fine-tuning and fitting "
                   "(default: the brightest over the sample)")
    s.add_argument("--network", help=f"'pretrained' (the network shipped for the rig) or a `hemicube train` run "
                   f"folder (default: {rc.network})")
    s.add_argument("--device", help=f"torch/Warp device: cpu, cuda, cuda:N (default: {rc.device})")
    s.add_argument("--footprint", choices=tuple(FOOTPRINTS), help="how a texel's photo value is read: "
                   "the value at its centre, the mean over its cell's pixels (less noise where a texel spans many "
                   f"pixels), or after the reference's anti-aliasing blur (default: {rc.footprint})")
    s.add_argument("--finetune-photos", choices=FINETUNE_PHOTOS, help="the photos fine-tuning fits: the line photos "
                   "(the paper's) or also the primary view's learned-pattern photos (default: "
                   f"{rc.finetune_photos})")
    s.add_argument("--spill-ratio", help="refit the texels next to a highlight more than this many times brighter "
                   "than their own from photos demosaiced by Malvar-He-Cutler 2004, or 'none' (default: "
                   f"{rc.spill_ratio})")
    s.add_argument("--finetune-precision", choices=PRECISIONS, help="fine-tuning's matrix products on a CUDA device: "
                   "TF32 (tensor cores; within 1%% of float32's objective, measured) or float32; the CPU's are float32 "
                   f"either way (default: {rc.finetune.precision})")
    s.add_argument("--accept-alignment", action="store_true", help="go on when the alignment check flags the two "
                   "views as disagreeing (reconstruction.stages.alignment_check; the default stops with one line)")
    s.add_argument("--break-lock", action="store_true", help=BREAK_LOCK_HELP)
    s.add_argument("--no-progress", action="store_true", help="no progress output")
    s.set_defaults(func=cmd_reconstruct)

    s = sub.add_parser("compare", help=COMMANDS["compare"])
    s.add_argument("truth", help="the true maps (a map folder: OpenSVBRDF or ours)")
    s.add_argument("recon", help="the maps to score (e.g. a reconstruction's maps/), on a square grid")
    s.add_argument("--rig", default="mini", help="built-in rig (paper, mini) or rig folder whose views and lights "
                   "are used (default: %(default)s)")
    s.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:N (default: %(default)s)")
    s.add_argument("--json", action="store_true", help="print every pair's scores as JSON instead of a table")
    s.set_defaults(func=cmd_compare)

    from twin.batch import add_arguments

    s = sub.add_parser("reconstruct-many", help=COMMANDS["reconstruct-many"])
    s.add_argument("captures", help="a folder whose sub-folders are capture folders")
    s.add_argument("-o", "--output", required=True, help="folder for one reconstruction per capture and batch.json")
    s.add_argument("--resolution", type=int, help=f"texture grid texels per side (default: {rc.resolution})")
    s.add_argument("--size-mm", type=float, help="texture grid side in mm (default: detected per capture)")
    s.add_argument("--network", help=f"'pretrained' or a `hemicube train` run folder (default: {rc.network})")
    s.add_argument("--device", help=f"cpu or cuda: with cuda, one GPU per task (default: {rc.device})")
    add_arguments(s)
    s.set_defaults(func=cmd_reconstruct_many, device_here=False)  # --device: the Ray workers' (twin.batch)

    s = sub.add_parser("train", help=COMMANDS["train"])
    s.add_argument("--rig", default="mini", help="built-in rig (paper, mini) or rig folder (default: %(default)s)")
    s.add_argument("--steps", type=int, help=f"optimiser steps in all (default: {tc.steps})")
    s.add_argument("--batch", type=int, help=f"lumitexels per step (default: {tc.batch})")
    s.add_argument("--lr", type=float, help=f"Adam learning rate (default: {tc.lr:g})")
    s.add_argument("--seed", type=int, default=tc.seed, help="seed of the initial weights and the data stream "
                   "(default: %(default)s)")
    s.add_argument("--device", help=f"torch/Warp device: cpu, cuda, cuda:N (default: {tc.device})")
    s.add_argument("--eval-every", type=int, help=f"steps between held-out evaluations (default: {tc.eval_every})")
    s.add_argument("--checkpoint-every", type=int, help=f"steps between checkpoints "
                   f"(default: {tc.checkpoint_every})")
    s.add_argument("--pair-fraction", type=float, help=f"fraction of albedo-swap steps, 0-1 "
                   f"(default: {tc.pair_fraction})")
    s.add_argument("--dropout", type=float, help=f"dropout on every layer but the last, 0-1 (default: {tc.dropout}, "
                   "paper §6)")
    s.add_argument("--architecture", choices=("paper", "compact"), help=f"network: the released one scaled to the "
                   f"rig, or the compact one that ships (default: {tc.architecture})")
    s.add_argument("--peak-term", action="store_true", default=None, help="the decoder adds one lobe over the LEDs' "
                   "directions (narrow specular peaks; docs/performance.md)")
    s.add_argument("--measurement-noise", type=float, help=f"sigma of the multiplicative noise on the measurements in "
                   f"training (default: {tc.measurement_noise}, paper §6)")
    s.add_argument("--patterns-per-view", type=int, help=f"K signed patterns, captured as 2K photos (default: "
                   f"{tc.patterns_per_view}, the released network's)")
    s.add_argument("--materials", help="training materials: '' uniform GGX ranges (default), 'suite:SEEDS' the "
                   "material suite's compositions (database-like), 'maps:DIR' folders of OpenSVBRDF maps "
                   "(reconstruction.network.data.SamplingConfig.materials)")
    s.add_argument("--time-limit", type=float, metavar="SECONDS", help="checkpoint and stop after this many "
                   "seconds (re-run to resume): chunks for lent machines (default: none)")
    s.add_argument("-o", "--output", required=True, help="run folder (re-run to resume)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    s.set_defaults(func=cmd_train)


    net = sub.add_parser("network", help=COMMANDS["network"]).add_subparsers(dest="network_command", required=True)
    for name, text in (("score", "held-out figures of a `hemicube train` run's network, as JSON"),
                       ("ship", "write reconstruction/pretrained/<rig>/ (model.safetensors, model.json) from a "
                                "`hemicube train` run, float16 weight matrices, scored as shipped")):
        s = net.add_parser(name, help=text)
        s.add_argument("run", help="a `hemicube train` run folder")
        s.add_argument("--device", default="cpu", help="torch/Warp device: cpu, cuda (default: %(default)s)")
        if name == "ship":
            s.add_argument("-o", "--output", help="folder for the two files (default: the package's "
                           "reconstruction/pretrained/<rig>)")
            s.add_argument("--commit", default="", help="the commit the run was made at, for model.json (default: none)")
        s.set_defaults(func=cmd_network)


def register_bench(bench) -> None:
    """Add the reconstruction's benchmarks to the front's `bench` group."""
    s = bench.add_parser("reconstruct", help="seconds of decode, fine-tuning and fitting, extrapolated to 1024^2")
    s.add_argument("--rig", default="paper", help="built-in rig (paper, mini) or rig folder (default: %(default)s)")
    s.add_argument("--device", default="cpu", help="torch/Warp device: cpu, cuda (default: %(default)s)")
    s.add_argument("--texels", type=int, default=16384, help="synthetic texels timed (default: %(default)s)")
    s.add_argument("--network", help="a `hemicube train` run folder (default: the shipped one, else untrained)")
    s.set_defaults(func=cmd_bench)
    for name, what, repeats in (("fit-forward", "one forward-model evaluation of the GGX fit, against the autograd "
                                 "path over every LED", 5),
                                ("fit-jacobian", "one Jacobian of the GGX fit's residuals, analytic, against forward "
                                 "differences", 3)):
        s = bench.add_parser(name, help=f"seconds of {what}")
        s.add_argument("--rig", default="mini", help="built-in rig (paper, mini) or rig folder (default: %(default)s)")
        s.add_argument("--device", default="cpu", help="torch/Warp device: cpu, cuda (default: %(default)s)")
        s.add_argument("--texels", type=int, default=2304, help="texels at once (default: %(default)s, the mini "
                       "rig's 48^2 grid)")
        s.add_argument("--repeats", type=int, default=repeats, help="timed runs, the fastest reported (default: "
                       "%(default)s)")
        s.set_defaults(func=cmd_bench)
    _register_bench_pipeline(bench)


def _register_bench_pipeline(bench) -> None:
    """`bench latent-ceiling`, `bench fit-limits`, `bench e2e`, `bench train-scaling` (cmd_bench_pipeline). No
    option has a parser default: what is not given is the bench function's default, or --tiny's size."""
    from twin.capture.plan import DEFAULT_SEED

    def parser(name: str, text: str, device: str = "torch/Warp device: cpu, cuda (default: cpu)"):
        s = bench.add_parser(name, help=text)
        s.add_argument("--rig", help="built-in rig (paper, mini) or rig folder (default: paper)")
        s.add_argument("--device", help=device)
        s.add_argument("--tiny", action="store_true", help="small sizes on the mini rig that run on a CPU in seconds "
                       "(the options given win)")
        s.set_defaults(func=cmd_bench_pipeline)
        return s

    for name, text in (("latent-ceiling", "SSIM and Eq. 3 of the best latent (optimised against the exact "
                        "lumitexel) against the network's and fine-tuning's, on exact texels of samples"),
                       ("fit-limits", "the GGX fit's map errors from exact lumitexels, decoded ones, noisy photos "
                        "(and a capture through the pipeline), on exact texels of samples")):
        s = parser(name, text)
        s.add_argument("--sample", dest="samples", action="append", help="built-in sample or folder of maps, "
                       "repeatable (default: ramps)")
        s.add_argument("--resolution", type=int, help="texture grid texels per side (default: 64)")
        s.add_argument("--size-mm", type=float, help="side of the texture grid on the sample (default: 100)")
        s.add_argument("--finetune-iterations", type=int, nargs=3, metavar=("P1", "P2", "P3"),
                       help="fine-tuning's iteration caps per pass (default: `hemicube reconstruct`'s)")
        if name == "latent-ceiling":
            s.add_argument("--steps", type=int, help="Adam steps of the best-latent search (default: 2000)")
            s.add_argument("--lr", type=float, help="its learning rate (default: 0.02)")
            s.add_argument("--network", help="'pretrained' or a `hemicube train` run folder (default: pretrained)")
        else:
            s.add_argument("--noise", type=float, help="relative sigma of the photos' noise (default: 0.005, about "
                           "a four-frame photo's)")
            s.add_argument("--seed", type=int, help=f"seed of the noise (default: {DEFAULT_SEED})")
            s.add_argument("--frames", type=int, help="frames an exposure the fit weighs the photos for (default: "
                           "the capture plan's)")
            s.add_argument("--fit-iterations", type=int, help="the fit's iterations (default: its own)")
            s.add_argument("--capture", help="a capture folder of this rig and the (one) sample: also run it "
                           "through the pipeline on the same grid and score it")

    s = parser("e2e", "`hemicube capture` then `hemicube reconstruct`, each its own process: seconds, memory, "
               "bytes; both folders verified")
    s.add_argument("--sample", help="built-in sample or folder of maps (default: ramps)")
    s.add_argument("--resolution", type=int, help="the sample's maps and the texture grid, texels per side "
                   "(default: each command's own)")
    s.add_argument("--seed", type=int, help=f"the capture's seed (default: {DEFAULT_SEED})")
    s.add_argument("--frames", type=int, help="frames an exposure (default: the capture's)")
    s.add_argument("--network", help="for the reconstruction: a `hemicube train` run folder (default: the shipped)")
    s.add_argument("--workdir", help="keep the capture and reconstruction folders here (default: a temporary "
                   "folder, removed)")
    s.add_argument("--twice", action="store_true", help="capture a second time with the same seed and check the "
                   "files are byte-identical (small sizes)")

    s = parser("train-scaling", "`hemicube train` under torchrun on 1, 2, ... processes: lumitexels/s, speed-up, "
               "held-out loss against the 1-process run", "cpu (gloo) or cuda (NCCL, one GPU a process) (default: cpu)")
    s.add_argument("--processes", type=int, nargs="+", help="process counts; 1 always runs (default: 1 2)")
    s.add_argument("--steps", type=int, help="training steps of each run (default: 200)")
    s.add_argument("--batch", type=int, help="the global batch (default: 1024)")
    s.add_argument("--eval-every", type=int, help="steps between held-out evaluations (default: 50)")
    s.add_argument("--dropout", type=float, help="dropout (default: `hemicube train`'s)")
    s.add_argument("--measurement-noise", type=float, help="training's measurement noise (default: `hemicube "
                   "train`'s)")
    s.add_argument("--loss-rtol", type=float, help="the held-out loss's tolerance against the 1-process run "
                   "(default: 0.05)")
    s.add_argument("--workdir", help="keep the runs here (default: a temporary folder, removed)")
