"""GGX and local-frame fitting per texel (paper §7.2, reference §5): the decoded RGB lumitexels (and the
line-light measurements) -> anisotropic GGX parameters and a world-frame shading frame -> OpenSVBRDF maps.

    result = fit_ggx(rig, positions, lumitexels, lines=..., line_weights=..., config=FitConfig())
    maps = to_maps(result, grid_shape, size_mm, transparency, name)      # twin.materials.samples.SVBRDFMaps

Physics. The prediction of a texel is the twin's own forward model, not a re-implementation of GGX:
    m_hat[p, l, c] = twin.lumitexels(rig, pos, n, t, rho_d, rho_s, alpha_x, alpha_y, convention="physical",
                                     camera, transparency=0, visibility=True)[p, upper[l], c] * LUMITEXEL_SCALE
i.e. the "network units" of reconstruction.network.data (what reconstruction.network.data.synthesize renders in grey);
with torch tensors in, twin.lumitexels is differentiable through its Warp tape. The line term predicts
M_hat[p, k, c] = sum_l W[k, l, c] m_hat[p, l, c] (reference §2.4) for the upper-LED line weights W.

Loss per texel (reference §5 adds lambda_m times the line term to the lumitexel term):
    "log1p"  mean_{l,c} (log(1 + m_hat) - log(1 + m))^2 + lambda_lines mean_{k,c} (log(1 + M_hat) - log(1 + M))^2
             (the network's Eq. 3 form: network units are scaled so that log(1 + m) compresses the range)
    "mse"    mean_{l,c} ((m_hat - m) / s_m)^2 + lambda_lines mean_{k,c} ((M_hat - M) / s_M)^2, s = the mean
             target over all texels. The reference's MSE compares m_hat with s m for a frozen "albedo
             scalar" s and divides the exported rho by s again; m_hat is linear in rho, so that scalar only
             rescales the loss. Dividing by the target's mean does the same and keeps lambda dimensionless.

Albedos in closed form. Eq. 1 is linear in the albedos: m_hat[l, c] = rho_d[c] D[l, c] + rho_s[c] S[l, c]
with D = I_c Psi V (wi.n) / (pi r^2) and S = I_c Psi V fs (wi.n) / r^2 (twin.optics.lumitexel's docstring; Schlick's
F0 is grey, so fs is one number per LED). ONE launch of the forward model with rho_d = (1, 0, 0) and
rho_s = (0, 1, 0) gives D in channel 0 and S in channel 1 (twin.optics.jvp.basis_jvp, which also gives their
derivatives for the Jacobian); the other channels follow from the LEDs' RGB intensities (D[l, c] = D[l, 0] I[l, c]
/ I[l, 0]), and so do the photos' predictions, one matrix product of the grey bases with the weights times those
ratios. For given geometry, rho_d and rho_s then minimise the loss's Gauss-Newton quadratic at the target
(weights f'(m)^2; exact for "mse") on the box [0, 1] x [0, rho_s_max], per texel and channel, lumitexel and line
terms together (`_projected`).

Sums over the LEDs in Warp (issue #12). Every per-texel sum over the lumitexels' LEDs and channels, the albedo
quadratic's, the loss's and the Gauss-Newton system's J J^T and J r, is one Warp launch over the grey bases
(reconstruction.stages.fit_sums), which never stores a (texels x LEDs x 3) tensor beyond the target itself; torch keeps
the photos' few residuals. On the paper rig on an H100 this made the fit 3x faster and its memory half
(docs/performance.md); the stored-Jacobian path (_analytic_jacobian, _residuals) stays as the checked reference.

Parameterisation of the geometry: 5 unconstrained numbers per texel, [u, v, theta, a_x, a_y]:
  * n = normalize(N + u X + v Y) for the sample plane's normal N and axes X, Y (twin.materials.samples): n.N > 0 for
    every finite (u, v), smooth, no seam. The reference maps 2 sigmoids to a hemi-octahedral normal around
    the VIEW direction (§2.3), which gives no world meaning to its parameters and lets n_z < 0 under an
    oblique camera, against the map contract (n_z > 0); this is a justified alternative, not a copy.
  * t = cos(theta) t0 + sin(theta) n x t0, with t0 the plane's X carried along by the smallest rotation
    that takes N to n (defined on the whole open hemisphere): theta is world-meaningful (0 means "along
    +x" for a flat texel) and periodic, so it needs no sigmoid. The reference's theta = 2 pi sigmoid
    relative to a view-dependent axis (§2.3) has neither property.
  * alpha = exp(log lo + (log hi - log lo) sigmoid(a)) on FitConfig.alpha_range: the reference's range
    (0.006 + 0.497 sigmoid), log-spaced so that Adam's steps are relative changes of alpha, as the metric
    |log alpha| error is.
The neural method's heads add 6 numbers, rho_d = sigmoid(d) and rho_s = rho_s_max sigmoid(s) (reference §5).

Methods (FITTING_METHODS, dispatched by `fit_method`, one function each):
  * "direct" (ours): Levenberg-Marquardt on the 5 geometry numbers per texel, the albedos in closed form at
    every evaluation (variable projection: the 6 linear unknowns never slow it), with an analytic Jacobian (the
    bases' derivatives from one Warp launch, twin.optics.jvp; the albedos' own by the implicit function theorem;
    FitConfig.jacobian), in chunks of `batch` texels; on a grid, neighbour propagation (`_propagate`), then the
    joint prior on roughness and specular albedo (`_joint_roughness`, `_joint_albedos`; FitConfig.alpha_prior), which
    couples neighbouring texels of one material so that a lobe the photos barely see is pooled (issue #14).
  * "neural" (reference §5): a learnable feature texture (channels, R, C), Xavier-uniform, sampled with
    grid_sample (bilinear, align_corners=True) at the texel centres, feeds 5 MLP heads (n 2, theta 1,
    alpha 2, rho_d 3, rho_s 3), each channels -> hidden -> hidden -> hidden -> k with LeakyReLU(0.2), whose
    outputs are the 11 raw numbers above; Adam (lr 1e-3) on random texel batches from a seeded generator.

Initialisation (both methods; ours): candidate geometries (the plane normal, and for texels whose specular
peak points elsewhere the half vector of that peak; times a few isotropic and anisotropic roughness pairs
and tangent angles), each with its closed-form albedos; each texel starts from its lowest-loss candidate,
ranked on the primary view's lumitexels and photos.
The neural method first regresses its heads onto these numbers (warm start).

Measured (the evidence for "direct", "log1p" and lambda_lines, taken with the Adam version of "direct" before
issue #14; docs/accuracy.md has the material suite's measurements of the Levenberg-Marquardt fit, the joint
prior and the photo groups; mini rig, one core of a shared 2-core CPU). Synthetic: the `ramps` sample
resampled by twin.materials.samples, primary view; "exact" = the truth's lumitexels and lines; "decoded" = the
shipped network's RGB decode of the truth (grey shape latent from both views, per-channel albedo latents;
median error 27% per lumitexel, no fine-tuning) with the exact lines x (1 + 2% Gaussian noise). Pipeline:
a `hemicube capture` of ramps through reconstruction.pipeline (48 x 48, fine-tuned latents, extracted
lines without the held-out one), scored by reconstruction.evaluation.metrics.map_errors. Median (90th percentile):
normal (deg); alpha (relative; synthetic: |log alpha| of sorted pairs, pipeline: alpha_x); rho_s
(relative); tangent (deg, mod pi, where alpha ratio >= 1.5); CPU seconds.
                              normal        alpha          rho_s   tangent  CPU s
  48 x 48 exact, defaults     0.04 (0.07)   0.007 (0.06)   0.003   0.2      39
          exact, "mse"        0.04 (0.12)   0.009 (0.10)   0.006   0.3      31
          exact, neural       0.04 (0.26)   0.009 (0.11)   0.014   0.9      41   (600 steps x 256 texels)
  48 x 48 decoded, defaults   0.07 (0.16)   0.018 (0.16)   0.017   0.3      32
          decoded, "mse"      0.26 (0.68)   0.072 (0.39)   0.040   0.8      30
          decoded, neural     0.06 (0.21)   0.016 (0.10)   0.017   0.5      40
  pipeline, defaults          0.06 (0.24)   0.023 (0.41)   0.013   0.4      32
          "mse"               0.29 (0.74)   0.23  (0.64)   0.043   0.8      34
          neural              0.07 (0.30)   0.031 (0.31)   0.019   0.9      44
  pipeline, lambda_lines 0.01 / 1 / 10 / 100 / 1000: alpha 0.73 / 0.29 / 0.065 / 0.023 / 0.019;
  synthetic 24 x 24 decoded, lambda 0.01 / 1 / 10 / 100: 0.61 / 0.19 / 0.03 / 0.006 with exact lines, and
  (lambda 1 / 10 / 100) 0.19 / 0.03 / 0.02 with 2% line noise.
  The initialisation alone: alpha 0.22 (0.47), exact normals on the flat texels.
So: "direct" (as good or better in the bulk and on tangents, exact on exact targets, per texel so it
scales by chunks; the neural heads' sharing trims the alpha tail on decoded data), "log1p" (the decoder's
errors sit in the bright specular entries that "mse" weighs most) and lambda_lines = 100 (the measured
lines carry the truth, the decoded lumitexels the decoder's bias; 100 keeps some of the lumitexels'
LED-space detail, is within 0.5% alpha of 1000, and the better of 10 and 100 with 2% line noise).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch
from torch import nn

import twin
from twin.materials.samples import ALPHA_RANGE, RHO_D_RANGE, RHO_S_RANGE, SVBRDFMaps, canonical_anisotropy

from reconstruction.stages import fit_sums
from reconstruction.network.data import LUMITEXEL_SCALE
from reconstruction.stages.finetune import PRECISIONS

__all__ = ["FitConfig", "FitResult", "fit_ggx", "fit_method", "to_maps", "FITTING_METHODS", "METHODS", "LOSSES"]

LOSSES = ("log1p", "mse")
JACOBIANS = ("analytic", "forward")  # FitConfig.jacobian
METHODS = ("direct", "neural")  # FITTING_METHODS below: one function each
GEOMETRY_SIZE = 5  # [u, v, theta, a_x, a_y]
# texel-LED pairs evaluated at once when FitConfig.batch is None (ours, memory and speed): every texel of a mini-rig
# grid up to 660^2 in one range; 16,384 texels on the paper rig. A pair costs one view's grey bases and their 5
# derivatives at a time (12 floats; _linearisation), the chunk's copy of its target (3 floats) and passing
# temporaries: one Gauss-Newton system of 16,384 paper texels allocates 10.8 GiB (19.9 GiB while both views' bases
# were held at once). Why this many: on an H100 the fit of a paper-rig 512^2 grid took 90.4 s in chunks of 5,461
# texels, 80.1 s in 10,922, 68.2 s in 16,384 and 72.0 s in 21,845; below that a chunk's launches are too short to
# fill the GPU. With both views' bases at once, a 1024^2 reconstruction in chunks of 16,384 used 42.5 GB of the
# device, over issue #12's 40 GB (docs/performance.md, 2026-11-26). (Before the fit's sums moved into Warp,
# reconstruction.stages.fit_sums, it stored (texels x LEDs x 3) tensors for the albedo weights, the loss and each of 5
# Jacobian rows, and held 2^25 pairs: 16,384 paper texels at once ran out of an H100's 80 GB.)
AUTO_CHUNK_PAIRS = 3 * 2 ** 26
HEADS = (("normal", 2), ("theta", 1), ("alpha", 2), ("rho_d", 3), ("rho_s", 3))  # reference §5's 5 heads


@dataclass(frozen=True)
class FitConfig:
    """Settings of the GGX fit. Sources: reference §5 (the released fitting code) or ours (measured: the
    module docstring's table)."""

    method: str = "direct"  # ours, measured
    # direct (ours): Levenberg-Marquardt iterations (a Jacobian and an evaluation of the residuals each, on the texels
    # not yet converged); neural: Adam steps of `batch` texels (the reference runs 120,000 steps of 128 texels).
    iterations: int | None = None  # None: 20 (direct), 600 (neural)
    lr: float | None = None  # the neural method's Adam (None: 1e-3, reference §5); the direct method has none
    batch: int | None = None  # direct: texels per chunk (None: AUTO_CHUNK_PAIRS / LEDs); neural: per step (None: 256)
    # the widest of the reference's per-class ranges (§5 OBJECT_CONFIG: 0.006 + axay_range, 1.0 for wood and
    # woven; ps_range 20 for paper), one setting for every sample: issue #14's suite reaches alpha 0.6 and rho_s
    # 18, which the default-class ranges (0.503, 10) clip
    alpha_range: tuple = (0.006, 1.006)
    rho_s_max: float = 20.0
    lm_damping: float = 1e-2  # direct: Levenberg-Marquardt's initial mu (ours)
    # direct: the Levenberg-Marquardt's Jacobian (ours): "analytic", the bases' derivatives from one Warp launch per
    # camera (twin.optics.jvp) and the albedos' by variable projection (_analytic_jacobian); "forward", forward
    # differences of the residuals, five more evaluations of the forward model a step (the same-run baseline of
    # `hemicube bench fit-jacobian`)
    jacobian: str = "analytic"
    fd_step: float = 1e-3  # direct: forward-difference step of the Jacobian in every number (ours), and the
    # analytic one's where a lobe is isotropic (_tensor_system)
    # direct: a texel stops when a kept step lowers its loss by less (relative; ours); the joint prior stops when a
    # kept step lowers its objective by less than this times its size at noise level (_joint_roughness)
    tolerance: float = 1e-5
    propagation: int = 2  # direct, on a grid: rounds of neighbour propagation (ours; _propagate)
    # direct, on a grid (ours; _joint_roughness): the expected change of log alpha between neighbouring texels of
    # one material, the scale of a Gaussian smoothness prior that texels whose photos barely constrain alpha
    # (a weak or rough lobe) borrow from; None: every texel alone
    alpha_prior: float | None = 0.1
    # weight of the line term (reference §5's lambda_m; ours, measured) for photos of one frame an exposure: the
    # reconstruction pipeline multiplies it by the capture's frames per exposure (an inverse-variance weight). The
    # reference's 0.01-0.1 multiply unnormalised sums, whose squares exceed the lumitexels' by (mean M / mean m)^2
    # (81 on the mini rig's ramps, more with the paper rig's longer lines): 0.8-8 or more in this normalised loss.
    lambda_lines: float = 100.0
    loss: str = "log1p"  # ours, measured
    seed: int = 0  # the neural method's initialisation and batches (the direct method draws nothing)
    device: str = "cpu"
    # direct, analytic Jacobian (ours, issue #12): the projections of the bases' derivatives onto the photos' weights,
    # and those of the initial candidates (_best_candidate: they are only ranked), on a CUDA device in TF32 ("tf32",
    # the tensor cores' 10-bit mantissa) or "float32". Only the Gauss-Newton system's direction and the starting
    # point: the loss that accepts or refuses a step and the closed-form albedos stay float32, so
    # the fixed point of Levenberg-Marquardt does not move (docs/performance.md: the fit's median per-texel loss
    # against float32's, checked by `hemicube bench reconstruct`). The CPU's products are float32 either way.
    precision: str = "tf32"
    camera: str = "primary"  # the view the lumitexels were decoded for (reference §5: primary only)
    secondary_camera: str = "secondary"  # the view of fit_ggx's `secondary` photos (ours)
    # initial candidates (ours): roughness levels (log-spaced inside the reference range), tangent angles
    init_alphas: tuple = (0.02, 0.08, 0.3, 0.8)
    init_thetas: int = 3
    # neural method (reference §5: 24 channels, 128 hidden; scaled down for a CPU)
    features: int = 16  # the paper's "16 neural parameters" (reference §5; the code uses 24)
    hidden: int = 64
    warm_start_steps: int = 300  # regression of the heads onto the initial numbers (ours)

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"FitConfig.method must be one of {METHODS}, got {self.method!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"FitConfig.loss must be one of {LOSSES}, got {self.loss!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"FitConfig.precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.jacobian not in JACOBIANS:
            raise ValueError(f"FitConfig.jacobian must be one of {JACOBIANS}, got {self.jacobian!r}")
        for k, least in (("iterations", 0), ("batch", 1)):  # 0 iterations: the initialisation alone
            v = getattr(self, k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < least):
                raise ValueError(f"FitConfig.{k} must be an integer >= {least} or None, got {v!r}")
        for k in ("lr", "lm_damping", "fd_step", "tolerance", "alpha_prior"):
            v = getattr(self, k)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"FitConfig.{k} must be positive, got {v!r}")
        lo, hi = (float(a) for a in self.alpha_range)
        if not (ALPHA_RANGE[0] <= lo < hi <= ALPHA_RANGE[1]):
            raise ValueError(f"FitConfig.alpha_range must satisfy {ALPHA_RANGE[0]} <= lo < hi <= {ALPHA_RANGE[1]} "
                             f"(the map range), got {self.alpha_range}")
        object.__setattr__(self, "alpha_range", (lo, hi))
        if not (0 < self.rho_s_max <= RHO_S_RANGE[1]):
            raise ValueError(f"FitConfig.rho_s_max must lie in (0, {RHO_S_RANGE[1]}], got {self.rho_s_max}")
        if not (math.isfinite(self.lambda_lines) and self.lambda_lines >= 0):
            raise ValueError(f"FitConfig.lambda_lines must be >= 0, got {self.lambda_lines}")
        if not self.init_alphas or not all(lo < a < hi for a in self.init_alphas):
            raise ValueError(f"FitConfig.init_alphas must be non-empty and inside alpha_range {self.alpha_range}")
        if isinstance(self.propagation, bool) or not isinstance(self.propagation, int) or self.propagation < 0:
            raise ValueError(f"FitConfig.propagation must be an integer >= 0, got {self.propagation!r}")
        for k in ("init_thetas", "features", "hidden"):
            if getattr(self, k) < 1:
                raise ValueError(f"FitConfig.{k} must be >= 1, got {getattr(self, k)}")
        if self.warm_start_steps < 0:
            raise ValueError(f"FitConfig.warm_start_steps must be >= 0, got {self.warm_start_steps}")

    @property
    def steps(self) -> int:
        return self.iterations if self.iterations is not None else {"direct": 20, "neural": 600}[self.method]

    @property
    def learning_rate(self) -> float:
        return self.lr if self.lr is not None else 1e-3


@dataclass
class FitResult:
    """Per-texel GGX parameters (numpy float32, world frame, the twin's physical units as in SVBRDFMaps):
    normal (N, 3), tangent (N, 3) (the alpha_x axis), alpha_x (N,), alpha_y (N,), rho_d (N, 3), rho_s (N, 3);
    history: the mean per-texel loss at each step (over the texels fitted: a refit's, _fit_direct); seconds: wall
    time of the whole fit; info: method, loss, config, init_seconds, seconds_per_iteration, texel_loss (N,) at the
    end, and the direct method's texel_q (N, 5)."""

    normal: np.ndarray
    tangent: np.ndarray
    alpha_x: np.ndarray
    alpha_y: np.ndarray
    rho_d: np.ndarray
    rho_s: np.ndarray
    history: list = field(default_factory=list)
    seconds: float = 0.0
    info: dict = field(default_factory=dict)


# --- the problem: checked inputs on a device -------------------------------------------------------------
@dataclass
class _Photos:
    """One camera's photo measurements (the lines, the learned patterns' photos): M (3, n, K) channel-major
    (for matmul), f(M), their Gauss-Newton weights lam f'(M)^2 / (3 K), the upper-LED weights W (3, L, K),
    the "mse" scale (their mean) and their weight in the loss, lam = lambda_lines x K / (all photos' K): every
    photo of every camera weighs the same."""

    camera: str
    M: torch.Tensor
    M_f: torch.Tensor
    M_w: torch.Tensor
    W: torch.Tensor
    scale: float
    lam: float

    def part(self, idx: torch.Tensor) -> "_Photos":
        return replace(self, M=self.M[:, idx], M_f=self.M_f[:, idx], M_w=self.M_w[:, idx])


@dataclass
class _Problem:
    rig: object
    config: FitConfig
    pos: torch.Tensor  # (n, 3) float32, mm
    # (n, L, 3) the lumitexels m, or (a lumitexel source, fit_ggx) a function of texel indices that gives theirs:
    # part() asks it chunk by chunk. The loss's f(m) and the albedo quadratic's weights f'(m)^2 / (3 L) are
    # derived where they are used (the Warp sums, reconstruction.stages.fit_sums, from m itself), not stored: at 12,288
    # LEDs each is 147 kB a texel
    target: object
    leds: int  # L, the upper LEDs
    photos: tuple  # _Photos of each camera that has measurements (primary first); empty: lumitexels only
    upper_rig: object  # the rig with its upper LEDs only: what the fit evaluates (the bottom ones light nothing here)
    ratio: torch.Tensor  # (2, L, 3): I[l, c] / I[l, 0] and I[l, c] / I[l, 1] (module docstring)
    frame: torch.Tensor  # (3, 3) rows N, X, Y of the sample plane
    scale_m: float  # "mse": the targets' mean (the albedo scalar's role); 1 for log1p, which needs none

    @property
    def n(self) -> int:
        return self.pos.shape[0]

    @property
    def has_lines(self) -> bool:
        return bool(self.photos) and self.config.lambda_lines > 0

    @property
    def target_f(self) -> torch.Tensor:
        """(n, L, 3) f(m): what the loss compares f(m_hat) with (`_f`)."""
        return _f(self.target, self.config.loss, self.scale_m)

    def part(self, idx: torch.Tensor) -> "_Problem":
        """The same problem for the texels idx, their lumitexels on the device (a source's decoded now)."""
        target = self.target[idx] if torch.is_tensor(self.target) else _lumitexels_of(self.target, idx, self.leds)
        return replace(self, pos=self.pos[idx], target=target, photos=tuple(g.part(idx) for g in self.photos))


def _lumitexels_of(source, idx: torch.Tensor, leds: int) -> torch.Tensor:
    """A lumitexel source's lumitexels of the texels idx, checked as fit_ggx checks an array."""
    m = _tensor("lumitexels", source(idx), 3, idx.device)
    _check_lumitexels(m, (idx.numel(), leds, 3))
    return m


def _target_mean(m, n: int, leds: int, chunk: int, dev) -> float:
    """The target lumitexels' mean (the "mse" loss's scale): a source's `chunk` texels at a time."""
    if torch.is_tensor(m):
        return _mean(m)
    chunks = torch.arange(n, device=dev).split(chunk)
    return sum(_mean(_lumitexels_of(m, i, leds)) * i.numel() for i in chunks) / n


def _check_lumitexels(m: torch.Tensor, shape: tuple) -> None:
    if tuple(m.shape) != shape:
        raise ValueError(f"lumitexels must have shape (N, L_upper, 3) = {shape} (upper LEDs only, network units), "
                         f"got {tuple(m.shape)}")
    if _negative(m):
        raise ValueError(f"lumitexels must be >= 0 (decoded lumitexels are clamped at 0), got min {float(m.min()):g}")


def _f(x: torch.Tensor, loss: str, scale: float) -> torch.Tensor:
    """The loss's transform of lumitexels or measurements: log(1 + x) or x / scale (module docstring)."""
    return torch.log1p(x) if loss == "log1p" else x / scale


def _df(x: torch.Tensor, loss: str, scale: float) -> torch.Tensor:
    """f'(x), the loss's transform's slope (_f)."""
    return (1.0 + x).reciprocal() if loss == "log1p" else torch.full_like(x, 1.0 / scale)


def _df2(x: torch.Tensor, loss: str, scale: float) -> torch.Tensor:
    """f'(x)^2: the Gauss-Newton weight of a residual f(x_hat) - f(x) linearised at the target x."""
    return _df(x, loss, scale).square()


def _tensor(name: str, x, ndim: int, device: torch.device) -> torch.Tensor:
    """x (numpy or torch) as a float32 tensor on `device` (no copy when it already is one), checked:
    `ndim` dimensions, 3 last, finite."""
    if torch.is_tensor(x):
        if x.is_complex() or x.dtype == torch.bool:
            raise ValueError(f"{name} must be a real numeric array, got dtype {x.dtype}")
        t = x.detach().to(device=device, dtype=torch.float32)
    else:
        a = np.asarray(x)
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"{name} must be a real numeric array, got dtype {a.dtype}")
        t = torch.as_tensor(a, dtype=torch.float32, device=device)
    if t.ndim != ndim or t.shape[-1] != 3:
        raise ValueError(f"{name} must have {ndim} dimensions with 3 last (RGB or xyz), got shape {tuple(t.shape)}")
    if t.numel() and bool(torch.isfinite(torch.stack(torch.aminmax(t))).all()):
        return t  # one reduction and one sync (_negative's reason); the pieces only to name the first bad value
    for i, part in enumerate(_pieces(t)):
        bad = ~torch.isfinite(part)
        if bad.any():
            first = np.unravel_index(i * _PIECE + int(torch.nonzero(bad)[0, 0]), tuple(t.shape))
            raise ValueError(f"{name} contains NaN or Inf (first at index {tuple(int(v) for v in first)})")
    return t


