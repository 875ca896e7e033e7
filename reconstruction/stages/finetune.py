"""Three-pass fine-tuning of the per-texel latents against the linear-light photos (paper §7.1, reference §4),
batched over all texels.

    res = finetune(model, latent, lines, line_weights, FinetuneConfig(holdout=(31,)))
    res.latent            # (N, 72) [a_R(8), a_G(8), a_B(8), s(48)], the pass-3 latent
    simulate_lines(model, res.latent, line_weights)   # (N, K, 3) M_sim, also for the validation renders
    latent_for_lumitexels(model, res.latent, m, steps)  # the latent nearest known lumitexels m (Eq. 3): a ceiling

Inputs. `latent` (N, 56) = the network's grey latent [a(8), s(48)] (reference §3.2 output order);
`lines` (N, K, 3) = each texel's K linear-light photo measurements, primary view, in network units (the
units the decoder predicts: upper-LED lumitexels times reconstruction.network.data.LUMITEXEL_SCALE);
`line_weights` (K, L_upper, 3) in [0, 1] = the linear lights' relative drive on the UPPER LEDs (the
lumitexel's LEDs; `twin.capture.pattern_sets.linear_lights(rig).weights[:, upper]`).

Objective (reference §4, the same in every pass): a SUM over the batch's texels, lines and channels

    E = sum_n sum_k sum_c ( sqrt(M_sim[n,k,c] + eps) - sqrt(max(M_photo[n,k,c], 0) + eps) )^2
    M_sim[n,k,c] = sum_l W[k,l,c'] max(0, decoder(latent_c)[l])       (decoder output exp(.) - 1, §3.3)

* Noisy photos (ours): a measured line value can be slightly negative (dark frame subtracted from noise);
  it is clamped at 0 before the square root, as the simulated value is >= 0 by construction.
* eps (ours, `FinetuneConfig.sqrt_eps`, default 1e-6 network units, i.e. ~1e-6 of a white Lambertian
  texel under its nearest LED; a line of LEDs reads ~1-10): d sqrt(M)/dM is infinite at M = 0, which a
  texel whose decoded lumitexel is zero under a line hits exactly (the decoder's max(0, .)); eps inside
  BOTH square roots keeps the gradient finite (at most 1 / (2 sqrt(eps)) = 500) and leaves E = 0 when the
  simulation matches the photo.

The passes (reference §4 table; "per the table" also for the pattern channel):

    pass   variables                          init               target             W channel   lr
    1      grey 56-D [a, s]                   network latent     mean_c photo       W[..., 0]   0.02
    2      a_c (8-D) for c = R, G, B in turn  a_c = a_1, s = s_1  photo[..., c]      W[..., 0]   0.05
           (s fixed at s_1)
    3      72-D [a_R, a_G, a_B, s]            pass-2 result      photo (RGB)        W[..., c]   0.02

Outputs per pass as (N, 72) (reference §4 "output" row): pass0 = network latent as [a, a, a, s], pass1 =
[a_1, a_1, a_1, s_1], pass2 = [a_R, a_G, a_B, s_1], pass3 = [a_R, a_G, a_B, s_3].

Optimiser: a fresh Adam (betas 0.9 / 0.999, torch's eps 1e-8) for every batch and pass, and in pass 2 for
every channel (each channel is its own optimisation, "one channel after another"). An iterate is updated,
then the early-stopping rule is checked on the objective values seen so far: E_s is the objective at the
iterate BEFORE update s (s = 0, 1, ...); when the rule fires at s, s + 1 updates have been made and the
latent after the last update is returned (not the best one seen).

Iterations (`FinetuneConfig.source`):
* "code" (default, the released scripts): caps 500 / 50 / 500 with early stopping (`EARLY_STOP`):
    pass 1: r_s = 100 E_s / E_{s-10} for s >= 10; stop when the mean of the last 5 r (or of all of them
            while fewer than 5 exist: the table states no minimum count for pass 1) exceeds 95;
    pass 2: r_s = 100 E_s / E_{s-5} for s >= 5; stop when >= 5 values exist and the mean of the last 5 > 95;
    pass 3: r_s = 100 E_s / E_{s-10} for s >= 10; stop when >= 10 values exist, the mean of the last 5 > 98
            and s > 75.
  (Ours: a ratio with E_{s-lag} = 0 is 100 when E_s = 0 too and +inf otherwise.)
* "paper" (paper §7.1): exactly 100 / 50 / 200 iterations, no early stopping.

Batching (ours: all texels are optimised together in large batches on the GPU, not the reference's 100 at a time).
Batches of `batch` texels (16,384 by default; None: all N texels as one batch). Each texel's gradient depends
only on its own latent (the decoder is evaluated in eval mode: no dropout, no BatchNorm) and Adam is element-wise,
so without early stopping a texel's result does not depend on its batch (up to float rounding in batched matrix
products). WITH early stopping it does: the objective is the batch SUM (as in the reference, whose batches of
100 stop together), so the stopping ratio is the batch's, which stops when the batch as a whole stops improving.
Memory: backpropagation keeps the decoder's activations, about 10 GiB for 16,384 texels with the shipped compact
paper-rig network (docs/performance.md), which is why the default batch bounds it.

Hold-out (paper §7.1 holds out 1 of 64 line photos; the released code uses all 64, reference §9.7):
`holdout` line indices are left out of the objective and of nothing else (simulate_lines renders every line).

Deterministic: no random draws. The model is used in eval mode with its parameters frozen during the call
(its mode and requires_grad flags are restored afterwards).
"""
from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch

