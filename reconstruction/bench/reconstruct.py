"""`hemicube bench reconstruct`: seconds of the per-texel stages (decode, fine-tuning, GGX fitting) on
synthetic texels of a rig, extrapolated to a 1024^2 sample, with the reference's batching as the baseline.

The texels are drawn from the training distribution (reconstruction.network.data.sample_parameters, seeded); their
learned measurements and line measurements are rendered by the forward model, exactly (no photo noise).
The network is the rig's shipped one, a `hemicube train` run (--network), or else a seeded untrained network
of the rig's size: speed does not depend on the weights, accuracy does, so accuracy is not scored here
(`hemicube validate` scores it); the median per-texel losses are reported, to compare runs. Fine-tuning runs
three times: as `hemicube reconstruct` does (FinetuneConfig's defaults: the released code's iteration caps with its
early stopping, reference §4, in batches of 16,384 texels, TF32 products on CUDA), which gives the total; at the
paper's fixed iteration counts (100/50/200), the same work per texel whatever the data; and as the default in
float32, whose median per-texel objective the default's must match within 1% (the project's rule for a faster
precision, docs/performance.md; a check). The baseline is the paper's counts in batches of 100 texels (the released code's batching)
on a subset, per texel. The fit runs twice, with FitConfig's defaults (its Jacobian's projections in TF32 on CUDA)
and in float32, whose median per-texel loss the default's must match within 1% (the same rule; a check). The
device's used memory is polled throughout (twin.bench.PeakDeviceMemory: Warp's and
torch's allocations together).
"""
from __future__ import annotations

import time

import numpy as np

from reconstruction.bench.common import device_name, positive_int

SAMPLE_TEXELS = 1024 * 1024  # the paper's texture size (reference §6.1)
# The same-work check runs both batchings for a few Adam steps per pass. Over the timed runs' 350 steps the
# batch-size-dependent float32 rounding of the batched products (cuBLAS picks its kernels by the batch size)
# is amplified by the optimisation: on a GPU with an untrained network the two runs' lines ended several times
# the bound apart (docs/performance.md), while on the CPU they agree exactly. One step per pass compares the same
# computation (each pass's loss, gradients and update, per texel) before that amplification; the full runs'
# difference is reported. Why one: with the shipped compact paper network on a GPU, 1 / 1 / 1 steps agreed to a
# small fraction of the bound and 3 / 2 / 3 steps did not: a texel whose decoded lumitexel sits at the decoder's
# max(0, .) under a line meets the energy's sqrt where its slope is 500 (finetune's sqrt_eps), rounding decides
# which side it is on, and Adam's normalised steps carry that difference further with every step.
CHECK_ITERATIONS = (1, 1, 1)
FINETUNE_RTOL = 1e-3
FINETUNE_ATOL = 1e-4  # of the largest line value
PRECISION_RTOL = 0.01  # a faster precision's median per-texel objective within 1% of float32's


def _texels(rig, model, n: int, seed: int, device: str, exact: bool):
    """Learned (n, 2, K) and line (n, 64, 3) measurements, positions, the upper-LED line weights and, when
    `exact`, the exact RGB lumitexels (n, L_upper, 3) of n synthetic texels, in network units."""
    import torch

    import twin
    from twin.capture.pattern_sets import linear_lights

    from reconstruction.network.data import LUMITEXEL_SCALE, SamplingConfig, _generator, sample_parameters, synthesize

    p = sample_parameters(n, SamplingConfig(), rig, _generator(seed, "bench", 0))
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    W = linear_lights(rig).weights.astype(np.float32)
    learned, lines, lumi = [], [], []
    kw = dict(camera=next(iter(rig.cameras)), visibility=True, device=device)
    with torch.no_grad():
        for i in range(0, n, 8192):
            q = {k: v[i:i + 8192] for k, v in p.items()}
            views = torch.stack([synthesize(rig, q, c, device) for c in list(rig.cameras)[:2]], dim=1)
            learned.append(model.measure(views).cpu().numpy())
            args = {k: v.numpy() for k, v in q.items()}
            zero = np.zeros(len(args["position"]))
            lines.append(twin.measurements(rig, **args, patterns=W, transparency=zero, **kw)
                         * np.float32(LUMITEXEL_SCALE))
            if exact:
                lumi.append(twin.lumitexels(rig, **args, transparency=zero, **kw)[:, upper]
                            * np.float32(LUMITEXEL_SCALE))
    return (np.concatenate(learned), np.concatenate(lines), p["position"].numpy(), W[:, upper],
            np.concatenate(lumi) if exact else None)


