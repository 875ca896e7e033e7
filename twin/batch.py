"""Batches of independent jobs on Ray (docs/scale-out.md): `hemicube capture-many` and `hemicube reconstruct-many`.

    outcomes = run_batch(jobs, task, done=finished, options=BatchOptions(address=None, gpus_per_task=1))

One Ray task per job, on this machine (`ray.init()`: no set-up, as many tasks at a time as it has cores, or
GPUs for GPU tasks) or on a running cluster (`address`, e.g. "ray://head:10001" or "auto"). Ray schedules;
this module adds what a database build needs around it:
* idempotent: `done(job)` is asked in the driver before anything starts; a job whose output is finished and
  verifies (the caller checks its checksums) is skipped, with the result it reports;
* bounded retries: a task that raises, whose worker dies, or that runs over `timeout` seconds (its worker is
  then killed: a hung camera read or a stuck kernel must not hold a GPU forever) is submitted again, at most
  `retries` more times, then reported failed with its last error (one line); the batch goes on. The driver
  submits no more tasks than the cluster can run at once (its CPUs, or GPUs, over a task's share, counted
  when the batch starts), so that an attempt's clock starts when it can run, not while it queues;
* progress on stderr as tasks end, and one outcome per job at the end (status done / skipped / failed,
  attempts, seconds, the task's result) for the caller's table.
The task function must be importable by the workers (a module-level function of this project); it takes
the job's `args` as keyword arguments and returns a JSON-able dict. Jobs write their own output atomically,
so a killed batch resumes where it stopped when run again.
Environment: the variables in `PASSED_ENV` that are set in the driver go to every worker through Ray's
runtime_env (the Warp kernel cache, NCCL's and torch's switches, e.g. NVLink multicast off).
"""
from __future__ import annotations

import contextlib
import json
import os
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Job", "Outcome", "BatchOptions", "run_batch", "PASSED_ENV", "outcomes_table", "write_record",
           "recorded_results", "RECORD_FILE", "LOG_FOLDER"]

RECORD_FILE = "batch.json"  # the record of a batch, in its output folder
LOG_FOLDER = "logs"         # the jobs' logs, in its output folder

PASSED_ENV = ("WARP_CACHE_PATH", "PYTHONPATH", "HEMICUBE_REFERENCE", "NCCL_NVLS_ENABLE", "NCCL_DEBUG",
              "TORCH_SYMM_MEM_DISABLE_MULTICAST", "NVSHMEM_DISABLE_NVLS", "GENICAM_CACHE_V3_5")


@dataclass(frozen=True)
class Job:
    name: str            # unique in the batch; names the output
    args: dict           # keyword arguments of the task function


@dataclass
class Outcome:
    name: str
    status: str          # "done", "skipped" or "failed"
    attempts: int = 0
    seconds: float = 0.0  # of the last attempt, inside the worker (skipped: 0)
    result: dict = field(default_factory=dict)
    error: str | None = None

    def to_json(self) -> dict:
        return {"name": self.name, "status": self.status, "attempts": self.attempts, "seconds": self.seconds,
                "result": self.result, "error": self.error}


@dataclass(frozen=True)
class BatchOptions:
    address: str | None = None   # None: a local Ray started for this batch; else a running cluster's address
    cpus_per_task: float = 1.0
    gpus_per_task: float = 0.0   # > 0: GPU tasks (Ray sets CUDA_VISIBLE_DEVICES; the task uses "cuda")
    num_cpus: int | None = None  # local Ray only: cores it may use (default: all), i.e. tasks at a time
    retries: int = 2             # submissions after the first, per job
    timeout: float | None = None  # seconds an attempt may run (from its submission, worker start included)
    progress: bool = True

    def __post_init__(self):
        if not (isinstance(self.retries, int) and self.retries >= 0):
            raise ValueError(f"retries must be an integer >= 0, got {self.retries!r}")
        if not self.cpus_per_task > 0 or self.gpus_per_task < 0:
            raise ValueError("cpus_per_task must be > 0 and gpus_per_task >= 0")
        if self.num_cpus is not None and self.num_cpus < 1:
            raise ValueError(f"num_cpus must be >= 1, got {self.num_cpus}")
        if self.timeout is not None and not self.timeout > 0:
            raise ValueError(f"timeout must be > 0 seconds, got {self.timeout}")


