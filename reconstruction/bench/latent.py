"""`hemicube bench latent-ceiling`: how near any latent gets the decoder to the exact lumitexel, against what the
network's own latent and the pipeline's fine-tuning reach (docs/accuracy.md, "best latent").

For each sample, a texture grid over its true maps (common.exact_texels: exact and noise-free, no camera, so the
photo's noise and footprint are not in these numbers), and three latents per texel:
  network    the encoder's latent of the exact learned-pattern measurements (fine-tuning's pass 0): the baseline;
  finetuned  the pipeline's three-pass fine-tuning from it against the exact lines, the held-out line left out;
  best       the fine-tuned latent optimised further against the exact lumitexel itself, every LED and channel
             (reconstruction.stages.finetune.latent_for_lumitexels, paper Eq. 3): what this search finds the decoder
             can represent; what it misses, the decoder cannot (or the search does not reach).
Each is scored as validate scores the latent render: the held-out line rendered from its decoded lumitexel against
the exact held-out line on the grid (SSIM, PSNR; the median and 90th percentile per-texel relative error), and its
decode against the exact lumitexel (the median per-texel Eq. 3).

Checks: the search's starting objective is Eq. 3 of the fine-tuned latent's decode as decode_rgb gives it (the
search optimises the figure that is scored, to float32 summation order), and the search ends no worse than it
started on its own objective.
"""
from __future__ import annotations

import time

import numpy as np

from reconstruction.bench.common import (device_name, exact_lumitexels, exact_texels, finetune_config, positive_int,
                                         software, synchroniser)

OBJECTIVE_RTOL = 1e-4  # float32 sums of N L 3 non-negative terms, in torch's order against numpy's float64

# small sizes that run on a CPU in seconds (`--tiny`)
TINY = {"rig_name": "mini", "samples": ("ramps",), "resolution": 8, "steps": 10, "finetune_iterations": (10, 5, 10)}


def bench_latent_ceiling(rig_name="paper", device="cpu", samples=("ramps",), resolution=64, size_mm=100.0,
                         steps=2000, lr=0.02, network="pretrained", finetune_iterations=None) -> dict:
    """finetune_iterations: fine-tuning's three caps (None: FinetuneConfig's, as `hemicube reconstruct` runs it)."""
    import torch

    import twin
    from twin.bench import finish_checks, same_work

    from reconstruction.network.data import _wp_device
    from reconstruction.pipeline import load_network

    positive_int("resolution", resolution)
    positive_int("steps", steps)
    rig = twin.load_rig(rig_name)
    dev = _wp_device(device)
    model = load_network(network, rig, dev)
    torch.manual_seed(0)
    res = {"bench": "latent-ceiling", "rig": rig.name, "device": device_name(dev), "network": network,
           "resolution": resolution, "size_mm": size_mm, "best_steps": steps, "best_lr": lr,
           "finetune_iterations": list(finetune_config(finetune_iterations, (), dev).caps),
           "software": software(), "samples": {}}
    checks = []
    for name in samples:
        rec, objective = _sample(rig, model, name, resolution, size_mm, steps, lr, dev, finetune_iterations)
        res["samples"][name] = rec
        checks.append(same_work(f"{name}_search_start_vs_eq3_of_finetuned_decode", [objective["search_start"]],
                                [objective["finetuned_eq3"]], rtol=OBJECTIVE_RTOL))
        checks.append({"check": f"{name}_search_not_worse_than_its_start", "start": objective["search_start"],
                       "end_eq3": objective["best_eq3"],
                       "passed": bool(objective["best_eq3"] <= objective["search_start"] * (1 + OBJECTIVE_RTOL))})
    return finish_checks(res, checks)


def _sample(rig, model, name: str, R: int, size_mm: float, steps: int, lr: float, dev: str, iterations):
    """One sample's record (scores per latent, seconds per stage) and its objective figures for the checks."""
    import torch

    from reconstruction.network.data import synthesize
    from reconstruction.pipeline import choose_holdout
    from reconstruction.evaluation.metrics import image_scores
    from reconstruction.stages.finetune import decode_rgb, finetune, grey_to_rgb, latent_for_lumitexels, simulate_lines
    from reconstruction.stages.latents import decode

    sync = synchroniser(dev)
    seconds = {}

    def timed(stage, fn):
        sync()
        t = time.perf_counter()
        out = fn()
        sync()
        seconds[stage] = time.perf_counter() - t
        return out

    truth, grid, pos, params, W, lines = timed("exact_texels", lambda: exact_texels(rig, name, R, size_mm, dev))
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    Wu = W[:, upper]
    m_true = exact_lumitexels(rig, pos, params, dev)[:, upper]
    q = {"position": torch.from_numpy(pos), **{k: torch.tensor(v, dtype=torch.float32) for k, v in params.items()}}
    with torch.no_grad():  # the network's input as training synthesises it: each view's exact lumitexels, measured
        views = torch.stack([synthesize(rig, q, c, dev) for c in list(rig.cameras)[:2]], dim=1)
        model.eval()
        learned = model.measure(views).cpu().numpy()
    hold = choose_holdout(lines, np.ones(len(pos), bool))
    z = timed("decode", lambda: decode(model, learned, device=dev))
    ft = timed("finetune", lambda: finetune(model, z, lines, Wu, finetune_config(iterations, (hold,), dev)))
    best, start, _ = timed("best_latent", lambda: latent_for_lumitexels(model, ft.latent, m_true, steps, lr))

    exact_line = lines[:, hold]
    rec = {"holdout_line": hold, "alpha_range": [float(np.min(truth.alpha)), float(np.max(truth.alpha))]}
    eq3 = {}
    t = time.perf_counter()
    for label, lat in (("network", grey_to_rgb(z)), ("finetuned", ft.latent), ("best", best)):
        render = simulate_lines(model, lat, Wu[hold:hold + 1])[:, 0]
        per_texel = np.square(np.log1p(decode_rgb(model, lat).astype(np.float64)) - np.log1p(m_true)).sum(axis=(1, 2))
        eq3[label] = float(per_texel.sum())
        rel = np.abs(render - exact_line).mean(1) / np.maximum(exact_line.mean(1), 1e-12)
        s = image_scores(exact_line.reshape(R, R, 3), render.reshape(R, R, 3))
        rec[label] = {"ssim": s["ssim"], "psnr_db": s["psnr_db"], "median_rel_err": float(np.median(rel)),
                      "p90_rel_err": float(np.percentile(rel, 90)), "median_eq3": float(np.median(per_texel))}
    seconds["scoring"] = time.perf_counter() - t
    rec["seconds"] = seconds
    return rec, {"search_start": start, "finetuned_eq3": eq3["finetuned"], "best_eq3": eq3["best"]}
