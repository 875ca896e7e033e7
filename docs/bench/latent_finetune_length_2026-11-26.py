"""Does fine-tuning stop too early for the latent render? (issue #13: latent-render SSIM 0.88-0.97 against 0.98)

    python docs/bench/latent_finetune_length_2026-11-26.py SAMPLE RESOLUTION OUT.jsonl [--device cuda] [--rig paper]

Captures SAMPLE on the paper rig (seed 1, maps as fine as the grid, as `hemicube validate` does), aligns and
extracts it on a RESOLUTION^2 grid, decodes it with the shipped network, then fine-tunes the same decoded latents
under several FinetuneConfig variants (the default; float32; the paper's fixed 100/50/200; the released caps
500/50/500 without early stopping) with the same held-out line as the pipeline. For each it writes one JSON line:
the iterations, the seconds, the median per-texel pass-3 objective, and the held-out line's render from the
latent scored (SSIM, PSNR) against (a) the photo (what validate reports), (b) the TRUE maps' render (noise-free:
the network's and fine-tuning's share alone), beside (c) the true maps' render against the photo (the ceiling
the photo's noise and footprint allow). No fit: the latent render does not depend on it.
"""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def main(sample: str, resolution: int, out_path: str, device: str = "cuda", rig_name: str = "paper"):
    import torch

    import twin
    from reconstruction.alignment import AlignConfig, align_views
    from reconstruction.extraction import extract, texture_grid
    from reconstruction.finetune import FinetuneConfig, finetune, simulate_lines
    from reconstruction.latents import decode
    from reconstruction.metrics import image_scores, resample_maps
    from reconstruction.pipeline import choose_holdout, load_network
    from reconstruction.validation import _map_params, _render_lines
    from twin.capture.plan import indices_of
    from twin.capture.runner import SAMPLE_RESOLUTION, capture
    from twin.capture.session import CaptureSession

    rig = twin.load_rig(rig_name)
    work = Path(".gpu/lt") / f"{rig_name}_{sample}_{resolution}"
    t0 = time.perf_counter()
    cap = capture(rig, sample, work / "capture", seed=1, device=device, progress=False,
                  resolution=max(SAMPLE_RESOLUTION, resolution))
    session = CaptureSession.open(cap)
    t_cap = time.perf_counter() - t0
    uniform = indices_of(session).uniform
    alignment = align_views(session.photo(uniform, 0), session.photo(uniform, 1), rig, AlignConfig(device=device))
    grid = texture_grid(session, rig, resolution, None)
    meas = extract(session, rig, grid, alignment, progress=False)
    model = load_network("pretrained", rig, device)
    z56 = decode(model, meas.learned, device=device)
    hold = choose_holdout(meas.lines, meas.valid)
    R = grid.resolution
    photo = meas.lines[:, hold].reshape(R, R, 3)
    truth = resample_maps(session.ground_truth_maps(), grid.size_mm, R)
    true_render = _render_lines(rig, grid.positions(rig), _map_params(truth), meas.line_weights[hold],
                                device).reshape(R, R, 3)
    head = {"sample": sample, "resolution": R, "device": torch.cuda.get_device_name() if device.startswith("cuda")
            else "cpu", "holdout_line": hold, "capture_and_extraction_s": round(time.perf_counter() - t0, 1),
            "capture_s": round(t_cap, 1), "truth_vs_photo": image_scores(photo, true_render)}
    variants = {"default (code rules, tf32)": FinetuneConfig(),
                "code rules, float32": FinetuneConfig(precision="float32"),
                "paper 100/50/200, tf32": FinetuneConfig(source="paper"),
                "caps 500/50/500, no early stop, tf32": FinetuneConfig(early_stopping=False)}
    with open(out_path, "a") as f:
        for name, cfg in variants.items():
            cfg = replace(cfg, holdout=(hold,), device=device)
            t = time.perf_counter()
            ft = finetune(model, z56, meas.lines, meas.line_weights, cfg)
            sec = time.perf_counter() - t
            latent = simulate_lines(model, ft.latent, meas.line_weights[hold:hold + 1])[:, 0].reshape(R, R, 3)
            keep = [k for k in range(meas.lines.shape[1]) if k != hold]
            fit_lines = simulate_lines(model, ft.latent, meas.line_weights[keep])
            rel = np.abs(fit_lines - meas.lines[:, keep]).mean(axis=(1, 2)) / np.maximum(
                meas.lines[:, keep].mean(axis=(1, 2)), 1e-9)
            row = dict(head, variant=name, seconds=round(sec, 1),
                       iterations={k: int(np.median(v)) for k, v in ft.iterations.items()},
                       objective={k: [float(a) for a in v] for k, v in ft.objective.items()},
                       kept_lines_median_rel_abs_err=float(np.median(rel)),
                       latent_vs_photo=image_scores(photo, latent), latent_vs_truth=image_scores(true_render, latent))
            f.write(json.dumps(row) + "\n")
            f.flush()
            print(name, sec, row["latent_vs_photo"]["ssim"], row["latent_vs_truth"]["ssim"], flush=True)


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("sample")
    p.add_argument("resolution", type=int)
    p.add_argument("out")
    p.add_argument("--device", default="cuda")
    p.add_argument("--rig", default="paper")
    a = p.parse_args()
    main(a.sample, a.resolution, a.out, a.device, a.rig)