def _attempt(fn, args: dict, cpus: float, log: str | None, attempt: int) -> dict:
    """One attempt in a Ray worker: the task's result and its seconds. Errors come back as one line plus
    the place they were raised, so that the driver can report them without Ray's wrapping. With `log`, what
    the task prints (its stage lines, progress bars, the full traceback of a failure) is appended there."""
    if not os.environ.get("CUDA_VISIBLE_DEVICES"):
        import torch

        torch.set_num_threads(max(1, int(cpus)))  # the cores Ray gave this task, not all of the machine's
    with open(log, "a", buffering=1) if log else contextlib.nullcontext(None) as out, \
            contextlib.redirect_stdout(out or sys.stdout), contextlib.redirect_stderr(out or sys.stderr):
        print(f"--- attempt {attempt}, {time.strftime('%Y-%m-%d %H:%M:%S')}, pid {os.getpid()}, "
              f"CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES', '')!r}")
        t0 = time.perf_counter()
        try:
            result = fn(**args)
        except Exception as e:  # noqa: BLE001 - reported by the driver, retried there
            traceback.print_exc()
            tb = traceback.extract_tb(e.__traceback__)[-1]
            return {"ok": False, "error": f"{type(e).__name__}: {e}".splitlines()[0] +
                    f" ({os.path.basename(tb.filename)}:{tb.lineno})", "seconds": time.perf_counter() - t0}
        print(f"--- done in {time.perf_counter() - t0:.1f} s")
        return {"ok": True, "result": result, "seconds": time.perf_counter() - t0}


def _say(options: BatchOptions, msg: str) -> None:
    if options.progress:
        print(f"[batch] {msg}", file=sys.stderr, flush=True)


def write_record(path, header: dict, outcomes: list[Outcome]) -> None:
    """The batch's record file (`batch.json`: the header's keys and "outcomes"), replaced atomically."""
    from twin.atomic import write_bytes_atomic

    doc = {**header, "outcomes": [o.to_json() for o in outcomes]}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, (json.dumps(doc, indent=1) + "\n").encode())


def recorded_results(path) -> dict:
    """name -> result of the jobs a record file lists as done or skipped ({} when there is none)."""
    try:
        doc = json.loads(Path(path).read_text())
        return {o["name"]: o["result"] for o in doc["outcomes"] if o["status"] in ("done", "skipped")}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def run_batch(jobs: list[Job], fn, *, done=None, options: BatchOptions = BatchOptions(),
              record=None, header: dict | None = None, logs=None) -> list[Outcome]:
    """Run fn(**job.args) for every job not `done` (module docstring); outcomes in the jobs' order. With
    `record` (a path), the record file is written once the skips are known and again whenever a job ends, so
    that a killed batch keeps what it finished (first once Ray runs: a batch that cannot start leaves nothing);
    "pending" marks a job not ended yet. With `logs` (a folder), each
    job's output goes to logs/<name>.log, every attempt appended."""
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"job names must be unique; repeated: {dup}")
    outcomes = {j.name: Outcome(j.name, "pending") for j in jobs}
    todo = []
    for j in jobs:
        finished = done(j) if done is not None else None
        if finished is not None:
            outcomes[j.name] = Outcome(j.name, "skipped", result=finished)
            _say(options, f"{j.name}: finished before, skipped")
        else:
            todo.append(j)
    ordered = lambda: [outcomes[n] for n in names]  # noqa: E731
    update = (lambda: write_record(record, header or {}, ordered())) if record is not None else (lambda: None)
    if todo:
        _run_on_ray(todo, fn, outcomes, options, update, logs)  # records once Ray has started and can run them
    else:
        update()
    return ordered()


