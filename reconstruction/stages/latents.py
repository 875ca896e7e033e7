"""Decode (paper §7, reference §3.2 output): the network's encoder turns each texel's 2-view learned
measurements into its 56-D latent [albedo 8, shape 48]; and the latent texture file (reference §4 gathering).

    check_patterns(model, session, rig)          # the capture's learned frames are this network's patterns
    z = decode(model, meas.learned, device="cuda", batch=65536)     # (N, 56)
    write_latent_exr(path, latent72, grid_shape) / read_latent_exr(path)   # 72 float32 channels L_0 ... L_71
"""
from __future__ import annotations

import numpy as np
import torch

from reconstruction.stages.extraction import ExtractionError, capture_patterns, plan_indices

DECODE_BATCH = 65536  # texels per encoder batch: bounds memory for 1024^2 texels, large enough to fill a GPU


def check_patterns(model, session, rig) -> None:
    """The capture's learned frames (2K) must be the network's own exported patterns, level for level: the
    encoder only understands the measurements of the patterns it was trained with."""
    from reconstruction.network.train import export_patterns

    mine = export_patterns(model, rig)
    frames = plan_indices(session).learned_frames
    same = frames == len(mine.names)
    if same:
        theirs = capture_patterns(session, rig, list(mine.names))
        same = np.array_equal(np.rint(theirs * 255).astype(np.uint8), mine.levels)
    if not same:
        raise ExtractionError(f"{session.dir}: its learned frames ({frames}) are not this network's patterns "
                              f"({len(mine.names)} frames); decode it with the network whose patterns were captured")


def decode(model, learned: np.ndarray, *, device="cpu", batch: int = DECODE_BATCH) -> np.ndarray:
    """(N, 56) float32 latents [albedo, shape] of measurements (N, views, K), the encoder in eval mode."""
    learned = np.asarray(learned, dtype=np.float32)
    c = model.config
    if learned.ndim != 3 or learned.shape[1:] != (c.views, c.patterns_per_view):
        raise ValueError(f"measurements must be (N, {c.views}, {c.patterns_per_view}), got {learned.shape}")
    if not np.all(np.isfinite(learned)):
        raise ValueError("measurements hold NaN or Inf; decode only the valid texels")
    model = model.to(device).eval()
    out = np.empty((len(learned), c.latent_dim), np.float32)
    with torch.no_grad():
        for i in range(0, len(learned), batch):
            a, s = model.encode(torch.from_numpy(learned[i:i + batch]).to(device))
            out[i:i + batch] = torch.cat([a, s], dim=1).cpu().numpy()
    return out


def write_latent_exr(path, latent: np.ndarray, grid_shape) -> None:
    """Reference §4: the latent texture as float32 channels L_0 ... L_{D-1}, one image of grid_shape."""
    from twin.materials.exr import write_exr

    R, C = grid_shape
    z = np.asarray(latent, dtype=np.float32).reshape(R, C, -1)
    write_exr(path, {f"L_{k}": z[..., k] for k in range(z.shape[2])}, compression="piz")


def read_latent_exr(path) -> np.ndarray:
    """(R, C, D) float32 latents of a latent EXR (channels L_0 ... in numeric order)."""
    from twin.materials.exr import read_exr

    ch = read_exr(path)
    names = sorted((n for n in ch if n.startswith("L_")), key=lambda n: int(n[2:]))
    if not names:
        raise ValueError(f"{path}: no latent channels L_0 ...")
    return np.stack([ch[n] for n in names], axis=-1).astype(np.float32)
