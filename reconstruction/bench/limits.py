"""`hemicube bench fit-limits`: where the GGX fit's error enters, stage by stage: the fit itself (exact inputs), the
decoded lumitexels, the photos' noise, and the whole pipeline (docs/accuracy.md).

For each sample, a texture grid over its true maps and every measurement computed exactly at the texel centre
(common.exact_texels: no camera, no footprint), and the pipeline's fit (reconstruction.stages.fitting.fit_ggx with
the pipeline's inputs: the kept lines and the learned-pattern photos of the primary view, the secondary view's
learned-pattern photos, the joint prior on the grid; the photos' weight for `frames` frames an exposure, as
reconstruction.pipeline sets it) run on four sets of inputs:
  oracle         the exact lumitexels and the exact photos: the baseline, what the fit alone loses;
  decoded        the lumitexels decoded from the fine-tuned latents (the encoder's latent of the exact learned-pattern
                 photos as extraction forms it, fine-tuned against the exact lines, the held-out line left out), and
                 the exact photos;
  noisy_photos   the exact lumitexels, the photos times (1 + noise x a standard normal) each (texel, photo, channel);
  decoded_noisy  both: the latents fine-tuned against the noisy lines, the fit given the noisy photos.
With `capture`, a fifth: `pipeline`, that capture folder (of the same rig and sample, `hemicube capture`) run through
`hemicube reconstruct`'s pipeline on the same grid and scored as validate scores it. Each is scored against the truth
(reconstruction.evaluation.metrics.map_errors: the medians of the normal, tangent, alpha and albedo errors).
The default noise, 0.005, is about a four-frame photo's per-texel noise (docs/accuracy.md).

Check: the oracle's photos, rendered by the fused kernel, are its exact lumitexels projected onto the patterns
(the oracle is one: its two inputs describe the same texels).
"""
from __future__ import annotations

import time

import numpy as np

from reconstruction.bench.common import (device_name, exact_lumitexels, exact_texels, finetune_config, positive_int,
                                         software, synchroniser)
from reconstruction.evaluation.validation import exact_measurements
from twin.capture.plan import DEFAULT_SEED

ERRORS = ("normal_deg", "tangent_deg", "alpha_x_pct", "alpha_y_pct", "rho_d_pct", "rho_s_pct")
STAGES = ("oracle", "decoded", "noisy_photos", "decoded_noisy")
PROJECTION_RTOL = 1e-4  # float32 sums of L non-negative terms in two orders (twin.bench.LUMITEXEL_RTOL)
PROJECTION_ATOL = 1e-6  # of the largest value

# small sizes that run on a CPU in seconds (`--tiny`)
TINY = {"rig_name": "mini", "samples": ("ramps",), "resolution": 8, "finetune_iterations": (10, 5, 10),
        "fit_iterations": 2}


def bench_fit_limits(rig_name="paper", device="cpu", samples=("ramps",), resolution=64, size_mm=100.0, noise=0.005,
                     seed=DEFAULT_SEED, frames=None, capture=None, finetune_iterations=None,
                     fit_iterations=None) -> dict:
    """finetune_iterations: fine-tuning's three caps, fit_iterations: the fit's (None: FinetuneConfig's and
    FitConfig's, as `hemicube reconstruct` runs them); frames: the photos' frames an exposure the fit weighs them
    for (None: the capture plan's default)."""
    import torch

    import twin
    from twin.bench import finish_checks
    from twin.capture.plan import DEFAULT_FRAMES

    from reconstruction.network.data import _wp_device
    from reconstruction.pipeline import load_network

    positive_int("resolution", resolution)
    rig = twin.load_rig(rig_name)
    dev = _wp_device(device)
    model = load_network("pretrained", rig, dev)
    frames = DEFAULT_FRAMES if frames is None else frames
    torch.manual_seed(0)
    res = {"bench": "fit-limits", "rig": rig.name, "device": device_name(dev), "resolution": resolution,
           "size_mm": size_mm, "noise": noise, "seed": seed, "frames": frames,
           "finetune_iterations": finetune_iterations, "fit_iterations": fit_iterations, "stages": list(STAGES)
           + (["pipeline"] if capture is not None else []), "software": software(), "samples": {}}
    checks = []
    for name in samples:
        rec, check = _sample(rig, model, name, resolution, size_mm, noise, seed, frames, dev, finetune_iterations,
                             fit_iterations)
        if capture is not None:
            rec["pipeline"] = _pipeline(rig, capture, name, resolution, size_mm, dev)
        res["samples"][name] = rec
        checks.append(check)
    return finish_checks(res, checks)


