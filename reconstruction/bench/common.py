"""What the reconstruction's benchmarks share: argument checks, the device's and the software's names for the
record, timing with the device's queued work included, and the exact texels of a sample on a texture grid."""
from __future__ import annotations

import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def positive_int(name: str, v) -> None:
    """A clear error, before any work, for a count that is not a positive integer."""
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} must be a positive integer, got {v!r}")


def device_name(device) -> str:
    """The GPU's model for a CUDA device, else "cpu"."""
    import torch

    dev = torch.device(device)
    return torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"


def synchroniser(device):
    """A function that waits for the device's queued work: timings must include it."""
    import torch

    dev = torch.device(device)
    return (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)


def best_of(fn, repeats: int, sync) -> float:
    """The fastest of `repeats` timed calls of fn, queued device work included."""
    ts = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def log_tail(path, chars: int = 2000) -> str:
    """The end of a stage's log, for the record of a stage that failed."""
    return Path(path).read_text(errors="replace")[-chars:]


def software() -> dict:
    """The versions a figure depends on (python, torch, warp, the platform) and the checkout's commit, where the
    package runs from a git checkout (None otherwise)."""
    import torch
    import warp as wp

    root = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        commit = out.stdout.strip() if out.returncode == 0 else None
        if commit:
            dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                   capture_output=True, text=True, timeout=30).stdout.strip()
            commit += "+changes" if dirty else ""
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"python": sys.version.split()[0], "torch": torch.__version__, "warp": wp.__version__,
            "platform": platform.platform(), "git_commit": commit}


def exact_texels(rig, sample: str, resolution: int, size_mm: float, device: str):
    """A resolution^2 texture grid over size_mm of `sample`'s true maps (resampled as validate resamples them,
    from maps at 4x the grid) on `rig`, with what the forward model gives there exactly, at each texel's centre:
    no camera, no noise, no footprint. Returns (truth maps, grid, positions (N, 3), GGX parameters as arrays,
    line weights (64, L, 3) and the primary view's line measurements (N, 64, 3), in network units)."""
    from twin.capture.pattern_sets import linear_lights
    from twin.materials.samples import load_sample

    from reconstruction.evaluation.metrics import resample_maps
    from reconstruction.evaluation.validation import exact_measurements, map_parameters
    from reconstruction.stages.extraction import TextureGrid

    grid = TextureGrid(resolution, size_mm)
    truth = resample_maps(load_sample(sample, 4 * resolution), grid.size_mm, resolution)
    params = map_parameters(truth)
    pos = grid.positions(rig).astype(np.float32)
    W = linear_lights(rig).weights.astype(np.float32)
    lines = exact_measurements(rig, pos, params, W, next(iter(rig.cameras)), device)
    return truth, grid, pos, params, W, lines


def exact_lumitexels(rig, pos, params: dict, device) -> np.ndarray:
    """(N, num_leds, 3) lumitexels in the primary view, exact (twin.lumitexels, as
    reconstruction.evaluation.validation.exact_measurements), in network units."""
    import twin

    from reconstruction.network.data import LUMITEXEL_SCALE

    return twin.lumitexels(rig, pos, convention="physical", camera=next(iter(rig.cameras)), visibility=True,
                           device=device, transparency=np.zeros(len(pos)), **params) * np.float32(LUMITEXEL_SCALE)


def finetune_config(iterations, holdout, device):
    """FinetuneConfig as `hemicube reconstruct` runs it, but for the lines held out and, where given, the three
    passes' iteration caps (a bench's small sizes)."""
    from reconstruction.stages.finetune import FinetuneConfig

    over = {} if iterations is None else {"iterations": tuple(iterations)}
    return FinetuneConfig(holdout=tuple(holdout), device=device, **over)