def _normalise_encoder(model, learned: np.ndarray, device: str) -> None:
    """Give an untrained network the BatchNorm statistics of these measurements, as training would, so that its
    latents are of the size a trained encoder gives and fine-tuning stays finite (with the initial statistics,
    mean 0 and variance 1, the raw measurements passed through, the decoded exp overflowed and the fine-tuned
    latents ended non-finite: `latent72 must be finite`, on the CPU and on CUDA).
    The weights stay untrained: speed does not depend on them."""
    import torch

    bns = [m for m in model.encoder.modules() if isinstance(m, torch.nn.BatchNorm1d)]
    model.eval()  # no dropout, no measurement noise: only the BatchNorm layers collect statistics
    for m in bns:
        m.reset_running_stats()
        m.momentum = None  # a cumulative average over the chunks below
        m.train()
    x = torch.from_numpy(np.asarray(learned, np.float32)).to(device)
    with torch.no_grad():
        for i in range(0, len(x) - 1, 4096):  # chunks of >= 2 samples (BatchNorm needs two in training mode)
            model.encode(x[i:i + 4096])
    for m in bns:
        m.momentum = 0.1
    model.eval()


def bench_reconstruct(rig_name="paper", device="cuda", texels=16384, network=None, seed=0,
                      baseline_texels=1000) -> dict:
    import torch

    import twin

    from reconstruction.network.data import _wp_device
    from twin.bench import PeakDeviceMemory, finish_checks, same_work

    from reconstruction.stages.finetune import FinetuneConfig
    from reconstruction.stages.fitting import FitConfig
    from reconstruction.network.architecture import AcquisitionNet, count_parameters
    from reconstruction.pipeline import load_network
    from reconstruction.network.train import TrainConfig

    positive_int("texels", texels)
    rig = twin.load_rig(rig_name)
    dev = _wp_device(device)  # "cpu" or "cuda:N": one name for torch and Warp
    if network is not None:
        model, source = load_network(network, rig, dev), str(network)
    else:
        try:
            model, source = load_network("pretrained", rig, dev), "shipped"
        except ValueError:
            torch.manual_seed(seed)
            upper = int((~np.asarray(rig.is_bottom)).sum())
            model, source = AcquisitionNet(TrainConfig(rig=rig_name).network_config(upper)).to(dev).eval(), "untrained"
    # an untrained decoder's output is no lumitexel (exp overflows): the fit then takes the texels' exact
    # lumitexels, the same work per texel
    learned, lines, pos, W, exact = _texels(rig, model, texels, seed, dev, exact=source == "untrained")
    if source == "untrained":
        _normalise_encoder(model, learned, dev)

    if dev.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats(dev)
    with PeakDeviceMemory(dev) as memory:
        t_decode, runs, ft_seconds, baseline, check, fits = _timed_stages(model, rig, learned, lines, pos, W, exact,
                                                                          dev, baseline_texels)
    (fit, t_fit), (fit32, t_fit32) = fits["default"], fits["float32"]
    torch_peak = torch.cuda.max_memory_allocated(dev) / 2 ** 20 if dev.startswith("cuda") else None
    ft, t_finetune = runs["paper_counts"], ft_seconds["paper_counts"]
    nb, t_finetune_ref, full_diff = baseline
    scale = SAMPLE_TEXELS / texels
    per = {"decode": t_decode, "finetune": ft_seconds["default"], "fitting": t_fit}
    losses = {"finetune_default": _median_line_energy(model, runs["default"].latent, lines, W),
              "finetune_paper_counts": _median_line_energy(model, ft.latent, lines, W),
              "finetune_default_float32": _median_line_energy(model, runs["default_float32"].latent, lines, W),
              "fitting": float(np.median(fit.info["texel_loss"])),
              "fitting_float32": float(np.median(fit32.info["texel_loss"]))}
    # the rule for a faster precision: the median per-texel objective within 1% of float32's
    precision = same_work("finetune_default_vs_float32_median_objective", [losses["finetune_default"]],
                          [losses["finetune_default_float32"]], rtol=PRECISION_RTOL)
    fit_precision = same_work("fitting_default_vs_float32_median_loss", [losses["fitting"]],
                              [losses["fitting_float32"]], rtol=PRECISION_RTOL)
    return finish_checks({
        "bench": "reconstruct", "rig": rig.name, "device": device_name(dev), "texels": texels, "network": source,
        "fitting_target": "decoded" if exact is None else "exact lumitexels",
        "network_parameters": count_parameters(model),
        "finetune_iterations": runs["default"].iterations, "fit_info": {k: v for k, v in fit.info.items()
                                                                        if isinstance(v, (int, float, str))},
        "seconds": per, "seconds_per_1024sq_extrapolated": {k: v * scale for k, v in per.items()},
        "total_per_1024sq_extrapolated_s": sum(per.values()) * scale,
        "finetune_paper_counts": {"seconds": t_finetune, "iterations": ft.iterations,
                                  "total_per_1024sq_extrapolated_s": (t_decode + t_finetune + t_fit) * scale},
        "finetune_precision": FinetuneConfig().precision,
        "finetune_float32": {"seconds": ft_seconds["default_float32"], "iterations": runs["default_float32"].iterations,
                             "speedup_of_default": ft_seconds["default_float32"] / ft_seconds["default"]},
        "fit_precision": FitConfig().precision,
        "fitting_float32": {"seconds": t_fit32, "speedup_of_default": t_fit32 / t_fit},
        "median_texel_loss": losses,
        "peak_device_memory_mib": memory.peak_mib,
        "torch_max_allocated_mib": torch_peak,
        "baseline_finetune_batch100": {"texels": nb, "seconds": t_finetune_ref,
                                       "per_texel_ratio_vs_batched": (t_finetune_ref / nb) / (t_finetune / texels),
                                       "full_passes_max_diff_of_max": full_diff,
                                       "check_iterations": list(CHECK_ITERATIONS)},
    }, [check, precision, fit_precision])