_PIECE = 2 ** 24  # elements a piece: _pieces


def _pieces(t: torch.Tensor):
    """The flattened tensor in pieces of _PIECE elements: the means of the fit's inputs, and the search for a bad
    value, go piece by piece, so that none makes a temporary the size of the paper rig's lumitexels (9.7 GB per
    65,536 texels; a float64 mean of them cast the whole tensor first)."""
    return t.reshape(-1).split(_PIECE)


def _negative(t: torch.Tensor) -> bool:
    """Whether t holds a value below 0, by one reduction without temporaries (_tensor's checks: a fit at 1024^2 checks
    ~16 passes of 1M decoded lumitexels x 36,864 values, ~2,300 pieces a pass, and two checks with a sync for each
    piece were the way before; issue #12). NaN is _tensor's to report, which checks first."""
    return bool(t.numel()) and bool(torch.amin(t) < 0)


def _mean(t: torch.Tensor) -> float:
    """The mean in float64, piece by piece."""
    return sum(float(p.sum(dtype=torch.float64)) for p in _pieces(t)) / max(t.numel(), 1)


def _photos(name: str, wname: str, camera: str, M, W, n: int, L: int, config: FitConfig, dev,
            total: int) -> _Photos:
    """Checked photo measurements M (n, K, 3) (called `name`) under upper-LED weights W (K, L, 3) (`wname`) of
    `camera`, `total` photos in all groups."""
    M = _tensor(name, M, 3, dev)
    W = _tensor(wname, W, 3, dev)
    if tuple(W.shape[1:]) != (L, 3):
        raise ValueError(f"{wname} must have shape (K, L_upper, 3) = (K, {L}, 3) (upper LEDs), "
                         f"got {tuple(W.shape)}")
    if tuple(M.shape) != (n, W.shape[0], 3):
        raise ValueError(f"{name} must have shape (N, K, 3) = ({n}, {W.shape[0]}, 3), got {tuple(M.shape)}")
    if _negative(M) or _negative(W):
        raise ValueError(f"{name} and {wname} must be >= 0 (light measurements and LED drive levels)")
    scale = max(_mean(M), 1e-12)
    lam = config.lambda_lines * W.shape[0] / total
    M = M.permute(2, 0, 1).contiguous()
    return _Photos(camera, M, _f(M, config.loss, scale), _df2(M, config.loss, scale) * (lam / (3 * W.shape[0])),
                   W.permute(2, 1, 0).contiguous(), scale, lam)


def _problem(rig, positions, lumitexels, lines, line_weights, grid_shape, config: FitConfig,
             secondary=None) -> _Problem:
    for cam in (config.camera,) + ((config.secondary_camera,) if secondary is not None else ()):
        if cam not in rig.cameras:
            raise ValueError(f"rig {rig.name!r} has no camera {cam!r} (it has {list(rig.cameras)})")
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    L = upper.size
    intensity = np.asarray(rig.leds.intensity, dtype=np.float64)[upper]
    if np.any(intensity[:, :2] <= 0):
        raise ValueError("every upper LED needs a red and a green intensity > 0: the closed-form albedos take "
                         "the diffuse and specular responses from those channels (module docstring)")
    dev = torch.device(config.device)
    pos = _tensor("positions", positions, 2, dev)
    n = pos.shape[0]
    if n == 0:
        raise ValueError("positions is empty: nothing to fit")
    m = lumitexels if callable(lumitexels) else _tensor("lumitexels", lumitexels, 3, dev)
    if not callable(m):
        _check_lumitexels(m, (n, L, 3))
    if (lines is None) != (line_weights is None):
        raise ValueError("lines and line_weights go together: give both or neither")
    if config.method == "neural":
        if grid_shape is None:
            raise ValueError("method 'neural' needs grid_shape (R, C): the feature texture covers the texel grid")
        R, C = (int(v) for v in grid_shape)
        if R * C != n:
            raise ValueError(f"grid_shape {tuple(grid_shape)} has {R * C} texels but positions has {n} "
                             "(texels in row-major order of the grid)")
    photos = []
    if secondary is not None and lines is None:
        raise ValueError("secondary photos need the primary ones (lines) too")
    total = sum(len(x[1]) for x in ((lines, line_weights), secondary or (None, ())) if x[1] is not None)
    if lines is not None:
        photos.append(_photos("lines", "line_weights", config.camera, lines, line_weights, n, L, config, dev, total))
    if secondary is not None:
        photos.append(_photos("secondary photos", "their weights", config.secondary_camera, *secondary, n, L, config,
                              dev, total))
    # log1p needs no scale; "mse" the targets' mean, a source's in the fit's chunks (_chunks)
    scale_m = max(_target_mean(m, n, L, config.batch or _auto_chunk(L), dev), 1e-12) \
        if config.loss == "mse" else 1.0

    def T(a):
        return torch.as_tensor(a, dtype=torch.float32, device=dev)

    s = rig.sample
    return _Problem(rig, config, pos, m, L, tuple(photos),
                    replace(rig, leds=rig.leds.subset(upper)),
                    T(np.stack([intensity / intensity[:, :1], intensity / intensity[:, 1:2]])),
                    T(np.stack([s.normal, s.x_axis, s.y_axis])), scale_m)