from reconstruction.network.architecture import AcquisitionNet, _is_int, _is_real

__all__ = ["FinetuneConfig", "FinetuneResult", "EarlyStopRule", "EARLY_STOP", "SOURCES", "PASSES", "finetune",
           "simulate_lines", "decode_rgb", "decoded_lumitexels", "grey_to_rgb", "latent_for_lumitexels"]

PASSES = ("pass0", "pass1", "pass2", "pass3")
CHANNELS = "RGB"
# iteration counts per pass (1, 2, 3): the released scripts' caps (reference §4) and the paper's counts (§7.1)
SOURCES = {"code": (500, 50, 500), "paper": (100, 50, 200)}
PRECISIONS = ("tf32", "float32")  # FinetuneConfig.precision


@dataclass(frozen=True)
class EarlyStopRule:
    """The released scripts' stopping rule (reference §4 table): ratios r_s = 100 E_s / E_{s-lag} for
    s >= lag; stop at step s when at least `min_ratios` ratios exist, s >= `min_step`, and the mean of the
    last `window` ratios (all of them while fewer exist) exceeds `threshold`."""

    lag: int
    threshold: float
    window: int = 5
    min_ratios: int = 1
    min_step: int = 0

    def ratios(self, losses) -> list[float]:
        e = [float(v) for v in losses]
        out = []
        for s in range(self.lag, len(e)):
            prev = e[s - self.lag]
            out.append(100.0 * e[s] / prev if prev > 0 else (100.0 if e[s] == 0 else math.inf))
        return out

    def should_stop(self, losses) -> bool:
        """Whether the loop stops after the step whose objective is losses[-1] (losses = E_0 .. E_s)."""
        r = self.ratios(losses)
        if not r or len(r) < self.min_ratios or len(losses) - 1 < self.min_step:
            return False
        return float(np.mean(r[-self.window:])) > self.threshold

    def stop_step(self, losses) -> int | None:
        """The first s at which the rule fires on losses[:s + 1], or None."""
        for s in range(len(losses)):
            if self.should_stop(losses[:s + 1]):
                return s
        return None


# reference §4 table, passes 1, 2, 3 ("s > 75" is min_step 76)
EARLY_STOP = (EarlyStopRule(lag=10, threshold=95.0),
              EarlyStopRule(lag=5, threshold=95.0, min_ratios=5),
              EarlyStopRule(lag=10, threshold=98.0, min_ratios=10, min_step=76))


