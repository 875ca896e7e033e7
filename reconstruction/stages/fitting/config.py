"""The GGX fit's settings (FitConfig) and result (FitResult), and the names of its choices: the loss (LOSSES), the
direct method's Jacobian (JACOBIANS), the method (METHODS; reconstruction.stages.fitting.FITTING_METHODS).

Why the defaults (ours, measured on the mini rig's `ramps`, from exact targets to the whole pipeline; the figures are
in docs/accuracy.md): "direct" is as good as or better than "neural" in the bulk and on tangents, exact on exact
targets, and per texel, so it scales by chunks (the neural heads' sharing trims the roughness tail on decoded data);
"log1p", because the decoder's errors sit in the bright specular entries that "mse" weighs most; lambda_lines = 100,
because the measured photos carry the truth and the decoded lumitexels the decoder's bias, and 100 keeps some of the
lumitexels' LED-space detail while photo noise still favours it over 10.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from twin.materials.samples import ALPHA_RANGE, RHO_S_RANGE

from reconstruction.stages.finetune import PRECISIONS


LOSSES = ("log1p", "mse")
JACOBIANS = ("analytic", "forward")  # FitConfig.jacobian
METHODS = ("direct", "neural")  # reconstruction.stages.fitting.FITTING_METHODS: one function each
GEOMETRY_SIZE = 5  # [u, v, theta, a_x, a_y]


@dataclass(frozen=True)
class FitConfig:
    """Settings of the GGX fit. Sources: reference §5 (the released fitting code) or ours (measured: the
    module docstring says why the defaults, docs/accuracy.md has the figures)."""

    method: str = "direct"  # ours, measured
    # direct (ours): Levenberg-Marquardt iterations (a Jacobian and an evaluation of the residuals each, on the texels
    # not yet converged); neural: Adam steps of `batch` texels (the reference runs 120,000 steps of 128 texels).
    iterations: int | None = None  # None: 20 (direct), 600 (neural)
    lr: float | None = None  # the neural method's Adam (None: 1e-3, reference §5); the direct method has none
    # direct: texels per chunk (None: problem.AUTO_CHUNK_PAIRS / LEDs); neural: texels per step (None: 256)
    batch: int | None = None
    # the widest of the reference's per-class ranges (§5 OBJECT_CONFIG: 0.006 + axay_range, 1.0 for wood and
    # woven; ps_range 20 for paper), one setting for every sample: the validation suite's materials reach alpha 0.6
    # and rho_s 18, which the default-class ranges (0.503, 10) clip
    alpha_range: tuple = (0.006, 1.006)
    rho_s_max: float = 20.0
    lm_damping: float = 1e-2  # direct: Levenberg-Marquardt's initial mu (ours)
    # direct: the Levenberg-Marquardt's Jacobian (ours): "analytic", the bases' derivatives from one Warp launch per
    # camera (twin.optics.jvp) and the albedos' by variable projection (jacobian._analytic_jacobian); "forward",
    # forward differences of the residuals, five more evaluations of the forward model a step (the same-run baseline
    # of `hemicube bench fit-jacobian`)
    jacobian: str = "analytic"
    fd_step: float = 1e-3  # direct: forward-difference step of the Jacobian in every number (ours), and the
    # analytic one's where a lobe is isotropic (jacobian._tensor_system)
    # direct: a texel stops when a kept step lowers its loss by less (relative; ours); the joint prior stops when a
    # kept step lowers its objective by less than this times its size at noise level (joint._joint_roughness)
    tolerance: float = 1e-5
    propagation: int = 2  # direct, on a grid: rounds of neighbour propagation (ours; solver._propagate)
    # direct, on a grid (ours; joint._joint_roughness): the expected change of log alpha between neighbouring texels
    # of one material, the scale of a Gaussian smoothness prior that texels whose photos barely constrain alpha
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
    # direct, analytic Jacobian (ours; docs/performance.md): the projections of the bases' derivatives onto the
    # photos' weights, and those of the initial candidates (candidates._best_candidate: they are only ranked), on a
    # CUDA device in TF32 ("tf32", the tensor cores' 10-bit mantissa) or "float32". Only the Gauss-Newton system's
    # direction and the starting point: the loss that accepts or refuses a step and the closed-form albedos stay
    # float32, so the fixed point of Levenberg-Marquardt does not move (docs/performance.md: the fit's median
    # per-texel loss against float32's, checked by `hemicube bench reconstruct`). The CPU's products are float32
    # either way.
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
    history: the mean per-texel loss at each step (over the texels fitted: a refit's, direct._fit_direct); seconds: wall
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