# --- numbers <-> GGX parameters ------------------------------------------------------------------------
def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _base_tangent(n: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
    """X rotated by the smallest rotation taking N to n (Rodrigues with k = N x n, c = N.n > 0)."""
    N, X = frame[0].expand_as(n), frame[1].expand_as(n)
    k = torch.linalg.cross(N, n, dim=-1)
    c = (n * N).sum(-1, keepdim=True)
    return X * c + torch.linalg.cross(k, X, dim=-1) + k * ((k * X).sum(-1, keepdim=True) / (1 + c))


def _frame_steps(g: torch.Tensor, frame: torch.Tensor) -> dict:
    """_frame_of's steps for the first 3 geometry numbers [u, v, theta]: the length pn of p = N + u X + v Y, the
    normal n = p / pn, the base tangent t0 (_base_tangent), cos and sin of theta, n x t0, the turned tangent
    t = cos t0 + sin n x t0, its part tp normal to n and that part's length tl; "normal" and "tangent" = tp / tl
    (unit, world). _frame_derivatives differentiates these same steps."""
    N, X, Y = frame
    p = N + g[:, 0:1] * X + g[:, 1:2] * Y
    pn = torch.linalg.vector_norm(p, dim=-1, keepdim=True)
    n = p / pn
    t0 = _base_tangent(n, frame)
    th = g[:, 2:3]
    cos, sin = torch.cos(th), torch.sin(th)
    nt0 = torch.linalg.cross(n, t0, dim=-1)
    t = cos * t0 + sin * nt0
    tp = t - (t * n).sum(-1, keepdim=True) * n
    tl = torch.linalg.vector_norm(tp, dim=-1, keepdim=True)
    return {"pn": pn, "t0": t0, "cos": cos, "sin": sin, "nt0": nt0, "t": t, "tl": tl,
            "normal": n, "tangent": tp / tl}


def _frame_of(g: torch.Tensor, frame: torch.Tensor) -> dict:
    """The first 3 geometry numbers [u, v, theta] -> normal, tangent (unit, world)."""
    f = _frame_steps(g, frame)
    return {"normal": f["normal"], "tangent": f["tangent"]}


def _geometry(g: torch.Tensor, frame: torch.Tensor, config: FitConfig) -> dict:
    """(n, 5) numbers [u, v, theta, a_x, a_y] -> normal, tangent (unit, world), alpha_x, alpha_y, with alpha
    = exp(log lo + (log hi - log lo) sigmoid(a)) (the neural heads' bounded outputs, and the candidates)."""
    la, lb = (math.log(a) for a in config.alpha_range)
    alpha = torch.exp(la + (lb - la) * torch.sigmoid(g[:, 3:5]))
    return {**_frame_of(g, frame), "alpha_x": alpha[:, 0], "alpha_y": alpha[:, 1]}


def _log_geometry(q: torch.Tensor, frame: torch.Tensor, steps: dict | None = None) -> dict:
    """(n, 5) numbers [u, v, theta, log alpha_x, log alpha_y] (the direct method's) -> the geometry; `steps`: the
    numbers' _frame_steps, when the caller has them."""
    f = steps if steps is not None else _frame_steps(q, frame)
    return {"normal": f["normal"], "tangent": f["tangent"], "alpha_x": torch.exp(q[:, 3]),
            "alpha_y": torch.exp(q[:, 4])}


def _albedo_numbers(raw: torch.Tensor, config: FitConfig) -> dict:
    """The neural heads' 6 albedo numbers -> rho_d in [0, 1], rho_s in [0, rho_s_max] (reference §5)."""
    return {"rho_d": torch.sigmoid(raw[:, 0:3]), "rho_s": config.rho_s_max * torch.sigmoid(raw[:, 3:6])}


def _logit(p: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    p = p.clamp(eps, 1 - eps)
    return torch.log(p) - torch.log1p(-p)


def _encode_geometry(n, theta, alpha_x, alpha_y, frame, config: FitConfig) -> torch.Tensor:
    """Inverse of _geometry for n with n.N > 0, theta from the base tangent, alpha inside alpha_range."""
    N, X, Y = frame
    c = (n * N).sum(-1)
    la, lb = (math.log(a) for a in config.alpha_range)
    return torch.stack([(n * X).sum(-1) / c, (n * Y).sum(-1) / c, theta,
                        _logit((torch.log(alpha_x) - la) / (lb - la)), _logit((torch.log(alpha_y) - la) / (lb - la))],
                       dim=1)


# --- the forward model, the albedos, the loss -------------------------------------------------------------
def _lumitexels(prob: _Problem, geom: dict, rho_d: torch.Tensor, rho_s: torch.Tensor,
                camera: str | None = None) -> torch.Tensor:
    """(n, L_upper, 3) network units seen from `camera` (None: config.camera): the twin's Warp forward model
    (differentiable)."""
    c = prob.config
    m = twin.lumitexels(prob.upper_rig, prob.pos, geom["normal"], geom["tangent"], rho_d, rho_s, geom["alpha_x"],
                        geom["alpha_y"], convention="physical", device=c.device, camera=camera or c.camera,
                        transparency=torch.zeros(prob.n, device=prob.pos.device), visibility=True)
    return m * LUMITEXEL_SCALE


def _grey(prob: _Problem, geom: dict, camera: str | None = None, derivatives: tuple | None = None):
    """The grey bases val (2, n, L) = D0, S0 in network units: the lumitexels of unit diffuse and unit specular
    albedo in the LEDs' first and second channel, seen from `camera` (None: config.camera), one Warp launch of
    twin.optics.jvp.basis_jvp (the same led_response as the forward model); the channels follow by the LEDs'
    intensity ratios (_split, module docstring). With derivatives = (d_frame, d_log_alpha) (_frame_derivatives),
    (val, dD0, dS0), the bases' derivatives (n, 5, L) along the 5 numbers."""
    from twin.optics.jvp import basis_jvp

    d_frame, d_log_alpha = derivatives or (prob.pos.new_zeros(prob.n, 0, 3, 3), prob.pos.new_zeros(prob.n, 0, 2))
    val, dD0, dS0 = basis_jvp(prob.upper_rig, prob.pos, geom["normal"], geom["tangent"], geom["alpha_x"],
                              geom["alpha_y"], d_frame, d_log_alpha, camera=camera or prob.config.camera,
                              visibility=True)
    val.mul_(LUMITEXEL_SCALE)  # in place: basis_jvp's outputs are fresh, and at 12,288 LEDs large
    return (val, dD0.mul_(LUMITEXEL_SCALE), dS0.mul_(LUMITEXEL_SCALE)) if derivatives else val


def _split(prob: _Problem, val: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """D, S (n, L, 3) of the grey bases val (2, n, L) (_grey)."""
    return val[0][..., None] * prob.ratio[0], val[1][..., None] * prob.ratio[1]


def _project(g: "_Photos", x: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """A photo group's predictions (3, n, ..., K) of grey bases x (n, ..., L) whose channels follow by `ratio` (L, 3):
    one matrix product with the weights W[c] ratio[:, c], all channels side by side."""
    W = (g.W * ratio.T[:, :, None]).permute(1, 0, 2).reshape(g.W.shape[1], -1)  # (L, 3 K)
    out = (x.reshape(-1, x.shape[-1]) @ W).reshape(*x.shape[:-1], 3, g.W.shape[2])
    return out.movedim(-2, 0)


def _project_normal_rows(g: "_Photos", dD: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """_project of the diffuse basis's derivatives dD (n, 5, L): only the normal's two rows are projected, the
    others are zeros (the diffuse lobe does not depend on the tangent or the roughness, so basis_jvp's rows along
    theta and the log alphas are exact zeros; projecting them was 3/10 of the Jacobian's projections)."""
    out = _project(g, dD[:, :2], ratio)
    return torch.cat([out, out.new_zeros(*out.shape[:2], dD.shape[1] - 2, out.shape[3])], 2)


def _photo_bases(prob: _Problem, geom: dict, val: torch.Tensor) -> list:
    """For each photo group (prob.photos): (W D, W S), each (3, n, K), the bases of its camera (val for
    config.camera, one more launch for another) under its weights; [] without photos."""
    if not prob.has_lines:
        return []
    bases = {prob.config.camera: val}
    out = []
    for g in prob.photos:
        if g.camera not in bases:
            bases[g.camera] = _grey(prob, geom, g.camera)
        out.append(_photo_pair(prob, g, bases[g.camera]))
    return out


def _photo_pair(prob: _Problem, g: "_Photos", val: torch.Tensor) -> tuple:
    """(W D, W S), each (3, n, K): a photo group's predictions of the grey bases val (2, n, L) of its camera."""
    return _project(g, val[0], prob.ratio[0]), _project(g, val[1], prob.ratio[1])


def _solve_box(dd, dm, ds, ss, sm, rho_s_max: float):
    """argmin over a in [0, 1], b in [0, rho_s_max] of a^2 dd + 2ab ds + b^2 ss - 2a dm - 2b sm (elementwise).
    A convex quadratic on a box: its minimum is the unconstrained one when that is feasible, else on an
    edge, where it is the 1-D minimum clipped to the edge; all five are evaluated, the best feasible kept (the
    first of equals; (0, 0) where none is feasible). The five side by side, in one set of operations: on a GPU
    this runs once per evaluation of the loss, and one operation per candidate was launch-bound there."""
    tiny = 1e-30
    det = (dd * ss - ds * ds).clamp_min(tiny)
    s_, d_ = ss.clamp_min(tiny), dd.clamp_min(tiny)
    zero, one, top = torch.zeros_like(dd), torch.ones_like(dd), torch.full_like(dd, rho_s_max)
    a = torch.stack([(dm * ss - sm * ds) / det, zero, one, (dm / d_).clamp(0, 1),
                     ((dm - rho_s_max * ds) / d_).clamp(0, 1)])
    b = torch.stack([(sm * dd - dm * ds) / det, (sm / s_).clamp(0, rho_s_max), ((sm - ds) / s_).clamp(0, rho_s_max),
                     zero, top])
    e = a * a * dd + b * b * ss + 2 * a * b * ds - 2 * a * dm - 2 * b * sm
    ok = (a >= 0) & (a <= 1) & (b >= 0) & (b <= rho_s_max) & torch.isfinite(e)
    best = torch.where(ok, e, torch.full_like(e, math.inf)).argmin(0, keepdim=True)
    found = ok.any(0)
    return (torch.where(found, a.gather(0, best)[0], zero), torch.where(found, b.gather(0, best)[0], zero))


def _projected(prob: _Problem, val: torch.Tensor, photo_bases: list, sums: list | None = None):
    """(n, 3) rho_d, rho_s in closed form (module docstring) for the grey bases val (_grey) and each photo group's
    predictions (W D, W S) (_photo_bases), and the albedos each photo group is predicted with: config.camera's
    share the lumitexels' (the result), another camera's photos get their own pair, fitted to them alone (ours:
    the 45-degree view's texel footprint is ~1.4x longer, so where the colour varies it averages another
    mixture, and with shared albedos the fit explained that brightness difference between the views by a
    false specular lobe: fabric alpha 6% -> 78%; with its own albedos that view informs the geometry, the
    normal, tangent and roughness, only). Constants for autograd: at the minimiser the loss's gradient w.r.t.
    them vanishes (exactly for "mse", to first order for "log1p"), so the geometry's gradient needs none.
    `sums`: _albedo_sums of these bases, when the caller has them. Returns (rho_d, rho_s, [(rho_d, rho_s) of
    each photo group])."""
    with torch.no_grad():
        sums = sums if sums is not None else _albedo_sums(prob, val, photo_bases)
        a, b = _solve_box(*(s.double() for s in sums), prob.config.rho_s_max)
        albedos = (a.to(val.dtype), b.to(val.dtype))
        own = [albedos if g.camera == prob.config.camera else _own_albedos(prob, g, WD, WS)
               for g, (WD, WS) in zip(prob.photos, photo_bases)]
    return albedos[0], albedos[1], own


def _albedo_sums(prob: _Problem, val: torch.Tensor, photo_bases: list, derivatives: tuple | None = None):
    """The albedo quadratic's sums (dd, dm, ds, ss, sm), each (n, 3), of the lumitexels and config.camera's
    photos (_solve_box's a^2 dd + 2ab ds + b^2 ss - 2a dm - 2b sm: the loss to second order in the albedos), the
    lumitexels' in one Warp launch (reconstruction.stages.fit_sums). With derivatives = (dD0, dS0, photo_dbases), the
    bases' derivatives (n, 5, L) and each photo group's (dWD, dWS) (3, n, 5, K): (sums, their derivatives, each
    (n, 5, 3))."""
    with torch.no_grad():
        dD0, dS0, dpb = derivatives or (None, None, None)
        sums, dsums = fit_sums.albedo_sums(val, prob.target, prob.ratio, prob.config.loss, prob.scale_m, dD0, dS0)
        for i, (g, (WD, WS)) in enumerate(zip(prob.photos, photo_bases)):
            if g.camera == prob.config.camera:
                sums = [s + e for s, e in zip(sums, _photo_terms(g, WD, WS))]
                if derivatives:
                    dsums = [s + e for s, e in zip(dsums, _photo_dterms(g, WD, WS, *dpb[i]))]
    return (sums, dsums) if derivatives else sums


def _photo_terms(g: _Photos, WD: torch.Tensor, WS: torch.Tensor) -> list:
    """A photo group's share of the albedo quadratic's sums (dd, dm, ds, ss, sm), each (n, 3)."""
    return [(g.M_w * e).sum(2).T for e in (WD * WD, WD * g.M, WD * WS, WS * WS, WS * g.M)]


def _own_albedos(prob: _Problem, g: _Photos, WD: torch.Tensor, WS: torch.Tensor) -> tuple:
    """The closed-form albedos of one photo group alone (_projected)."""
    with torch.no_grad():
        return tuple(x.to(WD.dtype) for x in _solve_box(*(e.double() for e in _photo_terms(g, WD, WS)),
                                                   prob.config.rho_s_max))


def _predicted(photo_bases: list, albedos: list) -> list:
    """Each photo group's predictions (3, n, K) for its bases (W D, W S) and albedos (rho_d, rho_s) (n, 3)."""
    return [a.T[:, :, None] * WD + b.T[:, :, None] * WS for (WD, WS), (a, b) in zip(photo_bases, albedos)]


def _photo_residuals(prob: _Problem, photos_hat: list) -> list:
    """Each photo group's residuals (n, 3 K), sqrt(lambda / (3 K)) (f(M_hat) - f(M)), for its predictions
    (3, n, K): the sum of their squares is its share of the per-texel loss (module docstring)."""
    out = []
    for g, M_hat in zip(prob.photos, photos_hat):
        r = (_f(M_hat, prob.config.loss, g.scale) - g.M_f).permute(1, 0, 2).reshape(M_hat.shape[1], -1)
        out.append(r * math.sqrt(g.lam / M_hat[:, 0].numel()))
    return out


def _loss_of(prob: _Problem, m_hat: torch.Tensor, photos_hat: list) -> torch.Tensor:
    """(n,) per-texel loss (module docstring) of predicted lumitexels (n, L, 3) and photos (each (3, n, K))."""
    out = (_f(m_hat, prob.config.loss, prob.scale_m) - prob.target_f).square().mean(dim=(1, 2))
    return out + sum(r.square().sum(1) for r in _photo_residuals(prob, photos_hat))


def _projected_loss(prob: _Problem, geom: dict, sums: list | None = None):
    """The loss of `geom` with its closed-form albedos: (loss (n,), rho_d, rho_s); with a list `sums`, the
    albedo quadratic's sums (_albedo_sums) are appended to it. The lumitexels' share in one Warp launch
    (reconstruction.stages.fit_sums), the photos' in torch."""
    val = _grey(prob, geom)
    pb = _photo_bases(prob, geom, val)
    own_sums = _albedo_sums(prob, val, pb)
    if sums is not None:
        sums.append(own_sums)
    rd, rs, own = _projected(prob, val, pb, own_sums)
    loss = fit_sums.lumitexel_terms(val, prob.target, prob.ratio, rd, rs, prob.config.loss, prob.scale_m)[0]
    return loss + sum(r.square().sum(1) for r in _photo_residuals(prob, _predicted(pb, own))), rd, rs


def _loss(prob: _Problem, q: torch.Tensor) -> torch.Tensor:
    """(n,) per-texel loss of the direct method's numbers q with their closed-form albedos (_projected_loss): the
    sum of the squares of _residuals."""
    return _projected_loss(prob, _log_geometry(q, prob.frame))[0]


def _residuals(prob: _Problem, q: torch.Tensor) -> torch.Tensor:
    """(n, 3 L + 3 K) residuals of the direct method's numbers q with their closed-form albedos, scaled so that
    the sum of their squares is the per-texel loss (_loss_of): (f(m_hat) - f(m)) / sqrt(3 L), then
    sqrt(lambda / (3 K)) (f(M_hat) - f(M))."""
    c = prob.config
    geom = _log_geometry(q, prob.frame)
    val = _grey(prob, geom)
    pb = _photo_bases(prob, geom, val)
    rd, rs, own = _projected(prob, val, pb)
    D, S = _split(prob, val)
    m_hat = rd[:, None] * D + rs[:, None] * S
    lumi = (_f(m_hat, c.loss, prob.scale_m) - prob.target_f).reshape(prob.n, -1) / math.sqrt(m_hat[0].numel())
    return torch.cat([lumi, *_photo_residuals(prob, _predicted(pb, own))], dim=1)


def _rendered_loss(prob: _Problem, geom: dict, rho_d: torch.Tensor, rho_s: torch.Tensor) -> torch.Tensor:
    """The loss of explicit parameters (the neural method's)."""
    m_hat = _lumitexels(prob, geom, rho_d, rho_s)
    photos_hat = []
    for g in prob.photos if prob.has_lines else ():
        if g.camera == prob.config.camera:
            photos_hat.append(torch.matmul(m_hat.permute(2, 0, 1), g.W))
        else:  # another view: its own closed-form albedos (_projected)
            WD, WS = _photo_pair(prob, g, _grey(prob, geom, g.camera))
            photos_hat += _predicted([(WD, WS)], [_own_albedos(prob, g, WD, WS)])
    return _loss_of(prob, m_hat, photos_hat)


# --- initialisation --------------------------------------------------------------------------------------
def _peak_normal(prob: _Problem) -> torch.Tensor:
    """Each texel's half vector between the view and its brightest LED once the diffuse part is removed
    (diffuse level: the 25th percentile of m / D0 over the LEDs that light a plane-normal white texel
    well); the plane normal where that half vector is more than 60 deg off it."""
    c = prob.config
    N = prob.frame[0].expand(prob.n, 3)
    geom = _geometry(torch.zeros(prob.n, GEOMETRY_SIZE, device=N.device), prob.frame, c)
    d0 = _grey(prob, geom)[0] * prob.ratio[0].mean(1)  # the diffuse basis's mean over the channels
    grey = prob.target.mean(2)
    lit = d0 > 0.05 * d0.amax(1, keepdim=True)
    ratio = torch.where(lit, grey / d0.clamp_min(1e-12), torch.full_like(grey, math.nan))
    level = torch.nanquantile(ratio, 0.25, dim=1, keepdim=True).nan_to_num(0.0)
    l_max = (grey - level * d0).argmax(1)
    led = torch.tensor(prob.upper_rig.leds.positions, dtype=torch.float32, device=N.device)[l_max]
    cam = torch.tensor(prob.rig.camera(c.camera).centre, dtype=torch.float32, device=N.device)
    h = _unit(_unit(led - prob.pos) + _unit(cam - prob.pos))
    return torch.where(((h * N).sum(-1, keepdim=True) > 0.5), h, N)


def _diffuse_normal(prob: _Problem) -> torch.Tensor:
    """Each texel's normal from its diffuse shading alone (photometric stereo, Woodham 1980; ours as a
    candidate): m_l / f_l = rho_d (n . w_l) on the LEDs that the diffuse term dominates, f_l the unit-albedo
    diffuse response of a plane-normal texel divided by its cosine (intensity, emission profile, 1/r^2), w_l
    the direction to LED l; least squares for rho_d n over the LEDs in front of the normal (a ratio above zero)
    whose ratio lies between a tenth of those ratios' median and the median (below the highlight). Why: where the mirror
    direction of a steeply tilted texel leaves the LED dome, the brightest LED sits at the dome's edge and its
    half vector (_peak_normal) points far from the normal: on the paper rig, 18% of random texels (tilts
    43-59 deg) fell into a rough-lobe basin without this candidate, 8% with it (docs/performance.md). The plane
    normal where the system is degenerate."""
    c = prob.config
    N = prob.frame[0].expand(prob.n, 3)
    geom = _geometry(torch.zeros(prob.n, GEOMETRY_SIZE, device=N.device), prob.frame, c)
    d0 = _grey(prob, geom)[0] * prob.ratio[0].mean(1)  # the diffuse basis's mean over the channels
    led = torch.tensor(prob.upper_rig.leds.positions, dtype=torch.float32, device=N.device)
    w = _unit(led[None] - prob.pos[:, None])  # (n, L, 3)
    cos_n = (w * N[:, None]).sum(-1)
    f = torch.where(cos_n > 0.05, d0 / cos_n.clamp_min(0.05), torch.zeros_like(d0))
    ratio = torch.where(f > 0.05 * f.amax(1, keepdim=True), prob.target.mean(2) / f.clamp_min(1e-12),
                        torch.full_like(d0, math.nan))
    top = ratio.nan_to_num(0.0).amax(1, keepdim=True)
    lit = torch.where(ratio > 1e-6 * top, ratio, torch.full_like(ratio, math.nan))  # in front of the normal
    med = torch.nanquantile(lit, 0.5, dim=1, keepdim=True)
    use = (lit > 0.1 * med) & (lit <= med)
    wu = w * use[..., None]
    A = wu.transpose(1, 2) @ wu + 1e-9 * torch.eye(3, device=N.device)
    b = (wu * ratio.nan_to_num(0.0)[..., None]).sum(1)
    g = torch.linalg.solve(A, b[..., None])[..., 0]
    ok = (use.sum(1) >= 6) & torch.isfinite(g).all(1) & ((g * N).sum(1) > 0.1 * g.norm(dim=1))
    return torch.where(ok[:, None], _unit(g), N)


def _candidate_pairs(c: FitConfig) -> tuple[list, list]:
    """The roughness / tangent candidates (alpha_x, alpha_y, theta): the isotropic ones (every init_alphas), and the
    anisotropic ones (each pair alpha_y < alpha_x at init_thetas angles; the BRDF has period pi in theta)."""
    thetas = [math.pi * k / c.init_thetas for k in range(c.init_thetas)]
    return ([(a, a, 0.0) for a in c.init_alphas],
            [(ax, ay, th) for ax in c.init_alphas for ay in c.init_alphas if ay < ax for th in thetas])


def _best_candidate(prob: _Problem, normal: torch.Tensor, pairs: list):
    """For one normal per texel, the best (loss (n,), geometry numbers (n, 5), rho_d, rho_s) over the
    roughness / tangent candidates `pairs` (_candidate_pairs), each with its closed-form albedos. With
    FitConfig.precision "tf32", the candidates' projections onto the photos' weights use the tensor cores (on
    CUDA): a candidate is only ranked, Levenberg-Marquardt's float32 losses decide where the fit ends, and on the
    paper rig these projections were about half of the candidates' time, ~20% of the fit's (issue #12)."""
    from twin.optics.torch_ops import tf32_products

    c = prob.config
    n, dev = prob.n, prob.pos.device
    best = None
    for ax, ay, th in pairs:
        g = _encode_geometry(normal, torch.full((n,), th, device=dev), torch.full((n,), ax, device=dev),
                             torch.full((n,), ay, device=dev), prob.frame, c)
        with tf32_products(c.precision == "tf32"):
            loss, rd, rs = _projected_loss(prob, _geometry(g, prob.frame, c))
        if best is None:
            best = [loss, g, rd, rs]
        else:
            _keep_better(best, [loss, g, rd, rs])
    return best


def _keep_better(best: list, other: list, sel: torch.Tensor | None = None) -> torch.Tensor:
    """Put `other` (_best_candidate's list, of the texels sel, None: all) into `best`, in place, where its loss is
    lower; returns where it was."""
    old = best if sel is None else [x[sel] for x in best]
    better = other[0] < old[0]
    for x, was, y in zip(best, old, other):
        now = torch.where(better.view(-1, *[1] * (y.ndim - 1)), y, was)
        if sel is None:
            x.copy_(now)
        else:
            x[sel] = now
    return better


def _initial(prob: _Problem):
    """(geometry numbers (n, 5), rho_d, rho_s) of the best initial candidate per texel. The normal first: the plane
    normal, and where they point elsewhere (> 1 deg off), the specular peak's half vector (_peak_normal) and the
    diffuse shading's normal (_diffuse_normal), each with the isotropic roughness candidates; then the
    anisotropic candidates at each texel's best normal (_candidate_pairs)."""
    # candidates are ranked on config.camera's lumitexels and photos alone (ours): the other view's photos, with
    # albedos of their own (_projected), inform the geometry that Levenberg-Marquardt refines, and ranking with
    # them doubled the candidates' cost for no gain on the material suite (docs/accuracy.md, 2026-11-25).
    # The anisotropic candidates at the best normal only (ours, issue #12): they were 18 of the 22 candidates at each
    # of up to three normals, 3/10 of the fit's time on the paper rig; which normal is best is decided by where the
    # lobe points, which the isotropic candidates see as well (docs/performance.md, 2026-11-26)
    prob = replace(prob, photos=tuple(g for g in prob.photos if g.camera == prob.config.camera))
    isotropic, anisotropic = _candidate_pairs(prob.config)
    with torch.no_grad():
        N = prob.frame[0].expand(prob.n, 3)
        normal = N.clone()
        best = _best_candidate(prob, N, isotropic)
        for h in (_peak_normal(prob), _diffuse_normal(prob)):
            sel = torch.nonzero((h * N).sum(-1) < math.cos(math.radians(1.0))).flatten()
            if sel.numel():
                better = _keep_better(best, _best_candidate(prob.part(sel), h[sel], isotropic), sel)
                normal[sel] = torch.where(better[:, None], h[sel], normal[sel])
        if anisotropic:
            _keep_better(best, _best_candidate(prob, normal, anisotropic))
    return best[1], best[2], best[3]


# --- the methods -----------------------------------------------------------------------------------------
def _auto_chunk(leds: int) -> int:
    """Texels a chunk holds when FitConfig.batch is None: AUTO_CHUNK_PAIRS texel-LED pairs."""
    return max(1, AUTO_CHUNK_PAIRS // max(leds, 1))


def _chunk_size(prob: _Problem, size: int | None) -> int:
    """`size`, or None: _auto_chunk's texels (at most all of them)."""
    return size or min(prob.n, _auto_chunk(prob.leds))


def _chunks(prob: _Problem, size: int | None, count: int | None = None):
    """Contiguous index ranges of at most `size` (None: AUTO_CHUNK_PAIRS texel-LED pairs a range) over the texels,
    or over `count` rows."""
    return torch.arange(prob.n if count is None else count, device=prob.pos.device).split(_chunk_size(prob, size))


def _result(prob: _Problem, geom: dict, rho_d, rho_s, history, t_start, info) -> FitResult:
    out = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in {**geom, "rho_d": rho_d, "rho_s": rho_s}.items()}
    info = {"method": prob.config.method, "loss": prob.config.loss, "config": asdict(prob.config), **info}
    return FitResult(**out, history=[float(h) for h in history], seconds=time.perf_counter() - t_start, info=info)


def _forward_difference(prob: _Problem, q: torch.Tensor, r: torch.Tensor, to_numbers=None) -> torch.Tensor:
    """(n, 5, residuals) forward-difference Jacobian (FitConfig.fd_step) of _residuals at q, whose value is r, row j
    the derivative along number j; with `to_numbers`, of _residuals(to_numbers(q)) (another parameterisation of
    the same 5 numbers)."""
    h = prob.config.fd_step
    eye = torch.eye(GEOMETRY_SIZE, dtype=q.dtype, device=q.device) * h
    f = to_numbers or (lambda x: x)
    return torch.stack([(_residuals(prob, f(q + eye[j])) - r) / h for j in range(GEOMETRY_SIZE)], 1)


def _frame_derivatives(prob: _Problem, q: torch.Tensor) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The geometry of the numbers q and the inputs of twin.optics.jvp.basis_jvp for the 5 numbers' directions:
    d_frame (n, 5, 3, 3), the derivatives of the local frame's rows (t, n x t, n) along u, v, theta (zero along
    the log alphas), and d_log_alpha (n, 5, 2). In closed form, the chain rule through _frame_of's steps (ours:
    torch.func's batched forward mode took 9 ms a call for 2,304 texels on one CPU thread, this 3 ms;
    tests/test_fitting.py checks it against torch.func.jacfwd of _frame_of)."""
    n_tex = q.shape[0]
    N, X, Y = (f.expand(n_tex, 3) for f in prob.frame)

    def dot(a, b):
        return (a * b).sum(-1, keepdim=True)

    def cross(a, b):
        return torch.linalg.cross(a, b, dim=-1)

    f = _frame_steps(q, prob.frame)
    n, t0, nt0, t, tl, tangent = (f[k] for k in ("normal", "t0", "nt0", "t", "tl", "tangent"))
    cos, sin = f["cos"], f["sin"]
    k, c = cross(N, n), dot(n, N)  # _base_tangent's Rodrigues rotation
    kx = dot(k, X)

    def rows(dn, dt):
        """The frame rows' derivatives for the derivatives dn of n and dt of the unprojected tangent t."""
        dtp = dt - (dot(dt, n) + dot(t, dn)) * n - dot(t, n) * dn
        dtan = (dtp - tangent * dot(tangent, dtp)) / tl
        return torch.stack([dtan, cross(dn, tangent) + cross(n, dtan), dn], 1)

    d_frame = torch.zeros(n_tex, GEOMETRY_SIZE, 3, 3, dtype=q.dtype, device=q.device)
    for j, axis in enumerate((X, Y)):  # u, v: n moves, and t0 with it
        dn = (axis - n * dot(n, axis)) / f["pn"]
        dk, dc = cross(N, dn), dot(dn, N)
        dt0 = X * dc + cross(dk, X) + dk * (kx / (1 + c)) + k * (dot(dk, X) / (1 + c) - kx * dc / (1 + c) ** 2)
        d_frame[:, j] = rows(dn, cos * dt0 + sin * (cross(dn, t0) + cross(n, dt0)))
    d_frame[:, 2] = rows(torch.zeros_like(n), cos * nt0 - sin * t0)  # theta turns t about n
    d_log_alpha = torch.zeros(n_tex, GEOMETRY_SIZE, 2, dtype=q.dtype, device=q.device)
    d_log_alpha[:, 3, 0] = d_log_alpha[:, 4, 1] = 1.0
    return _log_geometry(q, prob.frame, f), d_frame, d_log_alpha


def _albedo_derivatives(sums: list, dsums: list, a: torch.Tensor, b: torch.Tensor, rho_s_max: float):
    """(da, db) (n, J, 3) of the closed-form albedos (_solve_box) along J directions, from the quadratic's sums
    (dd, dm, ds, ss, sm) (n, 3) and their derivatives (n, J, 3): the minimiser's own derivative (variable
    projection, Golub & Pereyra 1973), by the implicit function theorem on the free coordinates, 0 for one that
    sits on its box edge."""
    dtype = a.dtype
    dd, dm, ds, ss, sm = (x[:, None].double() for x in sums)
    ddd, ddm, dds, dss, dsm = (x.double() for x in dsums)
    a, b = a[:, None].double(), b[:, None].double()
    r1 = ddm - a * ddd - b * dds  # d(dm) - d(dd) a - d(ds) b
    r2 = dsm - a * dds - b * dss
    a_free = (a > 0) & (a < 1)
    b_free = (b > 0) & (b < rho_s_max)
    det = (dd * ss - ds * ds).clamp_min(1e-30)
    both = a_free & b_free
    da = torch.where(both, (ss * r1 - ds * r2) / det, torch.where(a_free, r1 / dd.clamp_min(1e-30), 0.0))
    db = torch.where(both, (dd * r2 - ds * r1) / det, torch.where(b_free, r2 / ss.clamp_min(1e-30), 0.0))
    return da.to(dtype), db.to(dtype)


def _number_bases(prob: _Problem, q: torch.Tensor):
    """camera -> its grey bases val (2, n, L) and their derivatives dD0, dS0 (n, 5, L) along the direct method's
    5 numbers [u, v, theta, log alpha_x, log alpha_y] at q (_grey with _frame_derivatives): _linearisation's
    bases."""
    geom, d_frame, d_log_alpha = _frame_derivatives(prob, q)
    return lambda camera: _grey(prob, geom, camera, (d_frame, d_log_alpha))


def _isotropic_bases(prob: _Problem, x: torch.Tensor):
    """camera -> the grey bases and their derivatives along the joint prior's tensor coordinates x = [u, v, m, c,
    s] (_to_tensor) at the isotropic lobe (c = s = 0; x's own c, s are not read), where the chain rule through the
    tangent angle (_tensor_system) divides by d = 0. With c + i s = d e^(2 i theta), the lobe's derivative along
    c is that of log alpha_x - log alpha_y at theta = 0, along s the same at theta = pi / 4, and along m that of
    both log alphas; an isotropic lobe is the same at any theta, so the bases are those at theta = 0. Exact at c =
    s = 0, for two launches of basis_jvp per camera (the second for the one direction s), where forward
    differences took six evaluations of the residuals (ours, issue #12)."""
    zero = torch.zeros_like(x[:, 0])
    q = torch.stack([x[:, 0], x[:, 1], zero, x[:, 2], x[:, 2]], 1)
    geom, d_frame, _ = _frame_derivatives(prob, q)
    turned = _log_geometry(q + q.new_tensor([0.0, 0.0, math.pi / 4, 0.0, 0.0]), prob.frame)
    d_frame = torch.cat([d_frame[:, :2], torch.zeros_like(d_frame[:, :2])], 1)  # u, v; m and c turn no frame row
    d_log_alpha = q.new_tensor([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0], [1.0, -1.0]]).expand(q.shape[0], 4, 2)
    along_s = (q.new_zeros(q.shape[0], 1, 3, 3), q.new_tensor([[[1.0, -1.0]]]).expand(q.shape[0], 1, 2))

    def bases(camera):
        val, dD, dS = _grey(prob, geom, camera, (d_frame, d_log_alpha))
        _, dD_s, dS_s = _grey(prob, turned, camera, along_s)
        return val, torch.cat([dD, dD_s], 1), torch.cat([dS, dS_s], 1)

    return bases


def _linearisation(prob: _Problem, bases):
    """What the analytic Jacobian of _residuals is made of, for `bases` (_number_bases at the numbers q, or
    _isotropic_bases): the bases' derivatives from basis_jvp per camera, the closed-form albedos' derivatives
    (_albedo_derivatives), the chain rule through the projections onto the photos' weights and the loss's
    transform. Costs about one evaluation of the forward model per camera where the forward difference takes five
    (FitConfig.jacobian). Returns config.camera's grey bases val (2, n, L) and their derivatives dD0, dS0 (n, 5,
    L), the shared albedos rd, rs (n, 3) and their derivatives da, db (n, 5, 3), and each photo group's residuals
    (n, 3 K) and Jacobian rows (n, 5, 3 K), along the 5 directions of `bases`."""
    from twin.optics.torch_ops import tf32_products

    c = prob.config
    photos = prob.photos if prob.has_lines else ()
    pb, dpb = [None] * len(photos), [None] * len(photos)

    def project(cam, bases):
        """Each photo group of camera cam: (W D, W S) and their derivatives (dWD, dWS), (3, n, 5, K) each."""
        for i, g in enumerate(photos):
            if g.camera == cam:
                pb[i] = _photo_pair(prob, g, bases[0])
                with tf32_products(c.precision == "tf32"):  # FitConfig.precision: the system's direction only
                    dpb[i] = (_project_normal_rows(g, bases[1], prob.ratio[0]), _project(g, bases[2], prob.ratio[1]))

    # another camera's bases are projected and freed before config.camera's are computed: a view's bases and their
    # derivatives are 12 floats a texel-LED pair (9.7 GB for a chunk of 16,384 paper texels), and both views' at once
    # were most of a chunk's memory: a system of such a chunk allocated 19.9 GiB, now 10.8 GiB (ours, issue #12)
    for cam in dict.fromkeys(g.camera for g in photos if g.camera != c.camera):
        project(cam, bases(cam))
    val, dD0, dS0 = bases(c.camera)
    project(c.camera, (val, dD0, dS0))
    sums, dsums = _albedo_sums(prob, val, pb, (dD0, dS0, dpb))
    rd, rs, own = _projected(prob, val, pb, sums)
    da, db = _albedo_derivatives(sums, dsums, rd, rs, c.rho_s_max)
    photo_J = []
    for g, (WD, WS), (dWD, dWS), (a, b) in zip(photos, pb, dpb, own):
        if g.camera == c.camera:
            ga, gb = da, db
        else:  # its own albedos (_projected), and their own derivatives
            ga, gb = _albedo_derivatives(_photo_terms(g, WD, WS), _photo_dterms(g, WD, WS, dWD, dWS), a, b,
                                         c.rho_s_max)
        M_hat = a.T[:, :, None] * WD + b.T[:, :, None] * WS
        dM = (ga.permute(2, 0, 1)[..., None] * WD[:, :, None] + gb.permute(2, 0, 1)[..., None] * WS[:, :, None]
              + a.T[:, :, None, None] * dWD + b.T[:, :, None, None] * dWS)  # (3, n, J, K)
        fpm = _df(M_hat, c.loss, g.scale) * math.sqrt(g.lam / M_hat[:, 0].numel())
        photo_J.append((fpm[:, :, None] * dM).permute(1, 2, 0, 3).reshape(prob.n, GEOMETRY_SIZE, -1))
    return val, dD0, dS0, rd, rs, da, db, _photo_residuals(prob, _predicted(pb, own)), photo_J


def _analytic_jacobian(prob: _Problem, q: torch.Tensor) -> torch.Tensor:
    """(n, 5, residuals) Jacobian of _residuals at q, exact (_linearisation), every row stored: what
    `hemicube bench fit-jacobian` and the tests check against central differences; the fit itself takes the
    Gauss-Newton system without the rows (_normal_equations)."""
    val, dD0, dS0, rd, rs, da, db, _, photo_J = _linearisation(prob, _number_bases(prob, q))
    c, ratio = prob.config, prob.ratio
    D, S = _split(prob, val)
    m_hat = rd[:, None] * D + rs[:, None] * S
    fp = _df(m_hat, c.loss, prob.scale_m) / math.sqrt(m_hat[0].numel())
    # (n, J, L, 3): f'(m_hat) d m_hat = f'(m_hat) (da D + rd dD + db S + rs dS), in place (the largest tensor here)
    dm = torch.mul(dD0[..., None], (rd[:, None] * ratio[0])[:, None])
    dm.addcmul_(dS0[..., None], (rs[:, None] * ratio[1])[:, None])
    dm.addcmul_(da[:, :, None], D[:, None]).addcmul_(db[:, :, None], S[:, None]).mul_(fp[:, None])
    return torch.cat([dm.reshape(prob.n, GEOMETRY_SIZE, -1), *photo_J], dim=2)


def _normal_equations(prob: _Problem, q: torch.Tensor) -> tuple:
    """(J J^T (n, 5, 5), J r (n, 5), the loss r.r (n,)) of the residuals r = _residuals at q and their analytic
    Jacobian J along the 5 numbers (_bases_system of _number_bases)."""
    return _bases_system(prob, _number_bases(prob, q))


def _bases_system(prob: _Problem, bases) -> tuple:
    """(J J^T (n, 5, 5), J r (n, 5), the loss r.r (n,)) of the residuals and their analytic Jacobian J along the 5
    directions of `bases` (_linearisation). The lumitexels' share, 3 L rows of 5 a texel, is summed in one Warp
    launch that never stores them (reconstruction.stages.fit_sums.lumitexel_terms); the photos' few rows in torch."""
    val, dD0, dS0, rd, rs, da, db, photo_r, photo_J = _linearisation(prob, bases)
    loss, A, g = fit_sums.lumitexel_terms(val, prob.target, prob.ratio, rd, rs, prob.config.loss, prob.scale_m,
                                          dD0, dS0, da, db)
    for r, J in zip(photo_r, photo_J):
        A = A + J @ J.transpose(1, 2)
        g = g + (J @ r[..., None])[..., 0]
        loss = loss + r.square().sum(1)
    return A, g, loss


def _photo_dterms(g: _Photos, WD, WS, dWD, dWS) -> list:
    """The derivatives (n, J, 3) of a photo group's share of the albedo sums (_photo_terms) along J directions,
    for photo bases (3, n, K) and their derivatives (3, n, J, K)."""
    Mw, M = g.M_w[:, :, None], g.M[:, :, None]
    WD, WS = WD[:, :, None], WS[:, :, None]
    return [(x * Mw).sum(3).permute(1, 2, 0) for x in (2 * WD * dWD, dWD * M, dWD * WS + WD * dWS, 2 * WS * dWS,
                                                         dWS * M)]


def _difference_system(prob: _Problem, q: torch.Tensor, to_numbers=None) -> tuple:
    """(J J^T, J r, r.r) of _residuals at q (at to_numbers(q), with `to_numbers`) by forward differences
    (_forward_difference)."""
    r = _residuals(prob, to_numbers(q) if to_numbers else q)
    J = _forward_difference(prob, q, r, to_numbers)
    return J @ J.transpose(1, 2), (J @ r[..., None])[..., 0], r.square().sum(1)


def _system(prob: _Problem, q: torch.Tensor) -> tuple:
    """(J J^T (n, 5, 5), J r (n, 5), the loss r.r (n,)): the Gauss-Newton system of _residuals at the numbers q, with
    the Jacobian that FitConfig.jacobian asks for."""
    if prob.config.jacobian == "analytic":
        return _normal_equations(prob, q)
    return _difference_system(prob, q)


def _levenberg_marquardt(prob: _Problem, q: torch.Tensor, history: np.ndarray) -> torch.Tensor:
    """Levenberg-Marquardt on the numbers q (n, 5) = [u, v, theta, log alpha_x, log alpha_y] of every texel at
    once (texels are independent: each has its own 5 x 5 system and damping mu). The Jacobian of the residuals
    (_residuals, the closed-form albedos re-solved at every evaluation: variable projection) is analytic or by
    forward differences, 5 more evaluations of the residuals per iteration (FitConfig.jacobian). A step is
    kept where it lowers the texel's loss (then mu / 3), else refused (mu x 4; Marquardt's scaling by the
    diagonal, plus a floor for the tangent angle of an isotropic texel, which moves nothing). A trial step is
    evaluated with its Gauss-Newton system (_system: the loss comes with it), which a kept step then uses and a
    refused one drops, keeping the texel's last: a loss and then a kept step's system evaluated the forward model
    and decoded the lumitexels twice, and most steps are kept. log alpha is clamped to alpha_range after each
    step. Texels whose last kept step changed their loss by less than FitConfig.tolerance (relative) or whose mu
    exceeds 1e10 drop out. history[i] += the sum of the losses after iteration i."""
    c = prob.config
    lo, hi = (math.log(a) for a in c.alpha_range)
    q = q.clone()
    q[:, 3:5] = q[:, 3:5].clamp(lo, hi)
    if not c.steps:  # the initialisation alone (FitConfig.iterations = 0): no system to take
        return q
    with torch.no_grad():
        AA, gg, loss = _system(prob, q)
        mu = torch.full_like(loss, c.lm_damping)
        active = torch.ones_like(loss, dtype=torch.bool)
        for i in range(c.steps):
            idx = torch.nonzero(active).flatten()
            if idx.numel():
                part, qa = prob.part(idx), q[idx]
                A, grad = AA[idx], gg[idx]
                d = torch.diagonal(A, dim1=1, dim2=2)
                damp = mu[idx, None] * (d + 1e-6 * d.sum(1, keepdim=True) + 1e-20)
                step = torch.linalg.solve(A + torch.diag_embed(damp), -grad[..., None])[..., 0]
                qn = qa + step
                qn[:, 3:5] = qn[:, 3:5].clamp(lo, hi)
                An, gn, ln = _system(part, qn)
                ok = torch.isfinite(ln) & (ln < loss[idx])
                gain = (loss[idx] - ln) / loss[idx].clamp_min(1e-30)
                q[idx] = torch.where(ok[:, None], qn, qa)
                loss[idx] = torch.where(ok, ln, loss[idx])
                AA[idx] = torch.where(ok[:, None, None], An, A)
                gg[idx] = torch.where(ok[:, None], gn, grad)
                mu[idx] = torch.where(ok, mu[idx] / 3, mu[idx] * 4)
                active[idx] = ~((ok & (gain < c.tolerance)) | (mu[idx] > 1e10))
            history[i] += float(loss.sum())
    return q


def _losses(prob: _Problem, q: torch.Tensor, texels: torch.Tensor | None = None) -> torch.Tensor:
    """(n,) per-texel loss of the direct method's numbers q (n, 5), in chunks of `batch` texels; with `texels` (n,),
    q's rows are those texels' (a chunk's lumitexels are asked for when it is evaluated, never all at once)."""
    with torch.no_grad():
        return torch.cat([_loss(prob.part(i if texels is None else texels[i]), q[i])
                          for i in _chunks(prob, prob.config.batch, q.shape[0])])


def _propagate(prob: _Problem, q: torch.Tensor, grid_shape, changed: torch.Tensor | None = None):
    """One round of neighbour propagation (ours, as PatchMatch propagates matches): each texel tries the
    fitted numbers of its 4 grid neighbours; where one lowers its loss by more than 0.1%, Levenberg-Marquardt
    restarts from it. Why: LM from the initial candidates lands in a local minimum on a few % of the texels
    of strongly anisotropic or narrow-lobed samples (a rotated tangent, a swapped roughness), isolated texels
    whose neighbours, of the same material, hold the right basin. `changed` (n,) bool: the texels the round
    before restarted (None: the first round, every texel); only those and their neighbours are tried, since
    every other texel would compare the same numbers as that round did and decide as it did (ramps at 1024^2 on
    the paper rig restarts ~0.4% of its texels in the first round, and a second round over all of them cost 20 s
    of an H100). Returns (q, texels restarted, the mask of those texels)."""
    R, C = (int(v) for v in grid_shape)
    rows, cols = torch.arange(R, device=q.device), torch.arange(C, device=q.device)
    shifts = ((1, 0), (-1, 0), (0, 1), (0, -1))

    def shifted(grid, dr, dc):  # each texel's neighbour along (dr, dc), itself at the edge
        return grid[(rows + dr).clamp(0, R - 1)][:, (cols + dc).clamp(0, C - 1)].reshape(R * C, *grid.shape[2:])

    if changed is None:
        region = torch.arange(prob.n, device=q.device)
    else:
        c = changed.reshape(R, C)
        near = changed.clone()
        for dr, dc in shifts:
            near |= shifted(c, dr, dc)
        region = torch.nonzero(near).flatten()
    own = _losses(prob, q[region], region)
    best, best_loss = q[region].clone(), own.clone()
    grid = q.reshape(R, C, GEOMETRY_SIZE)
    for dr, dc in shifts:
        cand = shifted(grid, dr, dc)[region]
        loss = _losses(prob, cand, region)
        better = loss < best_loss
        best, best_loss = torch.where(better[:, None], cand, best), torch.where(better, loss, best_loss)
    sel = torch.nonzero(best_loss < own * (1 - 1e-3)).flatten()
    moved = region[sel]
    # restarted in chunks like every other pass: paper stock at 1024^2 restarts so many texels that all at once
    # asked an H100 for 26 GB more than it had (2026-11-26)
    for k in (sel.split(_chunk_size(prob, prob.config.batch)) if sel.numel() else ()):
        idx = region[k]
        q[idx] = _levenberg_marquardt(prob.part(idx), best[k], np.zeros(prob.config.steps))
    mask = torch.zeros(prob.n, dtype=torch.bool, device=q.device)
    mask[moved] = True
    return q, int(moved.numel()), mask


def _final(prob: _Problem, q: torch.Tensor, sums: list | None = None) -> list:
    """Per chunk of texels: (geometry, loss, rho_d, rho_s) of the numbers q with their closed-form albedos;
    with a list `sums`, each chunk's albedo sums (_albedo_sums) are appended to it."""
    parts = []
    with torch.no_grad():
        for idx in _chunks(prob, prob.config.batch):
            geom = _log_geometry(q[idx], prob.frame)
            parts.append((geom, *_projected_loss(prob.part(idx), geom, sums)))
    return parts


def _to_tensor(q: torch.Tensor) -> torch.Tensor:
    """[u, v, theta, log alpha_x, log alpha_y] -> [u, v, m, d cos 2 theta, d sin 2 theta], m and d the mean and
    half difference of the log alphas: the log roughness tensor's coordinates, which do not depend on which
    axis is called the tangent (an isotropic lobe is d = 0 at any theta; a lobe and its 90-degree turn with
    the alphas swapped are one point)."""
    m, d = (q[:, 3] + q[:, 4]) / 2, (q[:, 3] - q[:, 4]) / 2
    return torch.stack([q[:, 0], q[:, 1], m, d * torch.cos(2 * q[:, 2]), d * torch.sin(2 * q[:, 2])], 1)


def _from_tensor(x: torch.Tensor) -> torch.Tensor:
    """The inverse of _to_tensor (theta in (-pi/2, pi/2], alpha_x >= alpha_y)."""
    d = torch.hypot(x[:, 3], x[:, 4])
    return torch.stack([x[:, 0], x[:, 1], torch.atan2(x[:, 4], x[:, 3]) / 2, x[:, 2] + d, x[:, 2] - d], 1)


def _tensor_system(prob: _Problem, x: torch.Tensor) -> tuple:
    """(J J^T, J r, r.r) of the residuals r = _residuals(_from_tensor(x)) in the tensor coordinates x, J their
    Jacobian there. The analytic one (FitConfig.jacobian) by the chain rule through _from_tensor (J = dq/dx^T J_q,
    so J J^T = dq/dx^T (J_q J_q^T) dq/dx), whose angle is undefined where the lobe is isotropic (d = 0): there, for
    d < 1e-4, the system of the isotropic lobe at [u, v, m, 0, 0] (_isotropic_bases; its error at such d is O(d),
    the chain rule's float32's epsilon / d relative, from the tangent angle's 1 / d); the loss is x's own."""
    if prob.config.jacobian != "analytic":
        return _difference_system(prob, x, _from_tensor)
    q = _from_tensor(x)
    d = torch.hypot(x[:, 3], x[:, 4])
    ds = d.clamp_min(1e-30)
    cos, sin = x[:, 3] / ds, x[:, 4] / ds
    dq = torch.zeros(x.shape[0], GEOMETRY_SIZE, GEOMETRY_SIZE, dtype=x.dtype, device=x.device)  # dq_j / dx_k
    dq[:, 0, 0] = dq[:, 1, 1] = dq[:, 3, 2] = dq[:, 4, 2] = 1.0
    dq[:, 2, 3], dq[:, 2, 4] = -sin / (2 * ds), cos / (2 * ds)  # theta = atan2(s, c) / 2
    dq[:, 3, 3], dq[:, 3, 4], dq[:, 4, 3], dq[:, 4, 4] = cos, sin, -cos, -sin  # m +- hypot(c, s)
    A, g, loss = _normal_equations(prob, q)
    A = dq.transpose(1, 2) @ A @ dq
    g = (dq.transpose(1, 2) @ g[..., None])[..., 0]
    near = torch.nonzero(d < 1e-4).flatten()
    if near.numel():
        part = prob.part(near)
        A[near], g[near], _ = _bases_system(part, _isotropic_bases(part, x[near]))
    return A, g, loss


def _residual_count(prob: _Problem) -> int:
    """The number of residuals of a texel (_residuals): 3 per LED and per photo."""
    return 3 * prob.leds + sum(3 * int(g.W.shape[2]) for g in (prob.photos if prob.has_lines else ()))


def _colour_weights(rho_d: torch.Tensor, grid_shape, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The prior's 4-neighbour weights lam w_ij on the grid: (R-1, C) between rows i and i+1, (R, C-1) between
    columns, w_ij = exp(-mean_c (log(rho_d_i + 0.02) - log(rho_d_j + 0.02))^2 / (2 0.1^2)): 1 within one
    diffuse colour, ~0 across a change of material (a printed edge, a ring, a stripe)."""
    R, C = grid_shape
    logd = torch.log(rho_d.double() + 0.02).reshape(R, C, 3)
    return (lam * torch.exp(-(logd[1:] - logd[:-1]).square().mean(-1) / (2 * 0.1 ** 2)),
            lam * torch.exp(-(logd[:, 1:] - logd[:, :-1]).square().mean(-1) / (2 * 0.1 ** 2)))


def _laplacian(x: torch.Tensor, weights, grid_shape) -> torch.Tensor:
    """L_w x for the weighted grid Laplacian of weights (_colour_weights), x (R C, k) row-major:
    (L_w x)_i = sum_j w_ij (x_i - x_j)."""
    R, C = grid_shape
    g = x.reshape(R, C, -1)
    out = torch.zeros_like(g)
    for w, dim in zip(weights, (0, 1)):
        n = g.shape[dim] - 1
        d = w[..., None] * (g.narrow(dim, 1, n) - g.narrow(dim, 0, n))
        out.narrow(dim, 1, n).add_(d)
        out.narrow(dim, 0, n).sub_(d)
    return out.reshape(x.shape)


def _block_pcg(blocks: torch.Tensor, weights, grid_shape, b: torch.Tensor, prior_dims: slice, iterations: int):
    """Solve (blockdiag(blocks) + L_w on the coordinates prior_dims) x = b by conjugate gradients with the
    block-Jacobi preconditioner. blocks (n, k, k) SPD, b (n, k). Returns (x, iterations used)."""
    k = blocks.shape[1]
    E = torch.zeros(k, device=b.device, dtype=b.dtype)
    E[prior_dims] = 1.0

    def apply(x):
        return (blocks @ x[..., None])[..., 0] + E * _laplacian(x, weights, grid_shape)

    deg = _degree(weights, grid_shape).reshape(-1, 1, 1)
    M_inv = torch.linalg.inv(blocks + deg * torch.diag(E))
    x = torch.zeros_like(b)
    r = b.clone()
    z = (M_inv @ r[..., None])[..., 0]
    p = z.clone()
    rz, rr0, it = float((r * z).sum()), float((r * r).sum()), 0
    while it < iterations and float((r * r).sum()) > 1e-20 * max(rr0, 1e-300):
        Ap = apply(p)
        step = rz / float((p * Ap).sum())
        x += step * p
        r -= step * Ap
        z = (M_inv @ r[..., None])[..., 0]
        rz, rz_old = float((r * z).sum()), rz
        p = z + (rz / rz_old) * p
        it += 1
    return x, it


def _degree(weights, grid_shape) -> torch.Tensor:
    """(R, C) sum_j w_ij of each texel."""
    R, C = grid_shape
    w_down, w_right = weights
    deg = torch.zeros(R, C, dtype=w_down.dtype, device=w_down.device)
    deg[1:] += w_down
    deg[:-1] += w_down
    deg[:, 1:] += w_right
    deg[:, :-1] += w_right
    return deg


def _pinned(H: torch.Tensor, tau: float) -> torch.Tensor:
    """(n,) bool: the texels whose own photos pin their mean log alpha to within tau / 4 (one standard deviation,
    from the Gauss-Newton block H (n, 5, 5) of unit-variance residuals at [u, v, m, c, s], the normal's two numbers
    free): their neighbours' roughness could move them by a small fraction of tau at most, so the joint prior
    leaves them where their own fit put them (_joint_roughness)."""
    A, B, C = H[:, 2:, 2:], H[:, 2:, :2], H[:, :2, :2]
    eye2 = torch.eye(2, dtype=H.dtype, device=H.device)
    S = A - B @ torch.linalg.solve(C + 1e-12 * (torch.diagonal(C, dim1=1, dim2=2).sum(1)[:, None, None] + 1) * eye2,
                                   B.transpose(1, 2))
    S = S + 1e-12 * (torch.diagonal(S, dim1=1, dim2=2).sum(1)[:, None, None] + 1) * torch.eye(3, dtype=H.dtype,
                                                                                             device=H.device)
    var = torch.linalg.inv(S)[:, 0, 0]
    return torch.isfinite(var) & (var > 0) & (var < (tau / 4) ** 2)


def _joint_roughness(prob: _Problem, q: torch.Tensor, rho_d: torch.Tensor, grid_shape, resume: dict | None = None,
                     save=None) -> tuple[torch.Tensor, dict]:
    """All texels' numbers at once under a smoothness prior on the roughness (ours, issue #14;
    FitConfig.alpha_prior = tau). Minimises, over x_i = [u, v, m, c, s] (_to_tensor: the normal's two numbers,
    the mean log alpha and the anisotropy as a vector at twice the tangent angle, so that neighbours compare
    lobes, not axis labels),
        F = sum_i |r_i(x_i)|^2 / sigma^2 + sum_{i~j} w_ij |a_i - a_j|^2 / tau^2,   a = [m, c, s],
    r_i the texel's residuals (_residuals: its photos and lumitexel, albedos in closed form), sigma^2 their
    median per-texel variance at the start (this capture's noise and misfit level), i~j 4-neighbours weighted
    by their diffuse colour's likeness (_colour_weights), by Levenberg-Marquardt on the joint problem: the
    per-texel 5 x 5 Gauss-Newton blocks coupled by the prior's grid Laplacian, each step solved by block
    conjugate gradients (_block_pcg). A texel with a clear lobe keeps its own roughness; one whose photos
    barely see the lobe takes its material's. Why: on the mini rig a rough, weak lobe is 0.5-2% of a photo
    (issue #14's fabric and paper), about the per-texel noise of the extracted photos (0.4%), so a texel's own
    fit errs by 15-60% and noise turns an isotropic lobe anisotropic, while the noise-free oracle fit is exact
    (docs/accuracy.md). The photos of a region are pooled, not its per-texel estimates, which noise biases.

    How it is solved, and why (docs/accuracy.md, step 15: paper's stock ended 0.2 low in log alpha because this loop
    stopped far from F's minimum, not because F put it there):
    - The texels whose own photos pin their roughness (_pinned, at the start: a sharp lobe, ink and foil) stay where
      their own fit put them; they still enter F and hold their neighbours through the prior, and only the others
      are evaluated again. Their lobes are the most nonlinear in x, and a step that overshot one of them refused
      the whole trial.
    - A damping mu_i per texel (Marquardt's, scaled by the block's diagonal): after a trial, a texel whose data term
      changed as its Gauss-Newton model predicted (to half the prediction) divides its mu by 3, any other doubles
      it; a refused trial (F did not fall) multiplies the latter's by 4 (every texel's, if each held). With one mu
      for all, the worst-modelled texel set it for all, and the flat directions of the weak lobes, where the pooled
      roughness moves by a small fraction of its distance a step, were damped still.
    - It stops when a kept trial lowers F by less than FitConfig.tolerance times n (R_i - 5), F's size were every
      texel fitted to its noise (R_i residuals a texel), not times F, which the misfit of a few mixed texels (a
      printed edge's) can make a hundred times that.
    `resume`: the state a killed run saved (_fit_direct's checkpoint), from which the loop goes on as it would have;
    `save(state)` is called after every trial. Returns (q, info); info's joint_trials lists each trial's [median mu
    of the free texels, its relative change of F, the share of free texels whose model held] (a refused one's change
    >= 0), joint_pinned the count of pinned texels."""
    c = prob.config
    R, C = (int(v) for v in grid_shape)
    weights = _colour_weights(rho_d, (R, C), 1.0 / c.alpha_prior ** 2)
    prior_dims = slice(2, 5)
    x = _to_tensor(q).double()
    lo, hi = (math.log(v) for v in c.alpha_range)
    dof = max(_residual_count(prob) - GEOMETRY_SIZE, 1)

    def data(x, texels: torch.Tensor, jac: bool = True):
        """Per chunk of the texels (only the 5 x 5 normal equations are kept, not the Jacobians: the paper rig's
        residuals are 3 x 12,288 + photos per texel): each one's sum of squared residuals, the Gauss-Newton
        blocks J^T J and gradients J^T r (None without jac)."""
        rows, Hs, gs = [], [], []
        with torch.no_grad():
            for idx in texels.split(_chunk_size(prob, c.batch)):
                part, xi = prob.part(idx), x[idx].float()
                if jac:
                    H, g, loss = _tensor_system(part, xi)
                    Hs.append(H.double())
                    gs.append(g.double())
                else:
                    loss = _loss(part, _from_tensor(xi))
                rows.append(loss.double())
        return torch.cat(rows), torch.cat(Hs) if jac else None, torch.cat(gs) if jac else None

    def prior(x):
        a = x[:, prior_dims]
        return float((a * _laplacian(a, weights, (R, C))).sum())  # sum_{i~j} w_ij |a_i - a_j|^2

    every = torch.arange(x.shape[0], device=x.device)
    if resume is None:
        rows, JJ, Jr = data(x, every)
        sigma2 = float((rows / dof).median().clamp_min(1e-30))
        F = float(rows.sum()) / sigma2 + prior(x)
        frozen = _pinned(JJ / sigma2, c.alpha_prior)
        mu = torch.full((x.shape[0],), c.lm_damping, dtype=torch.float64, device=x.device)
        F0, kept, cg, tried, trials = F, 0, 0, 0, []
    else:  # the same numbers the loop held when they were saved; the system at x is recomputed (deterministic)
        x = torch.as_tensor(resume["x"], dtype=torch.float64, device=x.device)
        sigma2, F, F0, kept, cg, tried = (resume[k] for k in ("sigma2", "F", "F0", "kept", "cg", "tried"))
        trials = list(resume.get("trials", []))
        rows, JJ, Jr = data(x, every) if tried < c.steps and not resume["done"] else (None,) * 3
        # a state saved before the damping per texel holds one mu and no pinned texels: it goes on with both
        mu = torch.as_tensor(np.broadcast_to(np.asarray(resume["mu"], np.float64), (x.shape[0],)).copy(),
                             device=x.device)
        frozen = (torch.as_tensor(np.asarray(resume["frozen"]), device=x.device) if "frozen" in resume
                  else torch.zeros(x.shape[0], dtype=torch.bool, device=x.device))
    done = resume is not None and resume["done"] or bool(frozen.all())
    free = (~frozen).double()[:, None]
    moving = torch.nonzero(~frozen).flatten()  # only these are evaluated again: the pinned ones' rows stay
    if resume is not None and kept and rows is not None:  # as the loop held them: the moving ones' from their own pass
        rows[moving], JJ[moving], Jr[moving] = data(x, moving)
    scale = dof * x.shape[0]

    def state():
        return {"x": x.cpu().numpy(), "sigma2": sigma2, "F": F, "F0": F0, "mu": mu.cpu().numpy(), "kept": kept,
                "cg": cg, "tried": tried, "done": done, "trials": trials, "frozen": frozen.cpu().numpy()}

    while not done and tried < c.steps:
        tried += 1
        H = JJ / sigma2
        g_data = Jr / sigma2
        g = g_data.clone()
        g[:, prior_dims] += _laplacian(x[:, prior_dims], weights, (R, C))
        d = torch.diagonal(H, dim1=1, dim2=2)
        H_damped = H + torch.diag_embed(mu[:, None] * (d + 1e-6 * d.sum(1, keepdim=True)) + 1e-12)
        # a pinned texel's block made rigid: its step is 0 and its neighbours see it fixed
        H_damped[frozen] = torch.eye(GEOMETRY_SIZE, dtype=H.dtype, device=H.device) * 1e30
        step, it = _block_pcg(H_damped, weights, (R, C), -g * free, prior_dims, 10 * (R + C))
        step = step * free
        cg += it
        xn = x + step
        # a trial step is evaluated by its loss alone, and a kept one's Gauss-Newton system computed after: at 1024^2
        # on the paper rig a pass of losses costs ~4 s and one of systems ~9 s (docs/performance.md, issue #12)
        rows_n = rows.clone()
        rows_n[moving] = data(xn, moving, False)[0]
        Fn = float(rows_n.sum()) / sigma2 + prior(xn)
        # each texel's data term: its actual decrease against its Gauss-Newton model's -(2 g.h + h H h)
        predicted = -(2 * (g_data * step).sum(1) + (step * (H @ step[..., None])[..., 0]).sum(1))
        actual = (rows - rows_n) / sigma2
        held = torch.isfinite(actual) & ((actual - predicted).abs() <= 0.5 * predicted.abs() + 1e-3)
        refused = not math.isfinite(Fn) or Fn >= F
        # (the loop runs only while some texel is free)
        trials.append([float(mu[moving].median()), Fn / F - 1 if math.isfinite(Fn) else None,
                       float(held[moving].double().mean())])
        if refused:
            mu = torch.where(held, mu, mu * 4) if not bool(held[moving].all()) else mu * 4
            done = bool((mu[moving] > 1e10).all())
        else:
            gain = (F - Fn) / scale
            x, F, kept = xn, Fn, kept + 1
            mu = torch.where(held, (mu / 3).clamp_min(1e-7), mu * 2)
            done = gain < c.tolerance
            if not done:
                rows[moving], JJ[moving], Jr[moving] = data(x, moving)
        if save is not None:
            save(state())
    out = _from_tensor(x.float())
    out[:, 3:5] = out[:, 3:5].clamp(lo, hi)
    return out, {"joint_steps": kept, "joint_cg_iterations": cg, "joint_objective": [F0, F],
                 "joint_sigma2": sigma2, "joint_trials": trials, "joint_pinned": int(frozen.sum())}


def _joint_albedos(prob: _Problem, sums: list, rho_d: torch.Tensor, rho_s: torch.Tensor, grid_shape,
                   sigma2: float) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The albedos of every texel at once, for the albedo quadratics `sums` (_albedo_sums per chunk of texels,
    from _final at the final geometry), under the same prior on rho_s as the roughness's
    (_joint_roughness; ours, issue #14): minimises
        sum_i Q_i(rho_d_i, rho_s_i) / sigma^2 + sum_{i~j} w_ij |rho_s_i - rho_s_j|^2 / (tau rho_ij)^2
    per channel, Q_i the texel's albedo quadratic (_albedo_sums, the loss to second order), w_ij the colour
    weights (_colour_weights), rho_ij the pair's mean grey rho_s from its own fit (>= 0.05): a relative change
    of tau between neighbours of one material. Linear, solved by block conjugate gradients (6 unknowns a
    texel), then clamped to the boxes. Why: once the roughness is pooled, a weak lobe's rho_s is still each
    texel's own, and its photos fix it no better than its roughness (fabric: rho_s 10-13%). Returns (rho_d,
    rho_s, conjugate-gradient iterations)."""
    c = prob.config
    R, C = (int(v) for v in grid_shape)
    dd, dm, ds, ss, sm = (torch.cat([x[k] for x in sums]).double() / sigma2 for k in range(5))
    dev = dd.device
    H = torch.zeros(R * C, 6, 6, dtype=torch.float64, device=dev)
    ch = torch.arange(3, device=dev)
    H[:, ch, ch], H[:, ch, ch + 3], H[:, ch + 3, ch], H[:, ch + 3, ch + 3] = dd, ds, ds, ss
    H += (1e-9 * torch.diagonal(H, dim1=1, dim2=2).sum(1) + 1e-30)[:, None, None] * torch.eye(6, dtype=H.dtype,
                                                                                               device=H.device)
    grey = rho_s.double().mean(1).reshape(R, C)
    w_down, w_right = _colour_weights(rho_d, (R, C), 1.0 / c.alpha_prior ** 2)
    scale = [((grey[1:] + grey[:-1]) / 2).clamp_min(0.05) ** 2, ((grey[:, 1:] + grey[:, :-1]) / 2).clamp_min(0.05) ** 2]
    x, it = _block_pcg(H, (w_down / scale[0], w_right / scale[1]), (R, C), torch.cat([dm, sm], 1), slice(3, 6),
                       10 * (R + C))
    return (x[:, :3].clamp(0.0, 1.0).to(rho_d.dtype), x[:, 3:].clamp(0.0, c.rho_s_max).to(rho_s.dtype), it)


# how often the direct fit's chunks save their state to a checkpoint (ours): a 1024^2 paper-rig fit takes minutes
# (docs/performance.md), a save of its numbers (5 floats a texel) a fraction of a second
CHECKPOINT_SECONDS = 30.0


def _resumed(checkpoint, prob: _Problem) -> dict | None:
    """The state a killed fit saved to `checkpoint` (_fit_direct), checked against this problem, or None."""
    state = checkpoint.load() if checkpoint is not None else None
    if state is None:
        return None
    q, hist = np.asarray(state.get("q")), np.asarray(state.get("history"))
    if (state.get("phase") not in ("chunks", "propagation", "joint") or q.shape != (prob.n, GEOMETRY_SIZE)
            or hist.shape != (prob.config.steps,) or not np.isfinite(q).all()
            or (state["phase"] == "joint" and np.shape(state.get("joint", {}).get("x")) != q.shape)
            or ("changed" in state and np.shape(state["changed"]) != (prob.n,))):
        raise ValueError("the fit's checkpoint does not belong to this fit (another texel count or iteration count, "
                         "or non-finite numbers); remove it to start the fit again")
    return state


def _fit_direct(prob: _Problem, grid_shape=None, checkpoint=None, start=None) -> FitResult:
    """Levenberg-Marquardt on the 5 geometry numbers per texel from the best initial candidate, with the
    albedos in closed form at every evaluation (module docstring), in chunks of `batch` texels; then, on a
    grid (grid_shape given), FitConfig.propagation rounds of neighbour propagation (_propagate), and the joint prior.
    info's texel_q holds the per-texel numbers before the joint prior (what a refit starts from).

    start: None, or a refit (q, redo) of the same texels after the photos of some changed: q (N, 5) an earlier
    fit's texel_q, redo (N,) bool the texels whose photos changed. Only those are fitted again, from their own
    initial candidates; every other texel keeps its numbers, which its unchanged photos would give again, and the
    propagation's first round starts from the refitted texels (ours, issue #14: the refit of the texels next to
    a brighter highlight, a few % of them, was a whole second fit).

    checkpoint: None, or an object with load() -> dict | None and save(dict) where the fit keeps its state as it
    goes: the numbers of the chunks fitted so far (at most every CHECKPOINT_SECONDS), after each propagation round,
    and after each step of the joint prior. A fit given the state a killed one saved goes on from there and ends
    with the same numbers as one that was never stopped (each chunk's fit depends on its own texels only, and the
    later phases on the numbers saved); the state's arrays are numpy, the rest JSON-able."""
    t_start = time.perf_counter()
    c = prob.config
    redo = None
    if start is not None:
        q_start, redo = np.asarray(start[0], np.float32), np.asarray(start[1])
        if q_start.shape != (prob.n, GEOMETRY_SIZE) or redo.shape != (prob.n,) or redo.dtype != bool \
                or not np.isfinite(q_start).all():
            raise ValueError(f"a refit's start must be an earlier fit's finite texel_q ({prob.n}, {GEOMETRY_SIZE}) "
                             f"and a boolean mask ({prob.n},) of the texels to fit again")
        redo = torch.as_tensor(redo, device=prob.pos.device)
    refitted = None if redo is None else int(redo.sum())
    state = _resumed(checkpoint, prob)
    if state is not None and state.get("refitted") != refitted:
        # another kind of fit's state under this key: a refit's saved before refits kept the other texels' numbers
        # (its chunks covered every texel), or a whole fit's; a refit takes seconds, so it starts again
        state = None
    if state is None:
        state = {"phase": "chunks", "chunks_done": 0,
                 "q": np.zeros((prob.n, GEOMETRY_SIZE), np.float32) if start is None else q_start.copy(),
                 "history": np.zeros(c.steps), "restarted": [], "refitted": refitted,
                 "seconds": {"init": 0.0, "iterations": 0.0, "propagation": 0.0, "joint": 0.0}}
    seconds = state["seconds"]
    history = np.array(state["history"], dtype=np.float64)
    q = torch.as_tensor(np.asarray(state["q"], np.float32), device=prob.pos.device)

    def save(**changes):
        if checkpoint is not None:
            state.update(changes, q=q.cpu().numpy(), history=history.copy(), seconds=seconds)
            checkpoint.save(state)

    last_save = time.perf_counter()
    chunks = _chunks(prob, c.batch) if redo is None else \
        [k for k in torch.nonzero(redo).flatten().split(_chunk_size(prob, c.batch)) if k.numel()]
    for k in range(state["chunks_done"] if state["phase"] == "chunks" else len(chunks), len(chunks)):
        idx = chunks[k]
        part = prob.part(idx)
        t0 = time.perf_counter()
        with torch.no_grad():
            g = _initial(part)[0]
            geom = _geometry(g, part.frame, c)
            q0 = torch.cat([g[:, :3], torch.log(geom["alpha_x"])[:, None], torch.log(geom["alpha_y"])[:, None]], 1)
        t1 = time.perf_counter()
        seconds["init"] += t1 - t0
        q[idx] = _levenberg_marquardt(part, q0, history)
        seconds["iterations"] += time.perf_counter() - t1
        if time.perf_counter() - last_save >= CHECKPOINT_SECONDS or k == len(chunks) - 1:
            save(chunks_done=k + 1, phase="chunks" if k < len(chunks) - 1 else "propagation")
            last_save = time.perf_counter()
    restarted = state["restarted"]
    if state["phase"] in ("chunks", "propagation"):
        changed = state.get("changed")  # None: the first round, or a checkpoint saved before rounds kept it
        # the first round tries every texel, a refit's only those next to the texels it fitted again
        changed = torch.as_tensor(np.asarray(changed), device=q.device) if restarted and changed is not None else redo
        for _ in range(c.propagation - len(restarted) if grid_shape is not None else 0):
            if (restarted and not restarted[-1]) or (changed is not None and not bool(changed.any())):
                break  # the last round moved nothing, or a refit fitted nothing again
            t2 = time.perf_counter()
            q, moved, changed = _propagate(prob, q, grid_shape, changed)
            restarted.append(moved)
            seconds["propagation"] += time.perf_counter() - t2
            save(restarted=restarted, changed=changed.cpu().numpy())
    t3 = time.perf_counter()
    texel_q = q.cpu().numpy().copy()
    parts = _final(prob, q)
    prior = {}
    joint_before = seconds["joint"]
    if grid_shape is not None and c.alpha_prior is not None:
        def save_joint(js):
            seconds["joint"] = joint_before + time.perf_counter() - t3
            save(phase="joint", joint=js)

        q, prior = _joint_roughness(prob, q, torch.cat([p[2] for p in parts]), grid_shape,
                                    state.get("joint") if state["phase"] == "joint" else None,
                                    save_joint if checkpoint is not None else None)
        sums = []
        parts = _final(prob, q, sums)
        rd, rs, prior["albedo_cg_iterations"] = _joint_albedos(prob, sums, torch.cat([p[2] for p in parts]),
                                                               torch.cat([p[3] for p in parts]), grid_shape,
                                                               prior["joint_sigma2"])
        sizes = [len(p[2]) for p in parts]
        parts = [(g, loss, a, b) for (g, loss, _, _), a, b in zip(parts, rd.split(sizes), rs.split(sizes))]
    seconds["joint"] = joint_before + time.perf_counter() - t3
    geom = {k: torch.cat([p[0][k] for p in parts]) for k in parts[0][0]}
    info = {"init_seconds": seconds["init"], "seconds_per_iteration": seconds["iterations"] / max(c.steps, 1),
            "propagation_seconds": seconds["propagation"], "propagation_restarts": restarted,
            "joint_seconds": seconds["joint"], **prior, "texel_q": texel_q,
            "texel_loss": torch.cat([p[1] for p in parts]).cpu().numpy()}
    return _result(prob, geom, torch.cat([p[2] for p in parts]), torch.cat([p[3] for p in parts]),
                   history / max(prob.n if refitted is None else refitted, 1), t_start, info)


def _linear(a: int, b: int, generator: torch.Generator) -> nn.Linear:
    """nn.Linear with Xavier-uniform weights and zero bias drawn from `generator` (skip_init: the global
    generator is never touched)."""
    lin = nn.utils.skip_init(nn.Linear, a, b)
    nn.init.xavier_uniform_(lin.weight, generator=generator)
    nn.init.zeros_(lin.bias)
    return lin


class _NeuralField(nn.Module):
    """Feature texture (channels, R, C) + the 5 MLP heads of reference §5 (sizes from FitConfig)."""

    def __init__(self, grid_shape, config: FitConfig, generator: torch.Generator):
        super().__init__()
        R, C = grid_shape
        self.texture = nn.Parameter(torch.empty(1, config.features, R, C))
        nn.init.xavier_uniform_(self.texture, generator=generator)  # reference §5: Xavier-uniform
        h = config.hidden
        self.heads = nn.ModuleList()
        for _, k in HEADS:
            widths = [config.features, h, h, h, k]
            layers = []
            for i in range(4):
                layers.append(_linear(widths[i], widths[i + 1], generator))
                if i < 3:
                    layers.append(nn.LeakyReLU(0.2))
            self.heads.append(nn.Sequential(*layers))

    def forward(self, uv: torch.Tensor) -> torch.Tensor:
        """uv (B, 2) in [-1, 1] (x = column, y = row) -> numbers (B, 11): geometry 5, then albedos 6."""
        f = nn.functional.grid_sample(self.texture, uv[None, None], mode="bilinear", align_corners=True)
        f = f[0, :, 0].T  # (B, channels)
        return torch.cat([head(f) for head in self.heads], dim=1)


def _texel_uv(grid_shape, device) -> torch.Tensor:
    """Row-major texel centres as grid_sample coordinates (align_corners=True: texel j of C at -1 + 2j/(C-1))."""
    R, C = grid_shape
    i, j = torch.meshgrid(torch.arange(R, device=device), torch.arange(C, device=device), indexing="ij")
    x = (2 * j / max(C - 1, 1) - 1).reshape(-1)
    y = (2 * i / max(R - 1, 1) - 1).reshape(-1)
    return torch.stack([x, y], dim=1).float()


def _fit_neural(prob: _Problem, grid_shape) -> FitResult:
    """Feature texture + 5 heads (reference §5), warm-started on the initial numbers, then Adam on random
    texel batches (drawn with replacement, as the reference) from a seeded generator."""
    t_start = time.perf_counter()
    c = prob.config
    gen = torch.Generator().manual_seed(c.seed)
    model = _NeuralField(tuple(int(v) for v in grid_shape), c, gen).to(prob.pos.device)
    uv = _texel_uv(grid_shape, prob.pos.device)
    init = [_initial(prob.part(idx)) for idx in _chunks(prob, c.batch)]
    target = torch.cat([torch.cat([g, _logit(rd), _logit(rs / c.rho_s_max)], dim=1) for g, rd, rs in init])
    t1 = time.perf_counter()
    # warm start (ours): regress the heads onto the initial numbers (no rendering, all texels per step)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(c.warm_start_steps):
        opt.zero_grad(set_to_none=True)
        nn.functional.mse_loss(model(uv), target).backward()
        opt.step()
    t2 = time.perf_counter()
    opt = torch.optim.Adam(model.parameters(), lr=c.learning_rate)
    batch = c.batch or 256
    history = []
    for _ in range(c.steps):
        idx = torch.randint(prob.n, (batch,), generator=gen).to(prob.pos.device)
        raw = model(uv[idx])
        part = prob.part(idx)
        loss = _rendered_loss(part, _geometry(raw[:, :5], prob.frame, c), **_albedo_numbers(raw[:, 5:], c)).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    t3 = time.perf_counter()
    with torch.no_grad():
        raw = model(uv)
        geom, alb = _geometry(raw[:, :5], prob.frame, c), _albedo_numbers(raw[:, 5:], c)
        texel_loss = torch.cat([_rendered_loss(prob.part(i), {k: v[i] for k, v in geom.items()}, alb["rho_d"][i],
                                               alb["rho_s"][i]) for i in _chunks(prob, c.batch)])
    info = {"init_seconds": t1 - t_start, "warm_start_seconds": t2 - t1,
            "seconds_per_iteration": (t3 - t2) / max(c.steps, 1), "texel_loss": texel_loss.cpu().numpy(),
            "batch": batch}
    return _result(prob, geom, alb["rho_d"], alb["rho_s"], history, t_start, info)


# one function per method, all (problem, grid_shape) -> FitResult (colour-science style dispatch)
FITTING_METHODS = {"direct": _fit_direct, "neural": _fit_neural}


def fit_method(rig, positions, lumitexels, *, method: str | None = None, lines=None, line_weights=None,
               secondary=None, grid_shape=None, config: FitConfig = FitConfig(), checkpoint=None,
               start=None) -> FitResult:
    """Dispatch to FITTING_METHODS[method] (None: config.method) after checking the inputs (fit_ggx)."""
    if not isinstance(config, FitConfig):
        raise ValueError(f"config must be a FitConfig, got {type(config).__name__}")
    if method is not None and method != config.method:
        config = replace(config, method=method)
    direct = {k: v for k, v in (("checkpoint", checkpoint), ("start", start)) if v is not None}
    if direct and config.method != "direct":
        raise ValueError(f"a checkpoint or a refit's start belongs to the direct method only, not {config.method!r}")
    prob = _problem(rig, positions, lumitexels, lines, line_weights, grid_shape, config, secondary)
    return FITTING_METHODS[config.method](prob, grid_shape, **direct)


def fit_ggx(rig, positions, lumitexels, *, lines=None, line_weights=None, secondary=None, grid_shape=None,
            config: FitConfig = FitConfig(), checkpoint=None, start=None) -> FitResult:
    """Fit anisotropic GGX and the local frame per texel (module docstring) with config.method.

    positions (N, 3) mm, world; lumitexels (N, L_upper, 3) in network units (upper LEDs in rig order,
    np.flatnonzero(~rig.is_bottom)), torch or numpy, >= 0, or a lumitexel source: a function of a tensor of
    texel indices (on config.device) that returns their lumitexels (reconstruction.stages.finetune.decoded_lumitexels:
    decoded when a chunk of texels is fitted, so that a 1024^2 paper-rig sample's 150 GB never exist); lines
    (N, K, 3) network units with line_weights (K, L_upper, 3) (the upper-LED part of the line patterns'
    weights), optional together: any photos of config.camera under patterns (the linear lights, the learned
    patterns' + and - frames); secondary (photos (N, K2, 3), weights (K2, L_upper, 3)) the same for
    config.secondary_camera (optional; each camera's photos weigh lambda_lines in the loss); grid_shape (R, C)
    with N = R C in row-major order, needed by method "neural"; checkpoint (direct method): where the fit keeps its
    state so that a killed fit resumes (_fit_direct); start (direct method): a refit of some texels after their
    photos changed, from an earlier fit's numbers (_fit_direct). Raises ValueError on NaN/Inf or mis-shaped input (a
    source's, when the fit asks for those texels). Deterministic on the CPU: the same inputs and seed give the same
    result."""
    return fit_method(rig, positions, lumitexels, lines=lines, line_weights=line_weights, secondary=secondary,
                      grid_shape=grid_shape, config=config, checkpoint=checkpoint, start=start)


# --- export ----------------------------------------------------------------------------------------------
def to_maps(result: FitResult, grid_shape, size_mm: float, transparency=None, name: str = "fit") -> SVBRDFMaps:
    """FitResult (row-major texels of an R x C grid, R == C) -> SVBRDFMaps in the reference's export
    convention (§5, §7.1): alpha_x >= alpha_y (twin.materials.samples.canonical_anisotropy), rho clipped to the map
    ranges, unit n with n_z > 0 and a unit tangent orthogonal to it. transparency (R, C) in [0, 1] or None
    (opaque)."""
    R, C = (int(v) for v in grid_shape)
    N = result.normal.shape[0]
    if R * C != N:
        raise ValueError(f"grid_shape {(R, C)} has {R * C} texels but the result has {N}")
    if R != C:
        raise ValueError(f"SVBRDF maps are square: grid_shape must have R == C, got {(R, C)}")
    n = result.normal.astype(np.float64).reshape(R, C, 3).copy()
    n[..., 2] = np.maximum(n[..., 2], 1e-6)  # the parameterisation keeps n.N > 0; guard float round-off
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    t = result.tangent.astype(np.float64).reshape(R, C, 3)
    t = t - np.einsum("ijk,ijk->ij", t, n)[..., None] * n
    t /= np.linalg.norm(t, axis=2, keepdims=True)
    alpha = np.clip(np.stack([result.alpha_x, result.alpha_y], -1).reshape(R, C, 2), *ALPHA_RANGE)
    beta = np.zeros((R, C)) if transparency is None else np.asarray(transparency, dtype=np.float64)
    if beta.shape != (R, C):
        raise ValueError(f"transparency must have shape {(R, C)}, got {beta.shape}")
    maps = SVBRDFMaps(rho_d=np.clip(result.rho_d.reshape(R, C, 3), *RHO_D_RANGE),
                      rho_s=np.clip(result.rho_s.reshape(R, C, 3), *RHO_S_RANGE), alpha=alpha, normal=n,
                      tangent=t, transparency=beta, size_mm=size_mm, name=name)
    return canonical_anisotropy(maps)
