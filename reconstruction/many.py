"""`hemicube reconstruct-many CAPTURES_DIR -o OUT` (docs/scale-out.md): every capture folder under CAPTURES_DIR
reconstructed into OUT/<name>/, one Ray task each (twin.batch: local by default, a cluster with --address;
GPU tasks on CUDA), skipping what is finished, retrying failures a bounded number of times.

    OUT/<name>/          the reconstruction (reconstruction.output), replaced whole when done
    OUT/logs/<name>.log  what each job printed (stages, timings, a failure's traceback), every attempt
    OUT/batch.json       (twin.batch) one entry per capture: status, attempts, seconds, and the scores against the
                         capture's ground truth when it has one (twin captures do); rewritten as jobs end
A capture counts as finished when batch.json records it done and OUT/<name>/ verifies against its checksums
and was made with the same reconstruction settings; it is then skipped, keeping its recorded scores. A folder under
CAPTURES_DIR that is not a readable capture fails (after its retries) with the reason, and the others go on.
"""
from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path

from twin.batch import LOG_FOLDER, RECORD_FILE, BatchOptions, Job, outcomes_table, recorded_results, run_batch
from twin.outputs import Kind, claim_output

from reconstruction.output import ReconstructionFolder
from reconstruction.pipeline import ReconstructConfig, _jsonable, network_input

# the scores shown in the table: (header, key of the task's result)
COLUMNS = [("texels", "texels"), ("align px", "alignment.median_px"), ("normal deg", "maps.normal_deg.median"),
           ("ax %", "maps.alpha_x_pct.median"), ("ay %", "maps.alpha_y_pct.median"),
           ("rho_d %", "maps.rho_d_pct.median"), ("rho_s %", "maps.rho_s_pct.median"),
           ("ssim", "render.maps.ssim"), ("goals", "goals")]


def reconstruct_one(capture: str, output: str, config: dict) -> dict:
    """A Ray task: reconstruct one capture and score it when it carries ground truth (flat result dict)."""
    from reconstruction.evaluation.metrics import check, flatten_metrics
    from reconstruction.pipeline import reconstruct
    from reconstruction.evaluation.validation import evaluate, thresholds_for
    from twin.capture.session import CaptureSession

    cfg = _config(config)
    session = CaptureSession.open(capture)
    rig = session.rig()
    recon = reconstruct(capture, output, cfg, progress=True, rig=rig)  # stage lines: to the job's log
    out = {"texels": int(recon.grid.resolution ** 2), "rig": rig.name,
           **{f"timings.{k}": float(v) for k, v in recon.timings.items()}}
    if session.has_ground_truth:
        metrics, _ = evaluate(capture, recon, rig, device=cfg.device)
        flat = flatten_metrics(metrics)
        out.update({k: flat[k] for _, k in COLUMNS if k in flat})
        rows = check(metrics, thresholds_for(rig.name, cfg.resolution, session.sample))
        if rows:
            failed = sum(not r["passed"] for r in rows)
            out["goals"] = "pass" if not failed else f"{failed} missed"
    return out


# OUT, resumed (twin.outputs): its batch.json names the captures folder (capture-many's names its samples file)
RECONSTRUCT_MANY_FOLDER = Kind("a reconstruct-many folder", (RECORD_FILE,), field="captures")

# the settings a batch passes to its tasks (the command's options); the rest are ReconstructConfig's defaults
TASK_SETTINGS = ("resolution", "size_mm", "network", "device", "holdout_line")


def _config(d: dict) -> ReconstructConfig:
    return replace(ReconstructConfig(), **{k: v for k, v in d.items() if k in TASK_SETTINGS})


def find_captures(root) -> list[Path]:
    """The sub-folders of `root` (each should be a capture folder), sorted by name; hidden ones and the `logs/`
    folder that capture-many writes beside its captures are not captures."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder of capture folders")
    found = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name != LOG_FOLDER)
    if not found:
        raise ValueError(f"{root}: holds no capture folders")
    return found


def reconstruct_many(captures_dir, output, config: ReconstructConfig = ReconstructConfig(),
                     options: BatchOptions = BatchOptions()) -> list:
    """Run the batch (module docstring); returns twin.batch.Outcome per capture and writes OUT/batch.json."""
    out = Path(output)
    caps = find_captures(captures_dir)
    claim_output(out, RECONSTRUCT_MANY_FOLDER, [("the captures folder", captures_dir), network_input(config.network)])
    want = {k: v for k, v in asdict(config).items() if k in TASK_SETTINGS}
    if _config(want) != config:
        raise ValueError(f"reconstruct-many passes only {', '.join(TASK_SETTINGS)} to its tasks; the other "
                         "ReconstructConfig settings keep their defaults")
    previous = recorded_results(out / RECORD_FILE)
    jobs = [Job(c.name, {"capture": str(c), "output": str(out / c.name), "config": want}) for c in caps]
    full = _jsonable(asdict(config))

    def finished(job: Job):
        if job.name not in previous:  # scored and recorded, not only written (a kill may fall between)
            return None
        folder = ReconstructionFolder(job.args["output"])
        try:
            if folder.verify() or folder.summary().get("config") != full:
                return None
        except ValueError:  # no (readable) summary: not finished
            return None
        return previous[job.name]

    return run_batch(jobs, reconstruct_one, done=finished, options=options, record=out / RECORD_FILE,
                     header={"captures": str(Path(captures_dir)), "config": full}, logs=out / LOG_FOLDER)


def table(outcomes) -> str:
    return outcomes_table(outcomes, COLUMNS)