@dataclass(frozen=True)
class FinetuneConfig:
    """Settings of the three passes.

    source          "code": caps 500/50/500 with the released early-stopping rules (reference §4);
                    "paper": exactly 100/50/200 iterations, no early stopping (paper §7.1).
    iterations      override of the per-pass iteration caps (3 ints >= 0); None: from `source`.
    lrs             Adam learning rates per pass: 0.02 / 0.05 / 0.02 (paper and code agree).
    early_stopping  None: from `source` (on for "code", off for "paper").
    batch           texels per batch (large batches, not the reference's 100); None: all at once. The default
                    bounds the memory: the shipped paper-rig network allocates about 10 GiB for 16,384 texels, four
                    times that for 65,536 in one batch (docs/performance.md), and a larger batch gains nothing once
                    the GPU is full.
    holdout         line indices left out of the objective (the paper holds out 1 of 64; code: none).
    sqrt_eps        eps inside the square roots of the objective, network units (ours; module docstring).
    device          torch device of the optimisation ("cpu", "cuda", "cuda:1", ...); the model must be on it.
    precision       the matrix products of the passes on a CUDA device (mixed precision where it measurably does
                    not hurt): "tf32" (the tensor cores' 10-bit mantissa, float32 range and sums) or "float32".
                    With the shipped paper-rig network and these defaults, TF32 runs the passes faster with the
                    median per-texel pass-3 objective 0.31% above float32's, inside 1% (docs/performance.md; at
                    the paper's fixed 350 steps, source "paper", it is 1.5%: use float32 there). On the CPU every
                    product is float32 whatever the setting (the same bits). Only fine-tuning: the decoded
                    lumitexels the fit reads stay float32 (the fit has its own FitConfig.precision).
    """

    source: str = "code"
    iterations: tuple | None = None
    lrs: tuple = (0.02, 0.05, 0.02)
    early_stopping: bool | None = None
    batch: int | None = 16384
    holdout: tuple[int, ...] = ()
    sqrt_eps: float = 1e-6
    device: str = "cpu"
    precision: str = "tf32"

    def __post_init__(self):
        if self.source not in SOURCES:
            raise ValueError(f"FinetuneConfig.source must be one of {tuple(SOURCES)}, got {self.source!r}")
        if self.iterations is not None:
            it = tuple(self.iterations)
            if len(it) != 3 or not all(_is_int(v) and v >= 0 for v in it):
                raise ValueError(f"FinetuneConfig.iterations must be 3 integers >= 0 (passes 1, 2, 3) or None, "
                                 f"got {self.iterations!r}")
            object.__setattr__(self, "iterations", tuple(int(v) for v in it))
        lrs = tuple(self.lrs)
        if len(lrs) != 3 or not all(_is_real(v) and math.isfinite(v) and v > 0 for v in lrs):
            raise ValueError(f"FinetuneConfig.lrs must be 3 finite learning rates > 0, got {self.lrs!r}")
        object.__setattr__(self, "lrs", tuple(float(v) for v in lrs))
        if self.early_stopping is not None and not isinstance(self.early_stopping, (bool, np.bool_)):
            raise ValueError(f"FinetuneConfig.early_stopping must be a bool or None, got {self.early_stopping!r}")
        if self.batch is not None and not (_is_int(self.batch) and self.batch >= 1):
            raise ValueError(f"FinetuneConfig.batch must be a positive integer or None, got {self.batch!r}")
        hold = tuple(self.holdout)
        if not all(_is_int(h) and h >= 0 for h in hold) or len(set(hold)) != len(hold):
            raise ValueError(f"FinetuneConfig.holdout must be distinct line indices >= 0, got {self.holdout!r}")
        object.__setattr__(self, "holdout", tuple(sorted(int(h) for h in hold)))
        if self.precision not in PRECISIONS:
            raise ValueError(f"FinetuneConfig.precision must be one of {PRECISIONS}, got {self.precision!r}")
        if not (_is_real(self.sqrt_eps) and math.isfinite(self.sqrt_eps) and self.sqrt_eps > 0):
            raise ValueError(f"FinetuneConfig.sqrt_eps must be a finite number > 0, got {self.sqrt_eps!r}")
        try:
            torch.device(self.device)
        except (RuntimeError, TypeError) as e:
            raise ValueError(f"FinetuneConfig.device is not a torch device: {self.device!r}") from e

    @property
    def caps(self) -> tuple[int, int, int]:
        return self.iterations if self.iterations is not None else SOURCES[self.source]

    @property
    def stopping(self) -> bool:
        return (self.source == "code") if self.early_stopping is None else bool(self.early_stopping)


@dataclass
class FinetuneResult:
    """latent: (N, 72) float32 [a_R, a_G, a_B, s], the pass-3 latent.
    passes: "pass0" .. "pass3" -> (N, 72) float32 latents (module docstring).
    history: "pass1" .. "pass3" -> one list per optimisation run of the objective values E_0, E_1, ...
        (the batch sums before each update); a run is one batch in passes 1 and 3, one (batch, channel) in
        pass 2, ordered batch by batch (and R, G, B within a batch).
    iterations: "pass1" .. "pass3" -> updates made per run (same order as history).
    objective: "pass1" .. "pass3" -> (before, after): the pass's objective summed over ALL texels at its
        initial and final latents (pass 2: summed over the three channels).
    seconds: "pass1" .. "pass3" -> wall time of each pass (all batches; pass 0 is a copy).
    """

    latent: np.ndarray
    passes: dict
    history: dict
    iterations: dict
    objective: dict
    seconds: dict
    config: FinetuneConfig = field(default_factory=FinetuneConfig)