def _sample(rig, model, name, R, size_mm, noise, seed, frames, dev, iterations, fit_iterations):
    """One sample's record (errors and seconds per stage) and its check."""
    from twin.bench import same_work

    from reconstruction.evaluation.metrics import map_errors
    from reconstruction.network.train import export_patterns
    from reconstruction.pipeline import choose_holdout
    from reconstruction.stages.extraction import Measurements
    from reconstruction.stages.finetune import decoded_lumitexels, finetune
    from reconstruction.stages.fitting import FitConfig, fit_ggx, to_maps
    from reconstruction.stages.latents import decode

    sync = synchroniser(dev)
    t0 = time.perf_counter()
    truth, grid, pos, params, W, lines = exact_texels(rig, name, R, size_mm, dev)
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    P = export_patterns(model, rig).weights.astype(np.float32)  # the learned frames a capture shows for this network
    cams = list(rig.cameras)[:2]
    learned = np.stack([exact_measurements(rig, pos, params, P, c, dev) for c in cams], axis=1)  # (N, 2, 2K, 3)
    m_all = exact_lumitexels(rig, pos, params, dev)
    check = same_work(f"{name}_oracle_photos_vs_projected_lumitexels", lines,
                      np.einsum("nlc,klc->nkc", m_all.astype(np.float64), W), rtol=PROJECTION_RTOL,
                      atol=PROJECTION_ATOL)
    m_true = m_all[:, upper]
    hold = choose_holdout(lines, np.ones(len(pos), bool))
    keep = [k for k in range(lines.shape[1]) if k != hold]
    rng = np.random.default_rng(seed)
    noisy_lines = (lines * (1 + noise * rng.standard_normal(lines.shape))).astype(np.float32)
    noisy_learned = (learned * (1 + noise * rng.standard_normal(learned.shape))).astype(np.float32)
    ft_cfg = finetune_config(iterations, (hold,), dev)
    fit_cfg = FitConfig(device=dev, lambda_lines=FitConfig().lambda_lines * frames, iterations=fit_iterations)
    rec = {"holdout_line": hold, "alpha_range": [float(np.min(truth.alpha)), float(np.max(truth.alpha))],
           "seconds": {"exact_inputs": time.perf_counter() - t0}}

    def decoded(ln, lp):
        """The pipeline's decode of the learned photos (as extraction forms the network's input) and fine-tuning."""
        meas = Measurements(grid, ln, W[:, upper], np.zeros(len(pos)), np.ones(len(pos), bool),
                            np.zeros((len(pos), 2)), np.zeros((len(pos), 2)), lp, P[:, upper])
        ft = finetune(model, decode(model, meas.learned, device=dev), ln, W[:, upper], ft_cfg)
        return decoded_lumitexels(model, ft.latent, precision=ft_cfg.precision)

    inputs = {"oracle": (lambda: m_true, lines, learned),
              "decoded": (lambda: decoded(lines, learned), lines, learned),
              "noisy_photos": (lambda: m_true, noisy_lines, noisy_learned),
              "decoded_noisy": (lambda: decoded(noisy_lines, noisy_learned), noisy_lines, noisy_learned)}
    for stage, (lumi, ln, lp) in inputs.items():
        sync()
        t = time.perf_counter()
        photos = np.concatenate([ln[:, keep], lp[:, 0]], axis=1)
        weights = np.concatenate([W[keep][:, upper], P[:, upper]], axis=0)
        fit = fit_ggx(rig, pos, lumi(), lines=photos, line_weights=weights, secondary=(lp[:, 1], P[:, upper]),
                      grid_shape=grid.shape, config=fit_cfg)
        sync()
        rec["seconds"][stage] = time.perf_counter() - t
        e = map_errors(truth, to_maps(fit, grid.shape, grid.size_mm))
        rec[stage] = {k: e[k]["median"] for k in ERRORS}
    return rec, check


def _pipeline(rig, capture, name: str, R: int, size_mm: float, dev: str) -> dict:
    """A capture folder of `rig` and sample `name` through the pipeline on the same grid, scored as validate
    scores it (reconstruction.evaluation.validation.evaluate: the maps' errors on the sample)."""
    import tempfile
    from pathlib import Path

    from twin.capture.session import CaptureSession

    from reconstruction.evaluation.validation import evaluate
    from reconstruction.pipeline import ReconstructConfig, reconstruct

    session = CaptureSession.open(capture)
    if session.sample != name or session.rig().digest() != rig.digest():
        raise ValueError(f"{capture}: a capture of sample {session.sample!r} on rig {session.rig().name!r}, not of "
                         f"{name!r} on {rig.name!r}")
    with tempfile.TemporaryDirectory(prefix="hemicube-fit-limits-") as work:
        t = time.perf_counter()
        recon = reconstruct(capture, Path(work) / "reconstruction",
                            ReconstructConfig(resolution=R, size_mm=size_mm, device=dev), progress=False)
        seconds = time.perf_counter() - t
        metrics, _ = evaluate(capture, recon, rig, dev)
    return {**{k: metrics["maps"][k]["median"] for k in ERRORS}, "seconds": seconds,
            "stage_seconds": dict(recon.timings)}