def _run_on_ray(todo: list[Job], fn, outcomes: dict, options: BatchOptions, update, logs) -> None:
    try:
        import ray
    except ImportError:
        raise ValueError("batches run on Ray, which is not installed: pip install 'hemicube-twin[scale]'") from None

    env = {k: os.environ[k] for k in PASSED_ENV if k in os.environ}
    started_here = not ray.is_initialized()
    if started_here:
        kw = dict(runtime_env={"env_vars": env}, include_dashboard=False, logging_level="ERROR",
                  log_to_driver=False)
        if options.address is None:
            kw["num_cpus"] = options.num_cpus
        ray.init(address=options.address, **kw)
    try:
        if options.gpus_per_task > 0 and ray.cluster_resources().get("GPU", 0) < options.gpus_per_task:
            raise ValueError(f"GPU tasks asked for, but the Ray cluster has {ray.cluster_resources().get('GPU', 0):g} "
                             "GPUs; use --device cpu or a cluster with GPUs")
        task = ray.remote(num_cpus=options.cpus_per_task, num_gpus=options.gpus_per_task, max_retries=0)(_attempt)
        slots = _slots(ray.cluster_resources(), options)
        running, queue = {}, list(todo)  # running: ref -> (job, deadline)
        update()
        if logs is not None:
            Path(logs).mkdir(parents=True, exist_ok=True)

        def submit(job: Job) -> None:
            o = outcomes[job.name]
            o.attempts += 1
            log = str(Path(logs).resolve() / f"{job.name}.log") if logs is not None else None
            deadline = time.monotonic() + options.timeout if options.timeout is not None else float("inf")
            running[task.remote(fn, job.args, options.cpus_per_task, log, o.attempts)] = (job, deadline)

        ended, total = 0, len(todo)
        t0 = time.perf_counter()
        while running or queue:
            while queue and len(running) < slots:
                submit(queue.pop(0))
            wait = min(d for _, d in running.values()) - time.monotonic()
            ready, _ = ray.wait(list(running), num_returns=1, timeout=None if wait == float("inf") else max(wait, 0))
            if ready:
                ref = ready[0]
                job = running.pop(ref)[0]
                try:
                    r = ray.get(ref)
                except ray.exceptions.RayError as e:  # the worker died (killed, out of memory): retried alike
                    r = {"ok": False, "error": f"{type(e).__name__}: {str(e).splitlines()[0]}", "seconds": 0.0}
            else:  # the first deadline passed: kill that attempt's worker
                ref = min(running, key=lambda k: running[k][1])
                job = running.pop(ref)[0]
                ray.cancel(ref, force=True)
                r = {"ok": False, "error": f"TimeoutError: the attempt ran over the batch's timeout of "
                     f"{options.timeout:g} s; its worker was killed", "seconds": float(options.timeout)}
            o = outcomes[job.name]
            o.seconds = float(r["seconds"])
            if r["ok"]:
                o.status, o.result, o.error = "done", r["result"], None
            elif o.attempts <= options.retries:
                _say(options, f"{job.name}: attempt {o.attempts} failed ({r['error']}); retrying")
                o.error = r["error"]
                queue.insert(0, job)
                continue
            else:
                o.status, o.error = "failed", r["error"]
            ended += 1
            update()
            _say(options, f"{ended}/{total} {job.name}: {o.status} after {o.attempts} attempt(s), {o.seconds:.1f} s "
                 f"({time.perf_counter() - t0:.0f} s since the start)")
    finally:
        if started_here:
            ray.shutdown()


def _slots(resources: dict, options: BatchOptions) -> int:
    """How many tasks the cluster can run at once: its CPUs over a task's share, and its GPUs over a GPU task's
    (at least 1)."""
    n = int(resources.get("CPU", 1) // options.cpus_per_task)
    if options.gpus_per_task > 0:
        n = min(n, int(resources.get("GPU", 0) // options.gpus_per_task))
    return max(1, n)


def outcomes_table(outcomes: list[Outcome], columns: list[tuple[str, str]]) -> str:
    """A plain-text table: name, status, attempts, seconds, then `columns` (header, result key) with the
    values the task returned, and the error of a failed job."""
    head = ["name", "status", "attempts", "s"] + [h for h, _ in columns] + ["error"]
    rows = []
    for o in outcomes:
        vals = [o.name, o.status, str(o.attempts), f"{o.seconds:.1f}" if o.status == "done" else "-"]
        for _, key in columns:
            v = o.result.get(key) if o.result else None
            vals.append("-" if v is None else (f"{v:.3g}" if isinstance(v, float) else str(v)))
        vals.append(o.error or "")
        rows.append(vals)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    line = lambda r: "  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in rows])


def add_arguments(parser) -> None:
    """The batch options of the `*-many` commands."""
    parser.add_argument("--address", help="a running Ray cluster's address (e.g. auto, ray://HEAD:10001); default: "
                        "a local Ray started for this batch")
    parser.add_argument("--jobs", type=int, help="local Ray: tasks at a time on the CPU (default: the cores)")
    parser.add_argument("--gpus-per-task", type=float, help="GPUs per task with --device cuda (default: 1)")
    parser.add_argument("--retries", type=int, default=2, help="submissions after the first for a failing job "
                        "(default: %(default)s)")
    parser.add_argument("--timeout", type=float, help="seconds a job's attempt may run before its worker is "
                        "killed and the attempt counts as failed (default: no limit)")
    parser.add_argument("--no-progress", action="store_true", help="no progress lines on stderr")


def options_from(args, device: str) -> BatchOptions:
    gpus = args.gpus_per_task if args.gpus_per_task is not None else (1.0 if device.startswith("cuda") else 0.0)
    if gpus > 0 and not device.startswith("cuda"):
        raise ValueError("--gpus-per-task needs --device cuda")
    return BatchOptions(address=args.address, gpus_per_task=gpus, num_cpus=args.jobs, retries=args.retries,
                        timeout=args.timeout, progress=not args.no_progress)


def report(outcomes: list[Outcome], table: str, batch_file) -> int:
    """Print the table and a one-line verdict; exit code 1 when a job failed."""
    print(table)
    n = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    print(f"{n['done']} done, {n['skipped']} skipped (finished before), {n['failed']} failed; summary: {batch_file}")
    return 1 if n["failed"] else 0