# ------------------------------------------------------------------------------------------------ inputs


def _as_float_tensor(name: str, x) -> torch.Tensor:
    try:
        t = torch.as_tensor(np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float32))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a numeric array, got {type(x).__name__}") from e
    return t


def _check_finite(name: str, t: torch.Tensor) -> None:
    bad = ~torch.isfinite(t)
    if bad.any():
        idx = tuple(int(i) for i in torch.nonzero(bad)[0])
        raise ValueError(f"{name} must be finite: {int(bad.sum())} non-finite value(s), the first at index {idx}")


def _check_model(model) -> tuple[int, int, int]:
    if not isinstance(model, AcquisitionNet):
        raise ValueError(f"model must be an AcquisitionNet, got {type(model).__name__}")
    c = model.config
    return c.albedo_dim, c.shape_dim, c.num_leds


def _check_weights(line_weights, num_leds: int) -> torch.Tensor:
    w = _as_float_tensor("line_weights", line_weights)
    if w.ndim != 3 or w.shape[1:] != (num_leds, 3) or w.shape[0] < 1:
        raise ValueError(f"line_weights must have shape (K, {num_leds}, 3) (K lines x the model's upper LEDs x "
                         f"RGB), got {tuple(w.shape)}")
    _check_finite("line_weights", w)
    if w.min() < 0 or w.max() > 1:
        raise ValueError(f"line_weights must lie in [0, 1] (relative LED drive), got [{float(w.min())}, "
                         f"{float(w.max())}]")
    return w


def _model_device(model) -> torch.device:
    return next(model.parameters()).device


@contextmanager
def _frozen(model):
    """Eval mode and no parameter gradients for the duration; the caller's flags are restored after."""
    training = model.training
    flags = [p.requires_grad for p in model.parameters()]
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    try:
        yield model
    finally:
        for p, f in zip(model.parameters(), flags):
            p.requires_grad_(f)
        model.train(training)


def grey_to_rgb(latent: np.ndarray, albedo_dim: int = 8) -> np.ndarray:
    """(N, ad + sd) grey latent [a, s] -> (N, 3 ad + sd) RGB latent [a, a, a, s] (reference §4 pass0)."""
    a, s = latent[:, :albedo_dim], latent[:, albedo_dim:]
    return np.concatenate([a, a, a, s], axis=1)


# ------------------------------------------------------------------------------------------------ simulation


def _decode_rgb(model, x72: torch.Tensor, ad: int) -> torch.Tensor:
    """(B, 3 ad + sd) -> (3, B, L) lumitexels: channel c decodes (a_c, s) (reference §3.3)."""
    b = x72.shape[0]
    albedo = x72[:, :3 * ad].reshape(b, 3, ad).transpose(0, 1).reshape(3 * b, ad)
    shape = x72[:, 3 * ad:].repeat(3, 1)
    return model.decode_lumitexel(albedo, shape).reshape(3, b, -1)


def _sim_rgb(model, x72: torch.Tensor, w_lkc: torch.Tensor, ad: int) -> torch.Tensor:
    """M_sim (B, K, 3) = sum_l W[k, l, c] m_c[l]; w_lkc is the weights as (3, L, K)."""
    return torch.bmm(_decode_rgb(model, x72, ad), w_lkc).permute(1, 2, 0)


def simulate_lines(model, latent72, line_weights, batch: int | None = 16384) -> np.ndarray:
    """M_sim (N, K, 3) float32 of RGB latents (N, 3 ad + sd) under line_weights (K, L_upper, 3): channel c
    decodes (a_c, s) and is weighted by W[..., c] (reference §4 pass 3). Runs on the model's device, in
    eval mode, `batch` texels at a time (None: all; the default bounds the decoder's memory as decode_rgb's
    does: 262,144 paper-rig texels at once need more than a GPU's memory)."""
    ad, _, num_leds = _check_model(model)
    x = _checked_latent72(model, latent72)
    w = _check_weights(line_weights, num_leds)
    if batch is not None and not (_is_int(batch) and batch >= 1):
        raise ValueError(f"batch must be a positive integer or None, got {batch!r}")
    dev = _model_device(model)
    w_lkc = w.permute(2, 1, 0).contiguous().to(dev)
    n = x.shape[0]
    step = n if batch is None else int(batch)
    out = np.empty((n, w.shape[0], 3), dtype=np.float32)
    with _frozen(model), torch.no_grad():
        for i in range(0, n, max(step, 1)):
            out[i:i + step] = _sim_rgb(model, x[i:i + step].to(dev), w_lkc, ad).cpu().numpy()
    return out


