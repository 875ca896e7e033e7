"""`hemicube bench e2e`: a capture and its reconstruction as users run them, end to end, no extrapolation.

The real commands, each its own process, one after the other (as in docs/performance.md's end-to-end figures):
  capture       `hemicube capture --rig R --sample S --seed N [--sample-resolution N] [--frames F] --device D
                 -o W/capture`
  reconstruct   `hemicube reconstruct W/capture [--resolution N] [--network NET] --device D -o W/reconstruction`
with the commands' own defaults for everything not given (the bench's `--resolution` sets both the sample's maps,
capture's `--sample-resolution`, and the texture grid, reconstruct's `--resolution`). Per stage: the wall time of the
process (imports and Warp's kernel loads included), its exit code, the bytes it wrote, the host's peak resident memory
of the process, and, on CUDA, the peak of the device's used memory polled at device level while it ran
(twin.bench.PeakDeviceMemory: every process's Warp and torch allocations together). The reconstruction's own stage
times come from its summary (ReconstructionFolder.summary).

Baseline check, the product's own verification: every file of the capture matches its manifest's checksum
(twin.capture.session.verify), and the reconstruction folder's every file matches its summary's
(reconstruction.output.ReconstructionFolder.verify). With `twice`, a second capture of the same seed into another
folder must list the same files with the same checksums: the capture is byte-identical run to run (for small
sizes: it doubles the capture's time and disk).
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from reconstruction.bench.common import device_name, log_tail, software
from twin.capture.plan import DEFAULT_SEED

# small sizes for a CPU (`--tiny`): the mini rig's real commands, a 16^2 sample and grid, one frame an exposure
TINY = {"rig_name": "mini", "resolution": 16, "frames": 1}


def bench_e2e(rig_name="paper", device="cpu", sample="ramps", resolution=None, seed=DEFAULT_SEED, frames=None,
              network=None, workdir=None, twice=False) -> dict:
    """`workdir`: where the capture and reconstruction folders go (kept); None: a temporary folder, removed."""
    import tempfile

    from twin.bench import finish_checks

    if workdir is None:
        with tempfile.TemporaryDirectory(prefix="hemicube-bench-e2e-") as tmp:
            return bench_e2e(rig_name, device, sample, resolution, seed, frames, network, tmp, twice)
    work = Path(workdir)
    if work.exists() and not work.is_dir():
        raise ValueError(f"{work}: the work folder is a file; choose a folder (or none, for a temporary one)")
    work.mkdir(parents=True, exist_ok=True)
    sized = [] if resolution is None else ["--sample-resolution", str(resolution)]  # the sample's maps
    grid = [] if resolution is None else ["--resolution", str(resolution)]  # the texture grid
    capture_args = ["capture", "--rig", rig_name, "--sample", sample, "--seed", str(seed), "--device", device,
                    "--no-progress", *sized, *([] if frames is None else ["--frames", str(frames)])]
    recon_args = ["reconstruct", str(work / "capture"), "--device", device, "--no-progress", *grid,
                  *([] if network is None else ["--network", network])]
    stages = {"capture": _run_stage([*capture_args, "-o", str(work / "capture")], work, "capture", device)}
    if stages["capture"]["exit_code"] == 0:
        stages["reconstruct"] = _run_stage([*recon_args, "-o", str(work / "reconstruction")], work, "reconstruct",
                                           device)
    if twice:
        stages["capture_again"] = _run_stage([*capture_args, "-o", str(work / "capture_again")], work,
                                             "capture_again", device)
    res = {"bench": "e2e", "rig": rig_name, "device": device_name(device), "sample": sample, "seed": seed,
           "resolution": resolution, "frames": frames, "network": network, "workdir": str(work),
           "commands": {"capture": ["hemicube", *capture_args], "reconstruct": ["hemicube", *recon_args]},
           "software": software(), "stages": stages,
           "seconds": {k: v["seconds"] for k, v in stages.items()},
           "total_s": stages["capture"]["seconds"] + stages.get("reconstruct", {}).get("seconds", 0.0)}
    if "reconstruct" in stages and stages["reconstruct"]["exit_code"] == 0:
        from reconstruction.output import ReconstructionFolder

        summary = ReconstructionFolder(work / "reconstruction").summary()
        res["reconstruct_stages_s"] = summary.get("timings_s", {})
        res["texels"] = summary.get("texels")
    return finish_checks(res, _checks(work, stages, twice))


def _run_stage(args: list[str], work: Path, name: str, device: str) -> dict:
    """`python -m hemicube.cli ARGS` in its own process, its output in work/NAME.log: the stage's record."""
    import torch

    from twin.bench import PeakDeviceMemory

    out = Path(args[args.index("-o") + 1])
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    dev = str(torch.device(device)) if torch.device(device).type == "cuda" else "cpu"
    with open(work / f"{name}.log", "wb") as log, PeakDeviceMemory(dev) as memory:
        t = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "hemicube.cli", *args], stdout=log, stderr=subprocess.STDOUT,
                                env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
    rec = {"seconds": seconds, "exit_code": proc.returncode, "bytes_written": _bytes(out),
           "host_peak_rss_mib": usage.ru_maxrss / 1024, "peak_device_memory_mib": memory.peak_mib}
    return rec if proc.returncode == 0 else {**rec, "log_tail": log_tail(work / f"{name}.log")}


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else 0


def _checks(work: Path, stages: dict, twice: bool) -> list[dict]:
    from twin.capture.session import verify

    from reconstruction.output import ReconstructionFolder

    checks = [{"check": f"{name}_exit_code", "exit_code": s["exit_code"], "passed": s["exit_code"] == 0,
               **({"log_tail": s["log_tail"]} if "log_tail" in s else {})} for name, s in stages.items()]
    for name in ("capture", "capture_again") if twice else ("capture",):
        if stages[name]["exit_code"] == 0:
            bad = verify(work / name)
            checks.append({"check": f"{name}_manifest_verifies", "failed_files": bad[:10], "passed": not bad})
    if stages.get("reconstruct", {}).get("exit_code") == 0:
        bad = ReconstructionFolder(work / "reconstruction").verify()
        checks.append({"check": "reconstruction_folder_verifies", "failed_files": bad[:10], "passed": not bad})
    if twice and stages["capture"]["exit_code"] == 0 and stages["capture_again"]["exit_code"] == 0:
        checks.append(same_capture(work / "capture", work / "capture_again"))
    return checks


def same_capture(a, b) -> dict:
    """Whether two capture folders hold the same files with the same checksums (their manifests'; verified by
    the checks before this one): the record names the files that differ."""
    from twin.capture.session import CaptureSession

    fa, fb = CaptureSession.open(a).files, CaptureSession.open(b).files
    differ = sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k))
    return {"check": "second_capture_byte_identical", "files": len(fa), "differing_files": differ[:10],
            "passed": bool(fa) and not differ}