def _timed_stages(model, rig, learned, lines, pos, W, exact, dev: str, baseline_texels: int):
    """bench_reconstruct's timed stages: decode; fine-tuning as `hemicube reconstruct` runs it and at the paper's
    counts; the batch-of-100 baseline and its check; the fit of the default run's latents."""
    import torch

    from twin.bench import same_work

    from reconstruction.stages.finetune import (PRECISIONS, FinetuneConfig, _sync, decoded_lumitexels, finetune,
                                                simulate_lines)
    from reconstruction.stages.fitting import FitConfig, fit_ggx
    from reconstruction.stages.latents import decode

    def sync():  # timings must include the queued GPU work
        _sync(torch.device(dev))

    t = time.perf_counter()
    z = decode(model, learned, device=dev)
    sync()
    t_decode = time.perf_counter() - t
    # warm-up, untimed: the first fine-tuning of a process pays cuBLAS's and the kernels' first loads (more than the
    # pass itself on a GPU), which would count against whichever run went first
    b = FinetuneConfig().batch or len(z)  # one batch of the timed runs' size
    for precision in PRECISIONS:
        finetune(model, z[:b], lines[:b], W, FinetuneConfig(iterations=(1, 1, 1), holdout=(0,), device=dev,
                                                             precision=precision))
    sync()
    runs, ft_seconds = {}, {}
    for name, cfg in (("default", FinetuneConfig(holdout=(0,), device=dev)),
                      ("paper_counts", FinetuneConfig(source="paper", holdout=(0,), device=dev)),
                      ("default_float32", FinetuneConfig(holdout=(0,), device=dev, precision="float32"))):
        t = time.perf_counter()
        runs[name] = finetune(model, z, lines, W, cfg)
        sync()
        ft_seconds[name] = time.perf_counter() - t
    nb = min(baseline_texels, len(z))
    t = time.perf_counter()
    ft_ref = finetune(model, z[:nb], lines[:nb], W, FinetuneConfig(source="paper", holdout=(0,), device=dev,
                                                                    batch=100))
    sync()
    t_finetune_ref = time.perf_counter() - t
    # Same work: without early stopping a texel's optimisation does not depend on its batch (finetune's
    # docstring), so both batchings must render the same line measurements from their latents, after a few
    # steps (CHECK_ITERATIONS); after the timed runs' full passes the difference is reported, not checked. In
    # float32, the precision its bound was measured in: the check is of the batching, the precision has its own
    short = [finetune(model, z[:nb], lines[:nb], W, FinetuneConfig(source="paper", holdout=(0,), device=dev,
                                                                  iterations=CHECK_ITERATIONS, batch=b,
                                                                  precision="float32"))
             for b in (100, None)]
    check = same_work("finetune_batch100_vs_batched_lines_few_steps", *(simulate_lines(model, f.latent, W)
                                                                        for f in short),
                      rtol=FINETUNE_RTOL, atol=FINETUNE_ATOL)
    full_a = simulate_lines(model, ft_ref.latent, W)
    full_b = simulate_lines(model, runs["paper_counts"].latent[:nb], W)
    full_diff = float(np.max(np.abs(full_a - full_b)) / max(float(np.max(np.abs(full_b))), 1e-30))
    # each precision's fit of the same latents, decoded in that precision as `hemicube reconstruct` decodes them
    lumi = {p: exact if exact is not None else decoded_lumitexels(model, runs["default"].latent, precision=p)
            for p in PRECISIONS}
    few = min(64, len(pos))  # warm-up of both precisions, untimed, as fine-tuning's above
    for precision in PRECISIONS:
        m = lumi[precision]
        fit_ggx(rig, pos[:few], m if callable(m) else m[:few], lines=lines[:few], line_weights=W,
                config=FitConfig(device=dev, iterations=1, precision=precision))
    fits = {}
    for name, cfg in (("default", FitConfig(device=dev)), ("float32", FitConfig(device=dev, precision="float32"))):
        t = time.perf_counter()
        fit = fit_ggx(rig, pos, lumi[cfg.precision], lines=lines, line_weights=W, config=cfg)
        sync()
        fits[name] = (fit, time.perf_counter() - t)
    return t_decode, runs, ft_seconds, (nb, t_finetune_ref, full_diff), check, fits


def _median_line_energy(model, latent, lines, W) -> float:
    """The median over the texels of the fine-tuning objective (reference §4's sum over the lines and channels of
    (sqrt(M_sim) - sqrt(M_photo))^2, finetune's sqrt_eps) at a latent, the held-out line 0 left out as in the run."""
    from reconstruction.stages.finetune import FinetuneConfig, simulate_lines

    eps = FinetuneConfig().sqrt_eps
    sim = simulate_lines(model, latent, W)[:, 1:]
    e = (np.sqrt(sim + eps) - np.sqrt(np.maximum(lines[:, 1:], 0) + eps)) ** 2
    return float(np.median(e.sum(axis=(1, 2))))