def decode_rgb(model, latent72, batch: int = 16384, to_numpy: bool = True):
    """(N, L_upper, 3) float32 RGB lumitexels (network units) of RGB latents (N, 3 ad + sd): channel c
    decodes (a_c, s) (reference §3.3), on the model's device, in eval mode, `batch` texels at a time (the
    paper rig's 12,288 LEDs: 2.4 GB of output a batch, and the decoder's activations). A numpy array, or with
    to_numpy=False a tensor on the model's device. For the fit, decoded_lumitexels decodes chunk by chunk
    instead: all texels' lumitexels at once are 150 GB for a 1024^2 paper-rig sample."""
    x = _checked_latent72(model, latent72)
    out = _decode_rows(model, x, batch, "cpu" if to_numpy else _model_device(model))
    _release(_model_device(model))
    return out.numpy() if to_numpy else out


def decoded_lumitexels(model, latent72, batch: int = 16384, max_bytes: int = 2 ** 31, precision: str = "float32"):
    """The RGB lumitexels (decode_rgb) for reconstruction.stages.fitting.fit_ggx, on the model's device: decoded at once
    where they take at most `max_bytes` (a mini-rig grid: 11 MB), else a lumitexel source, a function of texel
    indices (a tensor) that decodes those texels when the fit asks for a chunk, so that only a chunk's lumitexels
    exist at a time (a 1024^2 paper-rig sample's are 150 GB). The latents are checked and moved to the
    device once; a chunk decoded again costs a third of one fine-tuning step (a forward pass, no backward).
    `precision` (PRECISIONS): the decoder's matrix products on a CUDA device, the fine-tuning's
    (FinetuneConfig.precision), so that the fit's targets are what the fine-tuned latents decode to where they were
    fitted; "tf32" halves the time of a decode of the paper rig's 12,288 LEDs (docs/performance.md;
    log1p(m) within 2.6e-3, RMS 5.7e-5; the decoder's own error is ~0.05 RMS). The CPU's are float32 either way."""
    from twin.optics.torch_ops import tf32_products  # Warp's kernels load with it: not at this module's import

    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    x = _checked_latent72(model, latent72).to(_model_device(model))

    def source(idx: torch.Tensor | None = None) -> torch.Tensor:
        with tf32_products(precision == "tf32"):
            return _decode_rows(model, x if idx is None else x[idx.to(x.device)], batch, x.device)

    return source() if x.shape[0] * _check_model(model)[2] * 3 * 4 <= max_bytes else source


def latent_for_lumitexels(model, latent72, lumitexels, steps: int, lr: float = 0.02,
                          batch: int = 4096) -> tuple[np.ndarray, float, float]:
    """The RGB latents (N, 3 ad + sd) that Adam (lr) reaches in `steps` steps from latent72 when it minimises paper
    Eq. 3 between their decode (decode_rgb) and the given lumitexels (N, L_upper, 3): the sum over the texels, LEDs
    and channels of (log(1 + m_hat) - log(1 + m))^2. No photos: as near as this search takes the decoder to each
    texel's lumitexel, the decoder's ceiling (docs/accuracy.md). `batch` texels at a time: a texel's term depends on
    its own latent only, and Adam's update is elementwise, so the batches do not change the result. Returns (the
    latents, the objective at the start, at the last step)."""
    ad, _, num_leds = _check_model(model)
    x = _checked_latent72(model, latent72)
    m = _as_float_tensor("lumitexels", lumitexels)
    if m.shape != (x.shape[0], num_leds, 3):
        raise ValueError(f"lumitexels must have shape ({x.shape[0]}, {num_leds}, 3), got {tuple(m.shape)}")
    dev = _model_device(model)
    out, first, last = np.empty(tuple(x.shape), np.float32), 0.0, 0.0
    with _frozen(model), torch.enable_grad():
        for i in range(0, x.shape[0], batch):
            target = torch.log1p(m[i:i + batch].to(dev).permute(2, 0, 1))  # (3, B, L), as _decode_rgb's

            def energy(z):
                return (torch.log1p(_decode_rgb(model, z, ad)) - target).square().sum()

            z, hist, _ = _adam_run(x[i:i + batch].to(dev), energy, steps, lr, None)
            out[i:i + batch] = z.cpu().numpy()
            first, last = first + hist[0], last + hist[-1]
    return out, first, last


