"""`hemicube design evaluate DESIGN...`: score capture designs side by side (docs/designer.md).

Each design (twin.design.design_file) is scored on figures a designer trusts; every figure says how it was
computed (the `how` table written beside the results):

reconstruction quality  the test Eq. 3 loss (paper §6: sum over LEDs of the squared log lumitexel error, mean
                        over texels) of the acquisition network trained with the design's patterns (learned, or
                        fixed and only the decoder trained) on the design's training distribution for its step
                        budget, once per training seed; mean and sample standard deviation over the seeds. The
                        test set: TEST_TEXELS texels of the design's test distribution (for "suite", material
                        compositions held back from training), drawn from a fixed seed, so designs with the same
                        test distribution are scored on the same texels. Designs compared in one table should
                        share the budget and the test distribution (the table warns otherwise).
noise                   per pattern and reference texel (the held-out texels of seed 0, primary camera), the
                        measurement B(W+) - B(W-) and its standard deviation under the sensor's shot and read
                        noise at the exposures the capture plan would choose (twin.design.noise); median and
                        10th-percentile SNR; the multiplexing gain against assembling the same measurement
                        from one-LED-at-a-time photos; patterns whose shortest exposure saturates.
acquisition             the design's pattern photos (2K per camera, both cameras together) at those
                        exposures plus a per-frame overhead, and the upload of the 2K frames to the LED
                        controller at the design's link rate (twin.design.costs; the protocol's exact bytes).
                        The fixed part of the plan (64 lines, uniform, bottom) is the same for every design on a
                        rig and is not counted.
LED duty                peak drive and exposure-weighted mean drive per LED over the pattern photos.
verdict                 for every pair of designs, "real" or "not resolved" with every reason
                        (twin.design.verdict): Welch's t-test on the seeds' test losses, and the bar every network
                        must pass first (2x below the measurement-blind predictor, a flat held-out curve).

Outputs in OUT: designs.csv, designs.json (every figure, the how table, the per-seed losses and held-out curves,
the verdicts), heldout.png
(loss with the seeds' spread), snr.png (SNR distributions), and per design its pattern crosses
(<name>/patterns.png) and training runs (<name>/seed<S>/).
"""
from __future__ import annotations

import csv
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from twin.outputs import Kind, claim_output

from reconstruction.network.run_folder import RUN_FOLDER

HOW = {
    "heldout_eq3": "Eq. 3 loss on the test distribution's fixed texels of the network trained for the design's "
                   "steps on its training distribution; mean over seeds",
    "heldout_eq3_std": "sample standard deviation of that loss over the training seeds",
    "blind_eq3": "Eq. 3 of the best measurement-blind predictor on the same texels (the per-LED mean of "
                 "log(1 + m)): a network at this value ignores its measurements",
    "blind_ratio_min": "blind_eq3 / the worst seed's test loss: how many times better than ignoring the measurements "
                       "the weakest network is (a verdict needs >= 2)",
    "tail_change_max": "the largest relative change of a seed's held-out loss over the last 20 % of its steps (the "
                       "training run's own held-out set, CURVE_POINTS evaluations; a verdict needs < 1 %)",
    "snr_median": "median over patterns and reference texels of |B(W+) - B(W-)| / sigma, plan exposures",
    "snr_p10": "10th percentile of the same",
    "mux_gain_median": "median of sigma(one-LED-at-a-time sum) / sigma(multiplexed pair), same texels, each "
                       "photo at its plan exposure (so the OLAT side takes olat_capture_s)",
    "olat_capture_s": "one photo per lit LED, bracketed from its brightest reference texel, both cameras",
    "saturated_patterns": "patterns whose shortest planned exposure still saturates a texel",
    "acquisition_s": "pattern photos: brackets + per-frame overhead, cameras together",
    "upload_s": "the 2K frames' WRITE/COMMIT/SHOW bytes at the link rate + one latency per command",
    "capture_s": "acquisition_s + upload_s",
    "duty_peak": "largest drive (level / 255) of any LED in any frame",
    "duty_mean_max": "largest exposure-weighted mean drive of any LED over the pattern photos",
    "maps_*": "with --maps: each sample captured with the first seed's patterns (capture seed 1), reconstructed "
              "with its network on the --maps-resolution grid (default 48^2), scored against the true maps "
              "(hemicube validate's metrics); mean over the samples of the median error (alpha: of alpha_x and "
              "alpha_y) and of the fitted maps' render SSIM against the held-out line photo",
    "maps_goals_missed": "with --maps: hemicube validate's goals (thresholds) missed, over all the samples",
}
# the output folders, resumed (twin.outputs): evaluate's holds its table, or a design's figures or training runs;
# optimise's its training run
EVALUATE_FOLDER = Kind("a design evaluate folder", ("designs.json", "*/figures.json",
                                                    *(f"*/seed*/{m}" for m in RUN_FOLDER.markers)))
