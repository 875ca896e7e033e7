"""The acquisition network of the OpenSVBRDF paper (§6), in torch, sized to the rig's LED count.

Paper §6 (reference §3.1) and the released code (reference §3.2-3.3), in one autoencoder:

    lumitexels (B, views, L) --PatternLayer--> measurements (B, views, K)
        --Encoder--> albedo latent (B, 8), shape latent (B, 48)
        --Decoder--> log-encoded primary-view lumitexel (B, L),  lumitexel = max(exp(.) - 1, 0)

* **Pattern layer** (paper: "layer 1 is a linear layer whose weights are the lighting patterns"): K signed
  patterns with 8-bit quantisation in the loop (straight-through), exported as (+, -) LED-level frames in
  the capture plan's order (`twin.capture.pattern_sets.signed_pairs`, names "learned_00+", "learned_00-", ...).
* **Encoder**: the paper's single encoder fed with all views' measurements (the released code's
  32-expert gated mixture of experts, reference §3.2, is not reproduced: one expert is built, with the
  released expert's branch shapes, scaled to the rig). Two branches: albedo -> 8, shape -> 48.
* **Decoder**: the released lumitexel decoder ("lumi net", reference §3.3): 11 linear layers, LeakyReLU
  (slope 0.01) after all but the last, output log(1 + m). Paper: dropout 30% on every layer except the
  last, Xavier initialisation.
* **Loss** (paper Eq. 3): sum over LEDs of (log(1 + m_hat) - log(1 + m))^2; the decoder's output *is*
  log(1 + m_hat).
* **Disentangling** (paper §6): `AcquisitionNet.albedo_swap_forward` decodes the four albedo/shape latent
  combinations of a pair of samples; the caller renders the four matching target lumitexels (albedos
  swapped between the two samples) and sums the loss over them (`albedo_swap_loss`).

Sizes. The released network is for L = 12,288 upper LEDs (166 M decoder parameters). For another rig the
hidden widths scale with L / 12,288 so that a rig of a few hundred LEDs trains on a CPU:

* decoder (`decoder_widths`): hidden width h -> ceil8(h * L / 12288), at least 64, then made monotone
  non-decreasing (a running maximum, so no hidden layer is below its scaled value); last width = L.
  For L = 12,288 this is exactly 56 -> 128 -> 256 -> 256 -> 512 -> 1024 -> 2048 -> 2048 -> 4096 -> 4096
  -> 8192 -> 12288.
* encoder branches (`encoder_widths`): the released expert's branches, albedo 64 -> 256 -> 1024 -> 512
  -> 64 -> 8 and shape 64 -> 256 -> 1024 -> 3072 -> 1024 -> 256 -> 48, hidden widths scaled by
  min(1, L / 12288), rounded up to a multiple of 8, at least 64 (they are never scaled *up*: the
  released ones already take 64 inputs, and more LEDs do not mean more measurements). Input width =
  views * K; output widths = albedo_dim, shape_dim. Along the albedo path this is 1 + 5 + 11 = 17 fully
  connected layers, the paper's count; the released shape branch has one layer more (6).

The compact architecture (`NetworkConfig.architecture = "compact"`, ours) exists because the
released decoder cannot ship: its 12,288-LED output layer alone is 100 M parameters. It keeps the released
decoder's first five hidden layers (to 1024 for L = 12,288) and replaces the rest by a factorised output
layer: a linear bottleneck of `COMPACT_RANK` (256, scaled like the hidden widths, at least 64) with no
activation, then the output layer. The lumitexel is thus a non-negative-clamped exp of a combination of 256
learned log-lumitexel bases, with coefficients a 5-layer MLP computes from the latent (a GGX lobe over the
LED dome is a smooth function of direction, which a few hundred bases can hold; how much it gives up on
narrow peaks is measured in docs/performance.md). Its encoder is the released one at half the hidden
widths. For the paper rig: 6.5 M parameters, 13 MB as float16 (`reconstruction.network.shipped` ships float16).

The peak term (`NetworkConfig.peak_term`, ours: a decoder conditioned on the LED's direction, with either
architecture): a lobe of alpha <= 0.02 lights ~3 of the paper rig's 12,288 LEDs, which a few hundred global bases
cannot place. The decoder adds one von Mises-Fisher lobe over the LEDs' directions d_l from the sample's centre,
    m_l = m_base,l + A exp(kappa (d_l . c - 1)),  computed as  log(1 + m_l) = logaddexp(y_l, log A + kappa (d_l . c - 1))
(y = log(1 + m_base), the decoder's own output), with (c, kappa, A) from a head on its last hidden layer (-> 128 -> 5):
the output stays log(1 + m), so every caller is unchanged. `decode_lumitexel` forms the same sum directly,
max(expm1(y) + exp(z), 0), which halves a fine-tuning step on the paper rig (docs/performance.md). The directions
are the rig's (`reconstruction.network.data.led_directions`), a buffer kept with the weights. Measured on the paper rig
(docs/performance.md): the narrow peaks' log RMS 2.43 -> 1.62 at equal training time, the whole held-out set +6%.

The mini rig (396 upper LEDs) gets a 260 k-parameter network (decoder 56 -> 64 x 5 -> 72 -> 72 -> 136 ->
136 -> 264 -> 396); the paper rig gets the released 166 M-parameter decoder. Small models train fastest
on a CPU with `torch.set_num_threads(1)` when the cores are shared.

Which view is decoded: the primary view (index 0), as in the paper ("output: the grey primary-view
lumitexel"). Units of m: whatever the training data uses (the released pipeline's photo units); the log
encoding makes the loss scale-aware, so train in the units the capture delivers.

No Warp here: pure torch (the lumitexels come from `twin` outside this module).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

__all__ = [
    "NetworkConfig", "REFERENCE_NUM_LEDS", "REFERENCE_DECODER_WIDTHS", "REFERENCE_ALBEDO_HIDDEN",
    "REFERENCE_SHAPE_HIDDEN", "ARCHITECTURES", "decoder_widths", "encoder_widths", "PatternLayer", "Encoder", "Decoder",
    "AcquisitionNet", "lumitexel_loss", "albedo_swap_loss", "log_to_lumitexel", "count_parameters",
]

REFERENCE_NUM_LEDS = 12 * 1024
REFERENCE_DECODER_WIDTHS = (56, 128, 256, 256, 512, 1024, 2048, 2048, 4096, 4096, 8192, 12288)
REFERENCE_ALBEDO_HIDDEN = (256, 1024, 512, 64)          # released albedo branch: 64 -> these -> 8
REFERENCE_SHAPE_HIDDEN = (256, 1024, 3072, 1024, 256)    # released shape branch: 64 -> these -> 48
MIN_HIDDEN = 64
ARCHITECTURES = ("paper", "compact")
COMPACT_TRUNK = 5     # compact decoder: the released decoder's first five hidden layers (to 1024 at L = 12,288)
COMPACT_RANK = 256    # compact decoder: the factorised output layer's rank at L = 12,288
COMPACT_ENCODER = 0.5  # compact encoder: the released branches' hidden widths times this
LEVELS = 255  # 8-bit LED drive (paper §5)
# the decoder's peak term (NetworkConfig.peak_term): its head's hidden width, its starting lobe (kappa 25: ~0.2 rad wide,
# amplitude e^-3) and the range of log kappa (kappa up to e^12: a lobe narrower than the paper rig's LED pitch)
PEAK_HIDDEN = 128
PEAK_KAPPA0, PEAK_LOG_A0 = 25.0, -3.0
PEAK_LOG_KAPPA = (-5.0, 12.0)


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _is_real(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


@dataclass(frozen=True)
class NetworkConfig:
    """Sizes and regularisation of the acquisition network.

    num_leds           L, the rig's upper LEDs (the lumitexel length); the bottom LEDs are not patterned.
    patterns_per_view  K signed patterns (each captured as a (+, -) photo pair; released: 32).
    views              cameras (released: 2; the encoder sees views * K measurements).
    albedo_dim, shape_dim  latent sizes (released: 8 + 48).
    dropout            dropout probability on every layer except the last (paper: 30%); 0 disables it.
    measurement_noise  sigma of the multiplicative N(1, sigma) noise on the measurements in training
                       (paper: 5%); 0 disables it.
    negative_slope     LeakyReLU slope (released: PyTorch's default 0.01).
    quantise           8-bit quantisation of the patterns in the loop (straight-through).
    architecture       "paper" (the released decoder and encoder, scaled to L) or "compact" (see the module
                       docstring: a factorised output layer and half-width encoder, small enough to ship).
    leds_off           lumitexel indices (upper LEDs) the patterns never drive: a layout with LEDs or boards
                       removed (twin.design); their weights are 0 in training and in the exported levels.
    fixed_patterns     the patterns are given (a fixed family: Hadamard, gradients, one LED at a time) and not
                       trained; only the encoder and decoder learn (PatternLayer.set_weights).
    peak_term          the decoder adds one lobe over the LEDs' directions to its output (`Decoder`; ours: the
                       narrow specular peaks that the compact decoder's bases cannot place). The directions are the
                       rig's (`Decoder.set_led_directions`), kept with the weights.
    shared_patterns    True (default): one pattern set photographed by every camera, the physical capture
                       (reference §3.2: the same 64 photos, 32 (+, -) pairs, are seen by camera 0 and
                       camera 1; the capture plan shows 64 learned frames once). False: an independent set
                       per view (views * 2K frames to capture). The pattern tensor is (views, K, L) either
                       way; shared sets are one parameter broadcast over the views.
    """

    num_leds: int
    patterns_per_view: int = 32
    views: int = 2
    albedo_dim: int = 8
    shape_dim: int = 48
    dropout: float = 0.3
    measurement_noise: float = 0.05
    negative_slope: float = 0.01
    quantise: bool = True
    shared_patterns: bool = True
    architecture: str = "paper"
    leds_off: tuple[int, ...] = ()
    fixed_patterns: bool = False
    peak_term: bool = False

    def __post_init__(self):
        object.__setattr__(self, "leds_off", tuple(self.leds_off))
        if not all(_is_int(i) and 0 <= i < self.num_leds for i in self.leds_off) or \
                len(set(self.leds_off)) != len(self.leds_off) or len(self.leds_off) >= self.num_leds:
            raise ValueError(f"NetworkConfig.leds_off must be distinct lumitexel indices in [0, {self.num_leds}) "
                             "leaving at least one LED on")
        for name in ("num_leds", "patterns_per_view", "views", "albedo_dim", "shape_dim"):
            v = getattr(self, name)
            if not _is_int(v) or v < 1:
                raise ValueError(f"NetworkConfig.{name} must be a positive integer, got {v!r}")
        if not _is_real(self.dropout) or not 0.0 <= float(self.dropout) < 1.0:
            raise ValueError(f"NetworkConfig.dropout must be a probability in [0, 1), got {self.dropout!r}")
        if not _is_real(self.measurement_noise) or not (0.0 <= float(self.measurement_noise) < math.inf):
            raise ValueError("NetworkConfig.measurement_noise must be a finite sigma >= 0, "
                             f"got {self.measurement_noise!r}")
        if not _is_real(self.negative_slope) or not (0.0 <= float(self.negative_slope) < 1.0):
            raise ValueError(f"NetworkConfig.negative_slope must lie in [0, 1), got {self.negative_slope!r}")
        for name in ("quantise", "shared_patterns", "fixed_patterns", "peak_term"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"NetworkConfig.{name} must be a bool, got {getattr(self, name)!r}")
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"NetworkConfig.architecture must be one of {ARCHITECTURES}, got {self.architecture!r}")

    @property
    def latent_dim(self) -> int:
        return self.albedo_dim + self.shape_dim

    @property
    def num_measurements(self) -> int:
        return self.views * self.patterns_per_view


def _ceil8(x: float) -> int:
    return int(math.ceil(x / 8.0 - 1e-9)) * 8


def decoder_widths(num_leds: int, latent_dim: int = 56, architecture: str = "paper") -> list[int]:
    """Layer widths of the lumitexel decoder, input first, output (L) last.

    "paper": 12 numbers for 11 linear layers, the released decoder (L = 12,288) with hidden widths scaled by
    L / 12,288, rounded up to a multiple of 8, at least 64, then a running maximum (monotone non-decreasing).
    Exactly the released widths for L = 12,288 and latent_dim = 56.
    "compact": the first COMPACT_TRUNK of those hidden widths, then the bottleneck rank (COMPACT_RANK scaled
    the same way), then L: 8 numbers for 7 linear layers (the last two, without an activation between
    them, are the factorised output layer).
    """
    if not _is_int(num_leds) or num_leds < 1:
        raise ValueError(f"num_leds must be a positive integer, got {num_leds!r}")
    if not _is_int(latent_dim) or latent_dim < 1:
        raise ValueError(f"latent_dim must be a positive integer, got {latent_dim!r}")
    if architecture not in ARCHITECTURES:
        raise ValueError(f"architecture must be one of {ARCHITECTURES}, got {architecture!r}")
    scale = num_leds / REFERENCE_NUM_LEDS
    hidden, running = [], 0
    for h in REFERENCE_DECODER_WIDTHS[1:-1]:
        running = max(running, MIN_HIDDEN, _ceil8(h * scale))
        hidden.append(running)
    if architecture == "compact":
        hidden = [*hidden[:COMPACT_TRUNK], max(MIN_HIDDEN, _ceil8(COMPACT_RANK * scale))]
    return [int(latent_dim), *hidden, int(num_leds)]


def _scaled_branch(hidden, scale: float) -> list[int]:
    return [max(MIN_HIDDEN, _ceil8(h * scale)) for h in hidden]


def encoder_widths(config: NetworkConfig) -> tuple[list[int], list[int]]:
    """(albedo branch widths, shape branch widths), input first, output last (see the module docstring)."""
    scale = min(1.0, config.num_leds / REFERENCE_NUM_LEDS)
    if config.architecture == "compact":
        scale *= COMPACT_ENCODER
    n_in = config.num_measurements
    albedo = [n_in, *_scaled_branch(REFERENCE_ALBEDO_HIDDEN, scale), config.albedo_dim]
    shape = [n_in, *_scaled_branch(REFERENCE_SHAPE_HIDDEN, scale), config.shape_dim]
    return albedo, shape


def _xavier_(module: nn.Module, negative_slope: float) -> None:
    """Xavier (Glorot) uniform weights with the LeakyReLU gain, zero biases, for every nn.Linear."""
    gain = nn.init.calculate_gain("leaky_relu", negative_slope)
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.xavier_uniform_(m.weight, gain=gain)
            nn.init.zeros_(m.bias)


# ------------------------------------------------------------------------------------------------ patterns


class _QuantiseSTE(torch.autograd.Function):
    """Forward: the 8-bit signed level q = round(|w| 255) / 255 * sign(w). Backward: identity (STE)."""

    @staticmethod
    def forward(ctx, w):
        return torch.round(w.abs() * LEVELS) / LEVELS * torch.sign(w)

    @staticmethod
    def backward(ctx, grad):
        return grad


class PatternLayer(nn.Module):
    """The lighting patterns as the network's first linear layer (paper §6).

    Weights: K = patterns_per_view SIGNED patterns per view, w = tanh(theta) in (-1, 1), tensor shape
    (views, K, L); theta is unconstrained. With `shared_patterns` (default) theta is (1, K, L) and the one
    set is used by every view, as in the physical capture where both cameras photograph the same frames.

    Why signed: the released network consumes signed patterns captured as (+, -) photo pairs,
    B(W+) - B(W-) (reference §2.4, `finetune/infer.py`); a signed pattern set is better conditioned than a
    non-negative one (the patterns can be mutually orthogonal and zero-mean, so the measurements are not
    dominated by a common "all LEDs on" component), and the capture plan already takes the photos in
    pairs, so a signed pattern costs no extra photos over what the plan does anyway.

    8-bit quantisation in the loop (config.quantise), straight-through: the forward pass uses
        q = round(|w| * 255) / 255 * sign(w),
    the levels the LED controller receives (the + frame gets round(max(w, 0) * 255), the - frame
    round(max(-w, 0) * 255)); the backward pass hands the gradient with respect to q to w unchanged, so
    d/dtheta = d/dq * (1 - tanh(theta)^2).

    forward(lumitexels (B, views, L)) -> (B, views, K): sum_l q[v, k, l] m[b, v, l] = B(W+) - B(W-).

    Initialisation: theta ~ N(0, 0.5^2) (standard deviation 0.5) from torch's generator in effect, so
    `torch.manual_seed` makes it reproducible.
    """

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        sets = 1 if config.shared_patterns else config.views
        self.theta = nn.Parameter(torch.randn(sets, config.patterns_per_view, config.num_leds) * 0.5,
                                  requires_grad=not config.fixed_patterns)
        mask = torch.ones(config.num_leds)
        mask[list(config.leds_off)] = 0.0
        self.register_buffer("mask", mask, persistent=False)  # from the config: not a learned state

    def set_weights(self, w) -> None:
        """Set the patterns to given signed weights w (K, L) in [-1, 1] (every view): theta = atanh(w), with
        |w| = 1 held just inside so that the 8-bit level is still 255."""
        w = torch.as_tensor(w, dtype=self.theta.dtype, device=self.theta.device)
        c = self.config
        if w.shape != (c.patterns_per_view, c.num_leds) or not torch.isfinite(w).all() or w.abs().max() > 1:
            raise ValueError(f"pattern weights must be finite, in [-1, 1], of shape ({c.patterns_per_view}, "
                             f"{c.num_leds}); got {tuple(w.shape)}")
        with torch.no_grad():
            self.theta.copy_(torch.atanh(w.clamp(-1 + 0.1 / LEVELS, 1 - 0.1 / LEVELS)).expand_as(self.theta))

    @property
    def num_frames(self) -> int:
        return 2 * self.config.patterns_per_view

    def weights(self) -> torch.Tensor:
        """w = tanh(theta), (views, K, L), unquantised, differentiable."""
        w = torch.tanh(self.theta) * self.mask
        return w.expand(self.config.views, -1, -1)

    def quantised_weights(self) -> torch.Tensor:
        """q, (views, K, L): the 8-bit weights (straight-through gradient)."""
        return _QuantiseSTE.apply(self.weights())

    def effective_weights(self) -> torch.Tensor:
        """The weights the forward pass uses: q when config.quantise, else w."""
        return self.quantised_weights() if self.config.quantise else self.weights()

    def forward(self, lumitexels: torch.Tensor) -> torch.Tensor:
        c = self.config
        if lumitexels.ndim != 3 or lumitexels.shape[1:] != (c.views, c.num_leds):
            raise ValueError(f"lumitexels must have shape (B, {c.views}, {c.num_leds}), got "
                             f"{tuple(lumitexels.shape)}")
        w = self.effective_weights().to(lumitexels.dtype)
        return torch.einsum("vkl,bvl->bvk", w, lumitexels)

    def _levels(self, view: int) -> torch.Tensor:
        c = self.config
        if not _is_int(view) or not 0 <= view < c.views:
            raise ValueError(f"view must be an integer in [0, {c.views}), got {view!r}")
        with torch.no_grad():
            w = self.weights()[view].detach().cpu()
            lv = torch.round(w.abs() * LEVELS)
            return lv * torch.sign(w)  # signed level, -255..255

    def export_levels(self, view: int = 0) -> np.ndarray:
        """uint8 (2K, L): LED drive levels, frames 2k (+ part) and 2k+1 (- part) of pattern k.

        levels / 255 with sign (+ frame minus - frame) reproduces the quantised weights q exactly; for each
        LED and pattern at most one of the two frames is non-zero.
        """
        signed = self._levels(view).numpy()
        out = np.zeros((self.num_frames, self.config.num_leds), dtype=np.uint8)
        out[0::2] = np.clip(signed, 0, LEVELS).astype(np.uint8)
        out[1::2] = np.clip(-signed, 0, LEVELS).astype(np.uint8)
        return out

    def export_names(self) -> list[str]:
        """Frame names in the plan's order: ["learned_00+", "learned_00-", "learned_01+", ...]."""
        return [f"learned_{k:02d}{s}" for k in range(self.config.patterns_per_view) for s in "+-"]


# ------------------------------------------------------------------------------------------------ encoder


def _mlp(widths, negative_slope: float, dropout: float, batchnorm: bool) -> nn.Sequential:
    """Linear layers; after each but the last: [BatchNorm1d], LeakyReLU, [Dropout]."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(widths) - 2:
            if batchnorm:
                layers.append(nn.BatchNorm1d(b))
            layers.append(nn.LeakyReLU(negative_slope))
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
    return nn.Sequential(*layers)


class Encoder(nn.Module):
    """Measurements -> (albedo latent, shape latent).

    Input: the views * K measurements, (B, views, K) or flattened (B, views * K) in the order
    [view 0's K, view 1's K, ...] (the released input order [cam0(32), cam1(32)]). In training mode each
    measurement is multiplied by N(1, measurement_noise) noise (paper: 5%); in eval mode the encoder is
    deterministic. Two MLP branches (widths: `encoder_widths`), each hidden layer followed by BatchNorm1d,
    LeakyReLU and dropout (paper: BN + LeakyReLU after every layer before the latent; dropout on all but the
    last layer); linear outputs.
    """

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        a_w, s_w = encoder_widths(config)
        self.albedo_branch = _mlp(a_w, config.negative_slope, config.dropout, batchnorm=True)
        self.shape_branch = _mlp(s_w, config.negative_slope, config.dropout, batchnorm=True)
        _xavier_(self, config.negative_slope)

    def forward(self, measurements: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c = self.config
        x = measurements
        if x.ndim == 3 and x.shape[1:] == (c.views, c.patterns_per_view):
            x = x.reshape(x.shape[0], -1)
        if x.ndim != 2 or x.shape[1] != c.num_measurements:
            raise ValueError(f"measurements must have shape (B, {c.views}, {c.patterns_per_view}) or "
                             f"(B, {c.num_measurements}), got {tuple(measurements.shape)}")
        if self.training and c.measurement_noise > 0:
            x = x * (1.0 + c.measurement_noise * torch.randn_like(x))
        return self.albedo_branch(x), self.shape_branch(x)


# ------------------------------------------------------------------------------------------------ decoder


class _Float32Product(torch.autograd.Function):
    """a @ b.T in float32 in the forward and the backward pass, whatever TF32 setting the caller runs under (the
    backward runs where autograd is called, outside any setting made around the forward). b is a constant."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        from twin.optics.torch_ops import tf32_products  # Warp's kernels load with it: not at this module's import

        ctx.save_for_backward(b)
        with tf32_products(False):
            return a @ b.T

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        from twin.optics.torch_ops import tf32_products

        (b,) = ctx.saved_tensors
        with tf32_products(False):
            return grad @ b, None


def log_to_lumitexel(log_lumitexel: torch.Tensor) -> torch.Tensor:
    """The decoder's log(1 + m) -> m = exp(.) - 1, clamped at >= 0 (reference §3.3)."""
    return torch.clamp(torch.expm1(log_lumitexel), min=0.0)


class Decoder(nn.Module):
    """Latent [albedo(albedo_dim), shape(shape_dim)] (released order) -> log-encoded lumitexel (B, L).

    The released lumi net with `decoder_widths` (11 linear layers), LeakyReLU after every layer except the
    last, dropout after every layer except the last (paper §6), no BatchNorm (as released), Xavier
    initialisation (uniform, LeakyReLU gain, zero bias). The compact architecture ends in the factorised
    output layer instead: its bottleneck layer has neither activation nor dropout. The output is log(1 + m);
    `decode_lumitexel` gives m = max(exp(out) - 1, 0).
    """

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        self.widths = decoder_widths(config.num_leds, config.latent_dim, config.architecture)
        if config.architecture == "compact":  # the trunk ends in the linear bottleneck, then the bases
            self.net = nn.Sequential(*_mlp(self.widths[:-1], config.negative_slope, config.dropout, batchnorm=False),
                                     nn.Linear(self.widths[-2], self.widths[-1]))
        else:
            self.net = _mlp(self.widths, config.negative_slope, config.dropout, batchnorm=False)
        _xavier_(self, config.negative_slope)
        if config.peak_term:  # drawn after the rest (torch's default initialisation): without it nothing changes
            self.peak = nn.Sequential(nn.Linear(self.widths[-2], PEAK_HIDDEN), nn.LeakyReLU(config.negative_slope),
                                      nn.Linear(PEAK_HIDDEN, 5))
            self.register_buffer("led_directions", torch.zeros(config.num_leds, 3))
            self._directions_set = False
            with torch.no_grad():  # it starts as a wide, dim lobe straight up: kappa 25 (~0.2 rad), A = e^-3
                self.peak[-1].weight.mul_(0.1)
                self.peak[-1].bias.copy_(torch.tensor([0.0, 0.0, 1.0, math.log(PEAK_KAPPA0), PEAK_LOG_A0]))

    def set_led_directions(self, directions) -> None:
        """The peak term's (L, 3) unit vectors from the sample's centre to the lumitexel's LEDs (world frame;
        reconstruction.network.data.led_directions(rig))."""
        d = torch.as_tensor(np.asarray(directions, dtype=np.float32))
        if not self.config.peak_term:
            raise ValueError("set_led_directions: this decoder has no peak term (NetworkConfig.peak_term)")
        if d.shape != (self.config.num_leds, 3) or not torch.isfinite(d).all() or \
                not torch.allclose(d.norm(dim=1), torch.ones(len(d)), atol=1e-4):
            raise ValueError(f"led directions must be ({self.config.num_leds}, 3) finite unit vectors, "
                             f"got shape {tuple(d.shape)}")
        self.led_directions.copy_(d)
        self._directions_set = True

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        if self.config.peak_term and prefix + "led_directions" in state_dict:
            self._directions_set = True

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        self._check(latent)
        if not self.config.peak_term:
            return self.net(latent)
        y, z = self._with_peak(latent)
        # log(1 + m_base + A exp(kappa (d . c - 1))) = logaddexp(y, log A + kappa (d . c - 1)), y = log(1 + m_base)
        return torch.logaddexp(y, z)

    def _check(self, latent: torch.Tensor) -> None:
        if latent.ndim != 2 or latent.shape[1] != self.config.latent_dim:
            raise ValueError(f"latent must have shape (B, {self.config.latent_dim}), got {tuple(latent.shape)}")
        if self.config.peak_term and not self._directions_set:
            raise ValueError("the decoder's peak term has no LED directions: set_led_directions(led_directions(rig)) "
                             "or load weights that carry them")

    def _with_peak(self, latent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(y, z) (B, L): the decoder's own log(1 + m_base) and the peak's log A + kappa (d . c - 1)."""
        h = self.net[:-1](latent)
        p = self.peak(h)
        c = p[:, :3] / p[:, :3].norm(dim=1, keepdim=True).clamp_min(1e-6)
        kappa = p[:, 3:4].clamp(PEAK_LOG_KAPPA[0], PEAK_LOG_KAPPA[1]).exp()
        # z as one product, [kappa c, log A - kappa] . [d, 1]: one (B, L) pass, where the product, the shift and the
        # scale took three. In float32 in both passes even where the caller allows TF32 (fine-tuning on CUDA does):
        # this product's inputs carry kappa (up to e^12), which TF32's 10-bit mantissa would round by ~5e-4 of
        # itself, moving the exponent by kappa times that; and kappa's gradient, c . (g @ d) - sum(g), cancels where
        # d . c ~ 1. Its inner size is 4, so it is bound by writing z either way (docs/performance.md: with the
        # guard, TF32 moves fine-tuning's gradients no more than in the logaddexp form it replaces).
        q = torch.cat([kappa * c, p[:, 4:5] - kappa], dim=1)
        d1 = torch.cat([self.led_directions, self.led_directions.new_ones(len(self.led_directions), 1)], dim=1)
        return self.net[-1](h), _Float32Product.apply(q, d1)

    def decode_lumitexel(self, latent: torch.Tensor) -> torch.Tensor:
        """m = max(exp(forward) - 1, 0); with the peak term as max(expm1(y) + exp(z), 0), the same sum without
        the log and exp of logaddexp: fewer passes over the (B, L) values, which bound fine-tuning on a GPU."""
        if not self.config.peak_term:
            return log_to_lumitexel(self.forward(latent))
        self._check(latent)
        y, z = self._with_peak(latent)
        return torch.clamp(torch.expm1(y) + torch.exp(z), min=0.0)


# ------------------------------------------------------------------------------------------------ network


class AcquisitionNet(nn.Module):
    """Pattern layer + encoder + decoder (paper §6).

    forward(lumitexels (B, views, L)) -> dict(measurements (B, views, K), albedo (B, albedo_dim),
        shape (B, shape_dim), log_lumitexel (B, L)); the decoded lumitexel is the primary view's (view 0),
        so its training target is lumitexels[:, 0]. forward(m_a, pair_with=m_b) -> dict(swap_log_lumitexel
        = albedo_swap_forward(m_a, m_b)).
    encode(measurements) -> (albedo, shape); decode(albedo, shape) -> log_lumitexel;
    decode_lumitexel(albedo, shape) -> lumitexel (exp - 1, clamped >= 0).
    albedo_swap_forward(m_a, m_b) -> (B, 4, L): the four latent combinations of a pair (paper §6).

    Modules are built in the order pattern layer, encoder, decoder, so `torch.manual_seed(s)` before
    construction fixes every parameter.
    """

    def __init__(self, config: NetworkConfig):
        super().__init__()
        if not isinstance(config, NetworkConfig):
            raise ValueError(f"config must be a NetworkConfig, got {type(config).__name__}")
        self.config = config
        self.patterns = PatternLayer(config)
        self.encoder = Encoder(config)
        self.decoder = Decoder(config)

    def measure(self, lumitexels: torch.Tensor) -> torch.Tensor:
        return self.patterns(lumitexels)

    def encode(self, measurements: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.encoder(measurements)

    def decode(self, albedo: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        return self.decoder(torch.cat([albedo, shape], dim=-1))

    def decode_lumitexel(self, albedo: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        return self.decoder.decode_lumitexel(torch.cat([albedo, shape], dim=-1))

    def forward(self, lumitexels: torch.Tensor, pair_with: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        if pair_with is not None:  # the albedo-swap step through forward, so that DDP sees it (reconstruction.network.train)
            return {"swap_log_lumitexel": self.albedo_swap_forward(lumitexels, pair_with)}
        measurements = self.measure(lumitexels)
        albedo, shape = self.encode(measurements)
        return {"measurements": measurements, "albedo": albedo, "shape": shape,
                "log_lumitexel": self.decode(albedo, shape)}

    def albedo_swap_forward(self, m_a: torch.Tensor, m_b: torch.Tensor) -> torch.Tensor:
        """Log-lumitexels (B, 4, L) of [(alb_a, shp_a), (alb_b, shp_b), (alb_b, shp_a), (alb_a, shp_b)].

        m_a, m_b: (B, views, L) lumitexels of the two samples of each pair. Both are measured and encoded
        in one batch (BatchNorm statistics over the 2B samples) and the four combinations decoded in one
        batch of 4B. Targets (rendered by the caller): sample a; sample b; a's shape (frame, roughness)
        with b's albedos (rho_d, rho_s); b's shape with a's albedos.
        """
        if m_a.shape != m_b.shape:
            raise ValueError(f"m_a and m_b must have the same shape, got {tuple(m_a.shape)} and {tuple(m_b.shape)}")
        n = m_a.shape[0]
        albedo, shape = self.encode(self.measure(torch.cat([m_a, m_b], dim=0)))
        alb_a, alb_b = albedo[:n], albedo[n:]
        shp_a, shp_b = shape[:n], shape[n:]
        albs = torch.cat([alb_a, alb_b, alb_b, alb_a], dim=0)
        shps = torch.cat([shp_a, shp_b, shp_a, shp_b], dim=0)
        out = self.decode(albs, shps)                       # (4B, L), combination-major
        return out.reshape(4, n, -1).transpose(0, 1)        # (B, 4, L)


# ------------------------------------------------------------------------------------------------ losses


def lumitexel_loss(log_pred: torch.Tensor, target: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Paper Eq. 3: per lumitexel sum_l (log(1 + m_hat_l) - log(1 + m_l))^2.

    log_pred: the network's output, already log(1 + m_hat); target: the linear lumitexel m (>= 0, same
    shape). The sum runs over the last axis (LEDs). reduction "mean" (default): the mean over all leading
    axes (the batch) of the per-lumitexel sums; "sum": their sum; "none": the per-lumitexel values, with
    the leading shape.
    """
    if log_pred.shape != target.shape:
        raise ValueError(f"log_pred and target must have the same shape, got {tuple(log_pred.shape)} and "
                         f"{tuple(target.shape)}")
    if log_pred.ndim < 1:
        raise ValueError("lumitexel_loss needs at least one (LED) axis")
    per = (log_pred - torch.log1p(target)).square().sum(dim=-1)
    if reduction == "mean":
        return per.mean()
    if reduction == "sum":
        return per.sum()
    if reduction == "none":
        return per
    raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}")


def albedo_swap_loss(log_pred: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Paper §6 disentangling loss: Eq. 3 summed over the 4 combinations, mean over the pairs.

    log_pred: `albedo_swap_forward`'s (B, 4, L); targets: the four linear lumitexels (B, 4, L) in the same
    order [a, b, (albedo b, shape a), (albedo a, shape b)].
    """
    if log_pred.ndim != 3 or log_pred.shape[1] != 4:
        raise ValueError(f"log_pred must have shape (B, 4, L), got {tuple(log_pred.shape)}")
    return lumitexel_loss(log_pred, targets, reduction="none").sum(dim=1).mean()


def count_parameters(model: nn.Module, trainable_only: bool = True) -> int:
    """Number of scalar parameters (those with requires_grad when trainable_only)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)