def _checked_latent72(model, latent72) -> torch.Tensor:
    ad, sd, _ = _check_model(model)
    x = _as_float_tensor("latent72", latent72)
    if x.ndim != 2 or x.shape[1] != 3 * ad + sd:
        raise ValueError(f"latent72 must have shape (N, {3 * ad + sd}), got {tuple(x.shape)}")
    _check_finite("latent72", x)
    return x


def _decode_rows(model, x: torch.Tensor, batch: int, device) -> torch.Tensor:
    """decode_rgb's lumitexels of checked latents x, `batch` texels at a time, into a tensor on `device`."""
    ad, _, num_leds = _check_model(model)
    dev = _model_device(model)
    out = torch.empty((x.shape[0], num_leds, 3), dtype=torch.float32, device=device)
    with _frozen(model), torch.no_grad():
        for i in range(0, x.shape[0], batch):
            out[i:i + batch] = _decode_rgb(model, x[i:i + batch].to(dev), ad).permute(1, 2, 0)
    return out


# ------------------------------------------------------------------------------------------------ objective


def _target_sqrt(photo: torch.Tensor, eps: float) -> torch.Tensor:
    return torch.sqrt(photo.clamp_min(0.0) + eps)


def _energy(sim: torch.Tensor, target_sqrt: torch.Tensor, eps: float) -> torch.Tensor:
    """reference §4: sum of (sqrt(M_sim) - sqrt(M_photo))^2 over everything (MSE, reduction = sum)."""
    return (torch.sqrt(sim + eps) - target_sqrt).square().sum()


class _Problem:
    """The three objectives on one batch (device tensors); holdout lines already removed."""

    def __init__(self, model, lines: torch.Tensor, w: torch.Tensor, ad: int, eps: float):
        self.model, self.ad, self.eps = model, ad, eps
        self.w0 = w[..., 0].T.contiguous()              # (L, K): W[..., 0], passes 1 and 2
        self.w_lkc = w.permute(2, 1, 0).contiguous()     # (3, L, K): W[..., c], pass 3
        self.grey_t = _target_sqrt(lines.mean(dim=2), eps)   # pass 1: mean over RGB of the photos
        self.rgb_t = _target_sqrt(lines, eps)                # passes 2 (one channel) and 3

    def e1(self, x56: torch.Tensor) -> torch.Tensor:
        m = self.model.decode_lumitexel(x56[:, :self.ad], x56[:, self.ad:])
        return _energy(m @ self.w0, self.grey_t, self.eps)

    def e2(self, a: torch.Tensor, s: torch.Tensor, c: int) -> torch.Tensor:
        m = self.model.decode_lumitexel(a, s)
        return _energy(m @ self.w0, self.rgb_t[..., c], self.eps)

    def e3(self, x72: torch.Tensor) -> torch.Tensor:
        return _energy(_sim_rgb(self.model, x72, self.w_lkc, self.ad), self.rgb_t, self.eps)


def _adam_run(x0: torch.Tensor, energy, steps: int, lr: float, rule: EarlyStopRule | None):
    """A fresh Adam on a copy of x0; returns (final x, objective values E_0.., updates made)."""
    x = x0.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=lr, betas=(0.9, 0.999))
    hist: list = []
    done = 0
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        e = energy(x)
        e.backward()
        opt.step()
        done += 1
        if rule is None:
            hist.append(e.detach())  # no host sync per step when nothing reads the value
        else:
            hist.append(float(e.detach()))
            if rule.should_stop(hist):
                break
    return x.detach(), [float(v) for v in hist], done


def _resolve(device: str) -> torch.device:
    """torch.device with the current CUDA index filled in ("cuda" -> "cuda:0"), comparable with a tensor's."""
    d = torch.device(device)
    if d.type == "cuda" and d.index is None and torch.cuda.is_available():
        d = torch.device("cuda", torch.cuda.current_device())
    return d


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _release(device: torch.device) -> None:
    """Give torch's cached GPU blocks back to the device at the end of a stage: the decoder's activations are
    sized unlike the next stage's tensors (the fit's, Warp's), which otherwise come on top of the cache
    (the device's used memory counts, and the cache held twice what torch ever held at once in a paper-rig bench;
    docs/performance.md)."""
    if device.type == "cuda":
        torch.cuda.empty_cache()