OPTIMISE_FOLDER = Kind("a design optimise folder", tuple(f"run/{m}" for m in RUN_FOLDER.markers))
REFERENCE_TEXELS = 256
TEST_TEXELS = 2048
TEST_SEED = 20231101  # the test texels' seed: the same texels for every design of a comparison
# held-out evaluations a training run makes: every tenth of its steps, so that one falls at 80 % of them, where the
# verdict's flatness over the last 20 % starts (twin.design.verdict)
CURVE_POINTS = 10


def train_config(design, out: Path, seed: int, device: str = "cpu", steps: int | None = None):
    """The TrainConfig that trains `design`'s network with training seed `seed`: the design's rig (written to
    out/rig, camera moves included), its LEDs left off, its fixed patterns (out/fixed_patterns.npz) or K learned
    ones, its training distribution and budget (`steps` overrides it)."""
    from reconstruction.network.data import SamplingConfig
    from reconstruction.network.train import TrainConfig
    from twin.capture.pattern_sets import signed_pairs
    from twin.capture.patterns import save_patterns
    from twin.rig.format import save_rig

    rig = design.rig
    rig_dir = out / "rig"
    if not rig_dir.is_dir():
        save_rig(rig, rig_dir)
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    pfile = ""
    fixed = design.signed_patterns()
    if fixed is not None:
        w = np.repeat(fixed[..., None], 3, axis=2)
        pfile = str(save_patterns(signed_pairs(w, [f"{design.family}_{k:02d}" for k in range(design.count)],
                                               rig.name, note=f"design {design.name}"), out / "fixed_patterns.npz"))
    tr = design.training
    steps = tr.steps if steps is None else int(steps)
    return TrainConfig(rig=str(rig_dir), steps=steps, batch=tr.batch, seed=seed, device=device,
                       dropout=tr.dropout, patterns_per_view=design.count, patterns_file=pfile,
                       leds_off=tuple(int(i) for i in np.flatnonzero(~design.led_on[upper])),
                       sampling=SamplingConfig(materials=tr.materials(tr.distribution)),
                       eval_every=max(1, steps // CURVE_POINTS), checkpoint_every=max(1, steps))


def _train_runs(design, out: Path, device: str, progress: bool) -> tuple[list[float], list, float, object]:
    """Train one network per seed (resumable: a finished run is read back), score each on the test texels; each
    run's held-out curve ([step, Eq. 3] at CURVE_POINTS evaluations); the measurement-blind predictor's loss on the
    test texels; the first seed's model."""
    from reconstruction.network.data import SamplingConfig, heldout_set
    from reconstruction.network.train import blind_loss, heldout_losses, load_run_model, read_metrics, train

    tr = design.training
    test = heldout_set(design.rig, SamplingConfig(materials=tr.materials(tr.test_distribution, test=True)),
                       TEST_TEXELS, TEST_SEED, device)
    losses, curves, first = [], [], None
    for seed in tr.seeds:
        run = out / f"seed{seed}"
        train(train_config(design, out, seed, device), run, progress=False)  # resumes a finished run at once
        model = load_run_model(run, device)
        losses.append(float(heldout_losses(model, test).mean()))
        curves.append([[r["step"], r["heldout_loss"]] for r in read_metrics(run / "metrics.jsonl")])
        if progress:
            print(f"design {design.name}: seed {seed}: test Eq. 3 {losses[-1]:.4g}", file=sys.stderr)
        if first is None:
            first = model
    return losses, curves, blind_loss(test["target"]), first


def _train_one(config, run: Path) -> dict:
    """One training run (a worker process of `evaluate`'s --jobs); which process and device trained it."""
    import os

    from reconstruction.network.train import train

    train(config, run, progress=False)
    return {"process": os.getpid(), "device": config.device,
            "visible_gpus": os.environ.get("CUDA_VISIBLE_DEVICES", "")}


def _take_gpu(slots) -> None:
    """A --jobs worker's start: it takes the next GPU ordinal from `slots` and sees only that GPU, so that each
    worker trains on its own GPU (round robin where there are more workers than GPUs)."""
    import os

    os.environ["CUDA_VISIBLE_DEVICES"] = str(slots.get())


def _train_parallel(designs, out: Path, device: str, jobs: int, progress: bool) -> dict:
    """Train every (design, seed) run in `jobs` processes (spawned: each starts its own Warp and torch), so that
    the scoring after finds them finished. With a CUDA device each worker gets a GPU of its own (`_take_gpu`), the
    GPUs taken in turn. The rig folders and fixed pattern files are written here first. Returns, per run ("design
    seed S"), the process and device that trained it."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    ctx = multiprocessing.get_context("spawn")
    init, initargs = None, ()
    if device.startswith("cuda"):
        import torch

        gpus = max(1, torch.cuda.device_count()) if device == "cuda" else 1
        ordinals = [k % gpus for k in range(jobs)] if device == "cuda" else [int(device.split(":")[1])] * jobs
        slots = ctx.Queue()
        for k in ordinals:
            slots.put(k)
        init, initargs, device = _take_gpu, (slots,), "cuda"  # each worker's only GPU is its cuda:0
    tasks = [(train_config(d, out / d.name, s, device), out / d.name / f"seed{s}", f"{d.name} seed {s}")
             for d in designs for s in d.training.seeds]
    done = {}
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=init, initargs=initargs) as pool:
        running = {pool.submit(_train_one, cfg, run): what for cfg, run, what in tasks}
        for f in as_completed(running):
            done[running[f]] = f.result()  # a failed run fails the comparison
            if progress:
                print(f"trained {running[f]} (process {done[running[f]]['process']})", file=sys.stderr)
    return dict(sorted(done.items()))


def override_rig(rig):
    """The rig that `--rig NAME|DIR` puts in place of every design file's `rig` (None: each file's own), loaded once
    before any work; a rig that cannot be loaded is one line naming the option (a ValueError: exit 2)."""
    if rig is None:
        return None
    import twin

    try:
        return twin.load_rig(rig)
    except (ValueError, OSError) as e:  # twin.rig.model.RigError is a ValueError
        raise ValueError(f"--rig: {e}") from None


def optimise(path: str, output, device: str = "cpu", steps: int | None = None, seed: int | None = None,
             progress: bool = True, rig=None) -> int:
    """Train a design's patterns and network on its training distribution (`hemicube design optimise`): a
    resumable `hemicube train` run in OUTPUT/run whose patterns.npz goes to `hemicube capture --patterns` and
    whose folder to `hemicube reconstruct --network`. `rig` (a built-in rig's name or a rig folder) overrides the
    design file's."""
    from reconstruction.network.train import train
    from twin.design.design_file import load_design

    rig = override_rig(rig)
    design = load_design(path, rig)
    out = Path(output)
    claim_output(out, OPTIMISE_FOLDER, [("the design file", path)])
    cfg = train_config(design, out, design.training.seeds[0] if seed is None else int(seed), device, steps)
    m = train(cfg, out / "run", progress=progress)
    print(f"design {design.name}: {m['steps']} steps on {design.training.distribution!r}, held-out Eq. 3 "
          f"{m['final_heldout_loss']:.4g}; patterns for `hemicube capture --patterns`: {out / 'run' / 'patterns.npz'}; "
          f"network for `hemicube reconstruct --network`: {out / 'run'}")
    return 0


MAP_METRICS = {"maps_alpha_pct": ("maps.alpha_x_pct.median", "maps.alpha_y_pct.median"),
               "maps_rho_d_pct": ("maps.rho_d_pct.median",), "maps_rho_s_pct": ("maps.rho_s_pct.median",),
               "maps_normal_deg": ("maps.normal_deg.median",), "maps_render_ssim": ("render.maps.ssim",)}


def _map_errors(design, run: Path, patterns, samples, out: Path, device: str, progress: bool,
                resolution: int | None = None) -> dict:
    """Median map errors through the twin: each sample captured with the design's patterns (capture seed 1) and
    reconstructed with its network on a `resolution`^2 grid (None: the pipeline's; `hemicube validate`'s end to
    end, whose thresholds at that grid count the goals missed); the mean over the samples of each
    median (alpha: of alpha_x's and alpha_y's), the validation goals missed in all, and the per-sample
    metrics."""
    from hemicube.validate import end_to_end
    from reconstruction.evaluation.metrics import flatten_metrics

    per = {}
    for i, name in enumerate(samples):  # a folder of its own per sample, named after it (a sample folder by its name)
        where = out / "maps" / f"{i:02d}_{Path(name).name.replace('@', '_seed')}"
        metrics, rows, _ = end_to_end(design.rig, name, device, where, resolution, 1, False, network=str(run),
                                      learned=patterns)
        flat = flatten_metrics(metrics)
        per[name] = {k: float(np.mean([flat[m] for m in ms])) for k, ms in MAP_METRICS.items()}
        per[name]["goals_missed"] = [r["metric"] for r in rows if not r["passed"]]
        if progress:
            print(f"design {design.name}: {name}: " + ", ".join(f"{k} {per[name][k]:.3g}" for k in MAP_METRICS)
                  + f"; goals missed: {per[name]['goals_missed'] or 'none'}", file=sys.stderr)
    return ({k: float(np.mean([p[k] for p in per.values()])) for k in MAP_METRICS}
            | {"maps_goals_missed": sum(len(p["goals_missed"]) for p in per.values()), "maps_per_sample": per})


def evaluate_design(design, out: Path, device: str = "cpu", progress: bool = True, maps=(),
                    maps_resolution: int | None = None) -> dict:
    """Every figure of one design (module docstring), its outputs written under `out`; with `maps` (sample
    names) also the map errors through the twin, on a `maps_resolution`^2 texture grid (None: the pipeline's)."""
    import torch

    from reconstruction.network.data import LUMITEXEL_SCALE, SamplingConfig, heldout_set
    from reconstruction.network.train import export_patterns
    from twin.capture.pattern_sets import signed_weights
    from twin.capture.plan import photo_exposures
    from twin.design.costs import led_duty, photo_seconds, upload_cost
    from twin.design.noise import measurement_noise, olat_functional_gain
    from twin.design.verdict import tail_change_max
    from twin.view.cross_plot import save_pattern_image

    out.mkdir(parents=True, exist_ok=True)
    rig = design.rig
    losses, curves, blind, model = _train_runs(design, out, device, progress)
    patterns = export_patterns(model, rig, note=f"design {design.name}")  # 2K frames (+, -), all rig LEDs
    save_pattern_image(patterns, rig, out / "patterns.png")
    signed = signed_weights(patterns)  # (K, L)

    # reference texels: the first of the test texels (the materials the design is for), physical radiance per LED;
    # synthesised on the training device (a GPU machine may lack Warp's CPU compiler), scored on the CPU
    tr = design.training
    held = heldout_set(rig, SamplingConfig(materials=tr.materials(tr.test_distribution, test=True)), REFERENCE_TEXELS,
                       TEST_SEED, device)
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    lit = np.flatnonzero((signed != 0).any(axis=0))
    exposures, olat, snr, gain, saturated = [], [], [], [], np.zeros(design.count, bool)
    for v, cam in enumerate(rig.cameras):
        m = np.zeros((REFERENCE_TEXELS, rig.num_leds))
        m[:, upper] = held["views"][:, v].to("cpu", torch.float64).numpy() / LUMITEXEL_SCALE
        sensor = rig.camera(cam).sensor
        noise = measurement_noise(rig, signed, m, sensor)
        exposures.append(noise["exposures_s"])                      # (K, 2, raw frames: bracket x frames)
        saturated |= noise["saturated"]
        # the one-LED-at-a-time capture the gain compares with: a photo per lit LED, bracketed as the plan does
        olat.append([photo_exposures(float(m[:, i].max()), sensor) for i in lit])
        if v == 0:
            snr = np.abs(noise["snr"])
            gain = olat_functional_gain(rig, signed, m, sensor)
    photos = np.stack(exposures, axis=2)                            # (K, 2 frames, cameras, raw frames)
    photos = photos.reshape(-1, *photos.shape[2:])                  # (2K, cameras, raw frames), plan order
    olat_s = float(photo_seconds(np.stack(olat, axis=1), design.capture.frame_overhead_s).sum())
    per_photo = photo_seconds(photos, design.capture.frame_overhead_s)
    acq = float(per_photo.sum())
    up = upload_cost(patterns.levels, design.capture.baud, design.capture.latency_s)
    duty = led_duty(patterns.levels, per_photo)
    finite = np.isfinite(snr)
    row = {
        "design": design.name, "rig": rig.name, "family": design.family, "patterns": design.count,
        "leds_on": int(design.led_on.sum()), "train_on": design.training.distribution,
        "test_on": design.training.test_distribution, "steps": design.training.steps, "seeds": len(losses),
        "heldout_eq3": float(np.mean(losses)),
        "heldout_eq3_std": float(np.std(losses, ddof=1)) if len(losses) > 1 else float("nan"),
        "blind_eq3": blind, "blind_ratio_min": float(blind / max(losses)),
        "tail_change_max": _nan_if_none(tail_change_max(curves)),
        "snr_median": float(np.median(snr[finite])) if finite.any() else float("nan"),
        "snr_p10": float(np.percentile(snr[finite], 10)) if finite.any() else float("nan"),
        "mux_gain_median": float(np.nanmedian(gain)), "olat_capture_s": olat_s,
        "saturated_patterns": int(saturated.sum()),
        "acquisition_s": acq, "upload_s": up.seconds, "capture_s": acq + up.seconds,
        "within_budget": bool(acq + up.seconds <= design.capture.budget_s),
        "duty_peak": float(duty["peak"].max()), "duty_mean_max": float(duty["mean"].max()),
    }
    if maps:
        row |= _map_errors(design, out / f"seed{design.training.seeds[0]}", patterns, maps, out, device, progress,
                           maps_resolution)
    per_seed = {"heldout_eq3_per_seed": losses, "heldout_curve_per_seed": curves}
    (out / "figures.json").write_text(json.dumps({**row, **per_seed}, indent=1))
    return {**row, **per_seed, "_snr": snr[finite]}


def _nan_if_none(v) -> float:
    """A figure the table prints: NaN where there is none (JSON's null)."""
    return float("nan") if v is None else float(v)


def _plots(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["design"] for r in rows]
    fig, ax = plt.subplots(figsize=(1.6 + 1.2 * len(rows), 3.2))
    ax.bar(names, [r["heldout_eq3"] for r in rows], yerr=[np.nan_to_num(r["heldout_eq3_std"]) for r in rows],
           capsize=4, color="#4c72b0")
    for i, r in enumerate(rows):
        ax.plot([i] * len(r["heldout_eq3_per_seed"]), r["heldout_eq3_per_seed"], "k.", ms=4)
        ax.plot([i - 0.4, i + 0.4], [r["blind_eq3"]] * 2, "r--", lw=1, label="blind predictor" if i == 0 else None)
    ax.legend(fontsize=7)
    ax.set_ylabel("test Eq. 3 loss")
    ax.set_title("reconstruction quality (bars: mean, dots: seeds)")
    fig.tight_layout()
    fig.savefig(out / "heldout.png", dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for r in rows:
        s = r["_snr"]
        if s.size:
            ax.hist(np.log10(np.maximum(s, 1e-3)), bins=40, histtype="step", label=r["design"])
    ax.set_xlabel("log10 SNR of a measurement (plan exposures)")
    ax.set_ylabel("patterns x texels")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "snr.png", dpi=120)
    plt.close(fig)


COLUMNS = ("design", "rig", "family", "patterns", "leds_on", "train_on", "test_on", "steps", "seeds", "heldout_eq3",
           "heldout_eq3_std", "blind_eq3", "blind_ratio_min", "tail_change_max",
           "snr_median", "snr_p10", "mux_gain_median", "olat_capture_s", "saturated_patterns", "acquisition_s", "upload_s",
           "capture_s", "within_budget", "duty_peak", "duty_mean_max")


def _command(paths, output, device, maps, jobs, maps_resolution, rig) -> str:
    """The command line that runs this evaluation (a study's record names it, whichever way it was started)."""
    args = ["hemicube", "design", "evaluate", *map(str, paths), "-o", str(output)]
    args += ["--device", str(device)] if str(device) != "cpu" else []
    args += ["--maps", *map(str, maps)] if maps else []
    args += ["--maps-resolution", str(maps_resolution)] if maps_resolution is not None else []
    args += ["--jobs", str(jobs)] if jobs != 1 else []
    args += ["--rig", str(rig)] if rig is not None else []
    return shlex.join(args)


def _study_path(study) -> Path | None:
    """`--study`'s file, checked before any work: a .json name, and no file there but an earlier record of a study
    (which a study run again replaces)."""
    if study is None:
        return None
    from twin.design.study import is_study

    p = Path(study)
    if p.suffix != ".json":
        raise ValueError(f"--study: {p} must name a .json file")
    if p.exists() and not is_study(p):
        raise ValueError(f"--study: {p} exists and is not a study record; choose another name")
    if not p.parent.is_dir():
        raise ValueError(f"--study: folder {p.parent} does not exist")
    return p


def evaluate(paths: list[str], output, device: str = "cpu", as_json: bool = False, progress: bool = True,
             maps=(), jobs: int = 1, maps_resolution: int | None = None, rig=None, study=None) -> int:
    """Load every design (all checked before any work), score each, write the table and plots, print it. With
    jobs > 1 the training runs go first, `jobs` at a time in separate processes. `maps` are scored on a
    `maps_resolution`^2 texture grid (None: the pipeline's). `rig` (a built-in rig's name or a rig folder) overrides
    every design file's `rig`; each file's layout changes and camera moves apply on top of it, its name is kept,
    and the table's `rig` column says which rig each design was scored on. `study`: also write the study's record
    there (twin.design.study: designs.json's numbers with the command, commit, versions, device and time; an
    earlier record there is replaced)."""
    from twin.atomic import write_bytes_atomic
    from twin.design.design_file import load_design
    from twin.design.study import study_record
    from twin.design.verdict import compare_all
    from twin.materials.samples import load_sample

    t0 = time.perf_counter()
    study_path = _study_path(study)
    command = _command(paths, output, device, maps, jobs, maps_resolution, rig)
    rig = override_rig(rig)
    designs = [load_design(p, rig) for p in paths]
    for name in maps:
        load_sample(name, 16)  # a bad sample name fails before any training
    names = [d.name for d in designs]
    if len(set(names)) != len(names):
        raise ValueError(f"design names must be distinct in one comparison, got {names}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    if maps_resolution is not None and (isinstance(maps_resolution, bool) or not isinstance(maps_resolution, int)
                                        or maps_resolution < 4):
        raise ValueError(f"maps resolution must be an integer >= 4 texels per side, got {maps_resolution!r}")
    out = Path(output)
    claim_output(out, EVALUATE_FOLDER, [("the design file", p) for p in paths] + [("the maps of sample " + str(m), m)
                                                                                 for m in maps])
    trained_by = _train_parallel(designs, out, device, jobs, progress) if jobs > 1 else {}
    rows = [evaluate_design(d, out / d.name, device, progress, maps, maps_resolution) for d in designs]
    for key, what in (("steps", "step budgets"), ("test_on", "test distributions")):
        seen = sorted({str(r[key]) for r in rows})
        if len(seen) > 1:
            print(f"warning: the designs differ in {what} {seen}: their test losses are not comparable",
                  file=sys.stderr)
    _plots(rows, out)
    columns = COLUMNS + (tuple(MAP_METRICS) + ("maps_goals_missed",) if maps else ())
    table = [{k: r[k] for k in columns} for r in rows]
    extra = ("heldout_eq3_per_seed", "heldout_curve_per_seed") + (("maps_per_sample",) if maps else ())
    verdicts = compare_all(rows)
    result = {"designs": [{**t, **{k: r[k] for k in extra}} for t, r in zip(table, rows)], "verdicts": verdicts,
              "how": HOW, **({"trained_by": trained_by} if trained_by else {})}
    write_bytes_atomic(out / "designs.json", json.dumps(result, indent=1).encode())
    if study_path is not None:
        from reconstruction.bench.common import device_name, software

        record = study_record(result, name=study_path.stem, command=command, software=software(),
                              device=device_name(device), seconds=time.perf_counter() - t0)
        write_bytes_atomic(study_path, json.dumps(record, indent=1).encode())
    with open(out / "designs.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns)
        w.writeheader()
        w.writerows(table)
    if as_json:
        print(json.dumps({"designs": table, "verdicts": verdicts, "how": HOW}, indent=1))
    else:
        fmt = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
        widths = [max(len(c), *(len(fmt(t[c])) for t in table)) for c in columns]
        print("  ".join(c.ljust(w) for c, w in zip(columns, widths)))
        for t in table:
            print("  ".join(fmt(t[c]).ljust(w) for c, w in zip(columns, widths)))
        if verdicts:
            print("\nverdicts (real: p < 0.05 over >= 3 seeds, every network 2x below the blind predictor and "
                  "its held-out curve flat; twin/design/verdict.py):")
            for v in verdicts:
                print(f"  {v['text']}")
        print(f"\nhow each figure was computed: {out / 'designs.json'} ('how'); plots: {out}/heldout.png, snr.png")
    return 0


# the sub-commands this package adds and their one-line help: what `hemicube --help` lists without importing
# the package's heavy modules (hemicube.cli.build_parser)
COMMANDS = {
    "design": "capture designs: score and compare lighting patterns and layouts",
}


def register(sub) -> None:
    d = sub.add_parser("design", help=COMMANDS["design"])
    ds = d.add_subparsers(dest="design_command", required=True)
    e = ds.add_parser("evaluate", help="score designs side by side: held-out loss over training seeds, "
                      "measurement SNR and multiplexing gain, acquisition and upload time, LED duty")
    e.add_argument("designs", nargs="+", metavar="DESIGN", help="design files (TOML; twin.design.design_file)")
    e.add_argument("-o", "--output", default="hemicube-design", help="output folder (re-run to resume; any other "
                   "existing path is refused) (default: %(default)s)")
    e.add_argument("--device", default="cpu", help="torch device for training (default: %(default)s)")
    e.add_argument("--json", action="store_true", help="print the table as JSON")
    e.add_argument("--no-progress", action="store_true", help="no progress lines on stderr")
    e.add_argument("--maps", nargs="+", default=(), metavar="SAMPLE", help="also capture and reconstruct these "
                   "samples through the twin with each design's patterns and network and report the map errors "
                   "(e.g. the material suite's held-back compositions: wood@9101 paper@9101; minutes each on a CPU; default: none)")
    e.add_argument("--maps-resolution", type=int, default=None, metavar="N", help="texture grid of the --maps "
                   "reconstructions, N^2 texels (default: the pipeline's, 48; a coarser grid scores sooner, against "
                   "that grid's thresholds)")
    e.add_argument("--jobs", type=int, default=1, help="training runs at a time, each in its own process (the "
                   "Warp CPU kernels and a small network's steps use one core each; on a GPU they overlap; "
                   "default: %(default)s)")
    e.add_argument("--rig", default=None, metavar="NAME|DIR", help="score every design on this rig instead of the "
                   "one its file names: a built-in rig (paper, mini) or a rig folder; each file's layout changes "
                   "and camera moves still apply, and its name is kept (default: each file's rig)")
    e.add_argument("--study", default=None, metavar="FILE.json", help="also write the study's record to FILE.json "
                   "(e.g. docs/designs/NAME.json): the table, per-seed losses and curves with the command, commit, "
                   "versions, device and time; an earlier record there is replaced (default: none)")
    e.set_defaults(func=lambda a: evaluate(a.designs, a.output, a.device, a.json, not a.no_progress, a.maps,
                                           a.jobs, a.maps_resolution, a.rig, a.study))
    o = ds.add_parser("optimise", help="train a design's patterns and network on its training distribution "
                      "(uniform GGX, the material suite, or folders of maps): patterns to capture with, a network "
                      "to reconstruct with")
    o.add_argument("design", help="a design file (TOML)")
    o.add_argument("-o", "--output", required=True, help="output folder (re-run to resume; any other existing "
                   "path is refused)")
    o.add_argument("--steps", type=int, help="training steps (default: the design's)")
    o.add_argument("--seed", type=int, help="training seed (default: taken from the design, the first of its "
                   "[training] seeds, 0 where the file lists none: the seed its figures were trained with, not the "
                   "other commands' default)")
    o.add_argument("--device", default="cpu", help="torch device (default: %(default)s)")
    o.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    o.add_argument("--rig", default=None, metavar="NAME|DIR", help="train on this rig instead of the one the file "
                   "names: a built-in rig (paper, mini) or a rig folder (default: the file's rig)")
    o.set_defaults(func=lambda a: optimise(a.design, a.output, a.device, a.steps, a.seed, not a.no_progress,
                                           a.rig))
