"""Where paper stock's and fabric's alpha error enters on the paper rig (issue #13 item 4: both miss alpha <= 10% there,
and neither the texel's footprint (512^2, the cell reading) nor the photos' weight per frame moved them): the fit, the
decoded lumitexels, or the photos' noise?

    [RIG=mini] python docs/bench/fit_limits_2026-11-27.py OUT.json DEVICE RESOLUTION NOISE SAMPLE [SAMPLE ...]

For each sample, a RESOLUTION^2 texture grid over 100 mm of its true maps (the paper rig, or RIG's; its shipped
network), and the pipeline's fit (FitConfig with the pipeline's photo weight for four frames, lambda_lines 400; the
kept lines and the learned-pattern photos of the primary view, the secondary view's learned-pattern photos with their
own albedos; the joint prior on the grid) run on four sets of inputs, every measurement computed exactly at the texel
centre (no camera, no footprint):
  oracle          the exact lumitexels and the exact photos;
  noisy_photos    the exact lumitexels, the photos times (1 + NOISE x a standard normal) each (texel, photo, channel);
  decoded         the lumitexels decoded from the fine-tuned latents (the encoder's latent of the exact learned-pattern
                  photos, fine-tuned against the exact lines, the held-out line left out), and the exact photos;
  decoded_noisy   both: the latents fine-tuned against the noisy lines, the fit given the noisy photos.
Each is scored as validate scores the maps (reconstruction.metrics.map_errors, medians). NOISE 0.005 is about a
four-frame photo's per-texel noise at the paper rig's 192^2 texels (docs/accuracy.md: 1.07% per texel and line photo
with one frame on the mini rig, about the paper rig's at 192^2, halved by four frames). A record of how the numbers
were measured, not part of the pipeline.
"""
import json
import os
import sys
import time

import numpy as np
import torch

import twin
from reconstruction.data import LUMITEXEL_SCALE
from reconstruction.extraction import TextureGrid
from reconstruction.finetune import FinetuneConfig, decoded_lumitexels, finetune
from reconstruction.fitting import FitConfig, fit_ggx, to_maps
from reconstruction.latents import decode
from reconstruction.metrics import map_errors, resample_maps
from reconstruction.pipeline import choose_holdout, load_network
from reconstruction.validation import _map_params
from twin.capture.pattern_sets import linear_lights
from twin.capture.plan import DEFAULT_FRAMES, default_learned
from twin.materials.samples import load_sample

out_path, dev, R, noise, names = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), sys.argv[5:]
rig = twin.load_rig(os.environ.get("RIG", "paper"))
model = load_network("pretrained", rig, dev)
upper = np.flatnonzero(~np.asarray(rig.is_bottom))
W = linear_lights(rig).weights.astype(np.float32)
P = default_learned(rig).weights.astype(np.float32)  # the (+, -) learned frames the paper rig's capture shows
cams = list(rig.cameras)[:2]
grid = TextureGrid(R, 100.0)
pos = grid.positions(rig).astype(np.float32)
fit_cfg = FitConfig(lambda_lines=FitConfig().lambda_lines * DEFAULT_FRAMES, device=dev)
ft_cfg = FinetuneConfig(device=dev)
record = {"rig": rig.name, "device": torch.cuda.get_device_name(0) if dev == "cuda" else "cpu", "resolution": R, "size_mm": 100.0,
          "noise": noise, "lambda_lines": fit_cfg.lambda_lines, "samples": {}}


def exact(params, patterns, camera):
    kw = dict(camera=camera, visibility=True, device=dev, transparency=np.zeros(len(pos)))
    return twin.measurements(rig, pos, patterns=patterns, convention="physical", **params, **kw) * np.float32(
        LUMITEXEL_SCALE)


for name in names:
    t0 = time.perf_counter()
    truth = resample_maps(load_sample(name, 4 * R), grid.size_mm, R)
    params = _map_params(truth)
    lines = exact(params, W, cams[0])                                      # (N, 64, 3)
    learned_photos = np.stack([exact(params, P, c) for c in cams], axis=1)  # (N, 2, 2K, 3)
    m_true = twin.lumitexels(rig, pos, convention="physical", camera=cams[0], visibility=True, device=dev,
                             transparency=np.zeros(len(pos)), **params)[:, upper] * np.float32(LUMITEXEL_SCALE)
    hold = choose_holdout(lines, np.ones(len(pos), bool))
    keep = [k for k in range(lines.shape[1]) if k != hold]
    rng = np.random.default_rng(7)
    noisy_lines = (lines * (1 + noise * rng.standard_normal(lines.shape))).astype(np.float32)
    noisy_learned = (learned_photos * (1 + noise * rng.standard_normal(learned_photos.shape))).astype(np.float32)
    rec = {"holdout_line": hold, "alpha_range": [float(np.min(truth.alpha)), float(np.max(truth.alpha))]}

    def latents(ln, lp):
        """The pipeline's decode (the learned measurements as extraction forms them) and fine-tuning."""
        learned = (lp[:, :, 0::2] - lp[:, :, 1::2]).mean(axis=3)
        z = decode(model, learned, device=dev)
        ft = finetune(model, z, ln, W[:, upper], FinetuneConfig(holdout=(hold,), device=dev))
        return decoded_lumitexels(model, ft.latent, precision=ft_cfg.precision)

    inputs = {"oracle": (lambda: m_true, lines, learned_photos),
              "noisy_photos": (lambda: m_true, noisy_lines, noisy_learned),
              "decoded": (lambda: latents(lines, learned_photos), lines, learned_photos),
              "decoded_noisy": (lambda: latents(noisy_lines, noisy_learned), noisy_lines, noisy_learned)}
    for label, (lumi, ln, lp) in inputs.items():
        t1 = time.perf_counter()
        photos = np.concatenate([ln[:, keep], lp[:, 0]], axis=1)
        weights = np.concatenate([W[keep][:, upper], P[:, upper]], axis=0)
        fit = fit_ggx(rig, pos, lumi(), lines=photos, line_weights=weights, secondary=(lp[:, 1], P[:, upper]),
                      grid_shape=grid.shape, config=fit_cfg)
        e = map_errors(truth, to_maps(fit, grid.shape, grid.size_mm))
        rec[label] = {k: e[k]["median"] for k in ("alpha_x_pct", "alpha_y_pct", "rho_d_pct", "rho_s_pct", "normal_deg",
                                                   "tangent_deg")}
        rec[label]["seconds"] = time.perf_counter() - t1
        print(name, label, json.dumps(rec[label]), flush=True)
    rec["seconds"] = time.perf_counter() - t0
    record["samples"][name] = rec
    with open(out_path, "w") as f:  # after every sample: a run stopped at a call's limit keeps what it finished
        json.dump(record, f, indent=1)