# ------------------------------------------------------------------------------------------------ finetune


# how often fine-tuning saves its state to a checkpoint (ours): a 1024^2 paper-rig sample fine-tunes for ~6 minutes
# (docs/accuracy.md), a save of its latents (200 floats a texel) takes about a second there
CHECKPOINT_SECONDS = 60.0


def _resumed(checkpoint, n: int, ad: int, sd: int, runs: int) -> dict | None:
    """The state a killed fine-tuning saved to `checkpoint` (finetune), checked against this problem, or None."""
    state = checkpoint.load() if checkpoint is not None else None
    if state is None:
        return None
    shapes = {"grey1": (n, ad + sd), "rgb2": (n, 3 * ad + sd), "rgb3": (n, 3 * ad + sd)}
    if (any(np.shape(state.get(k)) != v for k, v in shapes.items()) or not 0 <= int(state.get("done", -1)) <= runs
            or not all(np.isfinite(state[k]).all() for k in shapes)):
        raise ValueError("the fine-tuning checkpoint does not belong to this fine-tuning (another texel count or "
                         "batch size, or non-finite latents); remove it to start again")
    return state


def finetune(model, latent, lines, line_weights, config: FinetuneConfig = FinetuneConfig(),
             checkpoint=None, progress: bool = False) -> FinetuneResult:
    """The three fine-tuning passes (module docstring) of N texels.

    model: an AcquisitionNet on config.device (its decoder is used, in eval mode, parameters frozen);
    latent: (N, ad + sd) grey network latent [a, s]; lines: (N, K, 3) linear-light photo measurements in
    network units (finite; slightly negative values allowed, clamped at 0); line_weights: (K, L_upper, 3)
    in [0, 1]; checkpoint: None, or an object with load() -> dict | None and save(dict) where the passes keep their
    state as they go (the latents so far, at most every CHECKPOINT_SECONDS and at the end of each pass): given the
    state a killed run saved, the passes go on from the last batch it finished and end with the same latents as a
    run that was never stopped (each batch's optimisation depends on its own texels only); progress: a bar over the
    passes' batches on a terminal (twin.progress). Returns a FinetuneResult (numpy float32 latents)."""
    if not isinstance(config, FinetuneConfig):
        raise ValueError(f"config must be a FinetuneConfig, got {type(config).__name__}")
    ad, sd, num_leds = _check_model(model)
    dev = _resolve(config.device)
    if _model_device(model) != dev:
        raise ValueError(f"model is on {_model_device(model)} but FinetuneConfig.device is {config.device!r}; "
                         "move the model there first (model.to(device))")
    z = _as_float_tensor("latent", latent)
    if z.ndim != 2 or z.shape[1] != ad + sd or z.shape[0] < 1:
        raise ValueError(f"latent must have shape (N, {ad + sd}) (the grey network latent [a({ad}), s({sd})]), "
                         f"got {tuple(z.shape)}")
    _check_finite("latent", z)
    y = _as_float_tensor("lines", lines)
    w = _check_weights(line_weights, num_leds)
    k = w.shape[0]
    if y.ndim != 3 or y.shape != (z.shape[0], k, 3):
        raise ValueError(f"lines must have shape (N, K, 3) = ({z.shape[0]}, {k}, 3) (N from latent, K from "
                         f"line_weights), got {tuple(y.shape)}")
    _check_finite("lines", y)
    if config.holdout and config.holdout[-1] >= k:
        raise ValueError(f"FinetuneConfig.holdout index {config.holdout[-1]} is out of range for {k} lines")
    keep = torch.tensor([i for i in range(k) if i not in config.holdout], dtype=torch.int64)
    if keep.numel() == 0:
        raise ValueError("FinetuneConfig.holdout leaves no line in the objective")
    y, w = y[:, keep], w[keep]

    n = z.shape[0]
    step = n if config.batch is None else config.batch
    slices = [slice(i, min(i + step, n)) for i in range(0, n, step)]
    caps, lrs = config.caps, config.lrs
    rules = EARLY_STOP if config.stopping else (None, None, None)
    eps = config.sqrt_eps
    w_dev = w.to(dev)

    passes = {"pass0": torch.cat([z[:, :ad]] * 3 + [z[:, ad:]], dim=1)}
    state = _resumed(checkpoint, n, ad, sd, 3 * len(slices))
    if state is None:
        state = {"phase": "pass1", "done": 0, "grey1": np.zeros(tuple(z.shape), np.float32),
                 "rgb2": np.zeros(tuple(passes["pass0"].shape), np.float32),
                 "rgb3": np.zeros(tuple(passes["pass0"].shape), np.float32),
                 **{k: {p: [] for p in PASSES[1:]} for k in ("history", "iterations")},
                 **{k: {p: 0.0 for p in PASSES[1:]} for k in ("before", "after", "seconds")}}
    grey1, rgb2, rgb3 = (torch.from_numpy(np.asarray(state[k], np.float32)) for k in ("grey1", "rgb2", "rgb3"))
    history, iterations, before, after, seconds = (state[k] for k in ("history", "iterations", "before", "after",
                                                                    "seconds"))
    problems = [_Problem(model, y[sl].to(dev), w_dev, ad, eps) for sl in slices]

    from twin.optics.torch_ops import tf32_products  # Warp's kernels load with it: not at this module's import
    from twin.progress import progress_bar

    def track(name, x0, energy, i):
        """One Adam run of pass `name` (index i) from x0; records the objective, history and iterations."""
        x, hist, done = _adam_run(x0, energy, caps[i], lrs[i], rules[i])
        with torch.no_grad():
            before[name] += float(energy(x0))
            after[name] += float(energy(x))
        history[name].append(hist)
        iterations[name].append(done)
        return x.cpu()

    last_save = time.perf_counter()
    bar = progress_bar(total=3 * len(slices), initial=int(state["done"]), desc="fine-tuning", unit="batch",
                       enabled=progress)

    def finished(unit: int, last: bool) -> None:
        """Batch unit (pass-major) is done: save the state when it is time, and at the end of each pass."""
        nonlocal last_save
        bar.update(1)
        if checkpoint is not None and (last or time.perf_counter() - last_save >= CHECKPOINT_SECONDS):
            state.update(phase=PASSES[1 + (unit + 1) // len(slices)] if unit + 1 < 3 * len(slices) else "done",
                         done=unit + 1, grey1=grey1.numpy(), rgb2=rgb2.numpy(), rgb3=rgb3.numpy())
            checkpoint.save(state)
            last_save = time.perf_counter()

    def run(p: int, step) -> None:
        """Pass p (1, 2, 3) over the batches not yet done, `step(sl, pb)` for each."""
        t0, first = time.perf_counter(), (p - 1) * len(slices)
        for b in range(max(int(state["done"]) - first, 0), len(slices)):
            step(slices[b], problems[b])
            _sync(dev)
            seconds[PASSES[p]] += time.perf_counter() - t0
            t0 = time.perf_counter()
            finished(first + b, b == len(slices) - 1)

    with _frozen(model), torch.enable_grad(), tf32_products(config.precision == "tf32"):
        def pass1(sl, pb):  # the grey 56-D latent against the mean over RGB, W[..., 0]
            grey1[sl] = track("pass1", z[sl].to(dev), pb.e1, 0)

        def pass2(sl, pb):  # each channel's albedo a_c from a_1, shape fixed at s_1, channel c of the photos, W[..., 0]
            a1, s1 = grey1[sl, :ad].to(dev), grey1[sl, ad:].to(dev)
            for c in range(3):
                rgb2[sl, c * ad:(c + 1) * ad] = track("pass2", a1, (lambda a, c=c: pb.e2(a, s1, c)), 1)
            rgb2[sl, 3 * ad:] = grey1[sl, ad:]

        def pass3(sl, pb):  # the joint 72-D latent against the RGB photos, W[..., c]
            rgb3[sl] = track("pass3", rgb2[sl].to(dev), pb.e3, 2)

        for p, step in enumerate((pass1, pass2, pass3), start=1):
            run(p, step)
    bar.close()
    passes["pass1"] = torch.cat([grey1[:, :ad]] * 3 + [grey1[:, ad:]], dim=1)
    passes["pass2"], passes["pass3"] = rgb2, rgb3

    _release(dev)
    out = {p: passes[p].numpy().astype(np.float32, copy=False) for p in PASSES}
    return FinetuneResult(latent=out["pass3"], passes=out, history=history, iterations=iterations,
                          objective={p: (before[p], after[p]) for p in PASSES[1:]}, seconds=seconds,
                          config=config)
