"""Fine-tuning against the lines alone (the paper's) or the lines and the primary view's learned-pattern photos
(`ReconstructConfig.finetune_photos`): the latent render of the held-out line and the maps, on the same inputs.

    python docs/bench/finetune_learned_2026-11-27.py exact OUT.json DEVICE RIG RESOLUTION SAMPLE [SAMPLE ...]
    python docs/bench/finetune_learned_2026-11-27.py validate OUT.json DEVICE RIG RESOLUTION SAMPLE [SAMPLE ...]

exact: a RESOLUTION^2 grid over 100 mm of each sample's true maps, every measurement exact and noise-free (no
camera), as docs/bench/latent_limits_2026-11-27.py; the encoder's latent, fine-tuned both ways, the held-out line
rendered from each against the exact held-out line (SSIM as validate scores it).
validate: a capture of each sample (seed 1, maps at least RESOLUTION^2), reconstructed both ways into two folders
under OUT.json's folder, each scored as `hemicube validate` scores it (reconstruction.validation.evaluate).
A record of how the numbers were measured, not part of the pipeline. JSON is written after every sample.
"""
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import twin

mode, out_path, dev, rig_name, R, names = (sys.argv[1], Path(sys.argv[2]), sys.argv[3], sys.argv[4],
                                           int(sys.argv[5]), sys.argv[6:])
VARIANTS = ("lines", "lines+learned")
rig = twin.load_rig(rig_name)
record = {"mode": mode, "device": torch.cuda.get_device_name(0) if dev.startswith("cuda") else "cpu",
          "rig": rig_name, "resolution": R, "samples": {}}


def exact(name: str) -> dict:
    from reconstruction.data import LUMITEXEL_SCALE
    from reconstruction.extraction import TextureGrid
    from reconstruction.finetune import FinetuneConfig, finetune, grey_to_rgb, simulate_lines
    from reconstruction.latents import decode
    from reconstruction.metrics import image_scores, resample_maps
    from reconstruction.pipeline import choose_holdout, load_network
    from reconstruction.validation import _map_params
    from twin.capture.pattern_sets import linear_lights
    from twin.capture.plan import default_learned
    from twin.materials.samples import load_sample

    model = load_network("pretrained", rig, dev)
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    learned_w = default_learned(rig).weights.astype(np.float32)  # the rig's own learned frames, (+, -) pairs
    W = linear_lights(rig).weights.astype(np.float32)
    grid = TextureGrid(R, 100.0)
    pos = grid.positions(rig).astype(np.float32)
    cams = list(rig.cameras)
    kw = dict(visibility=True, device=dev, transparency=np.zeros(len(pos)))
    truth = resample_maps(load_sample(name, max(4 * R, 128)), grid.size_mm, R)
    params = _map_params(truth)
    scale = np.float32(LUMITEXEL_SCALE)
    meas = {c: twin.measurements(rig, pos, patterns=learned_w, convention="physical", camera=c, **params, **kw) * scale
            for c in cams[:2]}
    learned = np.stack([(meas[c][:, 0::2] - meas[c][:, 1::2]).mean(2) for c in cams[:2]], 1)  # (N, 2, K)
    lines = twin.measurements(rig, pos, patterns=W, convention="physical", camera=cams[0], **params, **kw) * scale
    hold = choose_holdout(lines, np.ones(len(pos), bool))
    z = decode(model, learned, device=dev)
    rec = {"holdout_line": hold}
    exact_line = lines[:, hold].reshape(R, R, 3)
    for label, lat in [("network", grey_to_rgb(z))] + [
            (v, finetune(model, z, *((lines, W[:, upper]) if v == "lines" else
                                     (np.concatenate([lines, meas[cams[0]]], 1),
                                      np.concatenate([W[:, upper], learned_w[:, upper]], 0))),
                         FinetuneConfig(holdout=(hold,), device=dev)).latent) for v in VARIANTS]:
        render = simulate_lines(model, lat, W[hold:hold + 1, upper])[:, 0]
        rel = np.abs(render - lines[:, hold]).mean(1) / np.maximum(lines[:, hold].mean(1), 1e-12)
        s = image_scores(exact_line, render.reshape(R, R, 3))
        rec[label] = {"ssim": s["ssim"], "psnr_db": s["psnr_db"], "median_rel_err": float(np.median(rel))}
    return rec


def validate(name: str) -> dict:
    from reconstruction.pipeline import ReconstructConfig, reconstruct
    from reconstruction.validation import evaluate
    from twin.capture.runner import SAMPLE_RESOLUTION, capture

    base = out_path.parent / f"{name}_{R}"
    t = time.perf_counter()
    cap = capture(rig, name, base / "capture", seed=1, device=dev, progress=False,
                  resolution=max(SAMPLE_RESOLUTION, R))
    rec = {"capture_s": time.perf_counter() - t}
    for v in VARIANTS:
        t = time.perf_counter()
        cfg = replace(ReconstructConfig(), resolution=R, device=dev, finetune_photos=v)
        recon = reconstruct(cap, base / f"reconstruction_{v.replace('+', '_')}", cfg, progress=False, rig=rig)
        metrics, _ = evaluate(cap, recon, rig, device=dev)
        m = metrics["maps"]
        rec[v] = {"seconds": time.perf_counter() - t, "timings_s": recon.timings, "render": metrics["render"],
                  "maps": m}
    return rec


for name in names:
    t0 = time.perf_counter()
    rec = (exact if mode == "exact" else validate)(name)
    rec["seconds"] = time.perf_counter() - t0
    record["samples"][name] = rec
    print(name, json.dumps({k: (v["render"]["latent"]["ssim"] if isinstance(v, dict) and "render" in v else v)
                            for k, v in rec.items()}, default=str), flush=True)
    out_path.write_text(json.dumps(record, indent=1, default=float))
