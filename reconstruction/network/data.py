"""Training data of the acquisition network (paper §6): lumitexels synthesised on the fly, exactly labelled.

Every sample is a texel with known parameters (position on the sample plane, shading frame, grey GGX
material) rendered by the twin's own forward-model kernels (`twin.lumitexels`, Eq. 1) on the device
where the network trains. Nothing is stored: a batch is a pure function of (seed, batch index).

    cfg = SamplingConfig()                                   # the defaults below, with their sources
    stream = LumitexelStream(rig, cfg, batch_size=50, seed=0, device="cuda:0")
    b = stream.batch(i)        # views (B, 2, L) [primary, augmented secondary], target (B, L), params
    p = stream.pair_batch(i)   # views_a, views_b (B, 2, L), targets (B, 4, L) for the albedo swap
    h = heldout_set(rig, cfg, n=4096, seed=0, device="cuda:0")   # views, target, params; fixed

Lumitexels here are what the network sees and predicts (reference §3.1): GREY (mean over RGB), UPPER
LEDs only (`~rig.is_bottom`, the 12,288 of the paper rig; the bottom board is not part of the
lumitexel, reference §1), the physical convention of the twin (rig LED profile and intensity, frame
visibility on, opaque texels: transparency 0), times `LUMITEXEL_SCALE`.

Determinism: parameters are drawn on the CPU from a `torch.Generator` seeded by `stream_seed(seed,
stream, index)` (a hash, i.e. counter-based), so any batch can be regenerated alone, in any order, and
is the same on every device; the lumitexels are then rendered on `device` (per-point kernels, no
cross-point reductions, so batching several parameter sets into one launch changes no value).
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
import torch

import twin

__all__ = ["LUMITEXEL_SCALE", "SamplingConfig", "sample_parameters", "perturb_for_secondary", "synthesize",
           "white_reference", "swap_albedos", "pair_targets", "stream_seed", "LumitexelStream", "heldout_set",
           "PARAM_KEYS", "SAME", "PERTURBED", "RANDOM", "material_table"]

# --- the lumitexel scale ----------------------------------------------------------------------------
# The loss of the network (paper Eq. 3, reference §3.1) is sum_l [log(1 + m_hat) - log(1 + m)]^2. The log
# only compresses the dynamic range if m is of order 1 .. 1e3: in the twin's physical units (radiance in
# W m^-2 sr^-1 for LEDs of 0.05 W/sr at ~0.36 m) a white Lambertian texel reads ~0.12, where log(1+m) ~ m
# is linear and the diffuse part would carry almost no weight next to a specular peak. We therefore scale
# the lumitexels so that a white Lambertian texel (rho_d = 1, rho_s = 0) at the sample centre, lit by the
# nearest top-board LED, reads 1. With the default SamplingConfig on the paper rig (2,000 held-out texels)
# the entries then have median 0.09, the per-texel maximum has median 3.5 and 99th percentile ~300, and the
# largest entry is ~3e3 (sharp specular peaks): the range over which log(1 + m) is meant to work.
# Value: 1 / white_reference(twin.load_rig("paper")) = 1 / 0.1226143 (LED 4959, 359.2 mm from the centre,
# physical convention; 8.1943 for the "mini" rig, whose nearest top LED is 359.5 mm away). Computed
# from the rig by `white_reference`; tests/test_data.py checks the constant against the paper rig.
LUMITEXEL_SCALE = 8.155658

PARAM_KEYS = ("position", "normal", "tangent", "rho_d", "rho_s", "alpha_x", "alpha_y")
SAME, PERTURBED, RANDOM = 0, 1, 2  # secondary-view augmentation of each sample (key "augmentation")
TILTS = ("cosine", "uniform")


@dataclass(frozen=True)
class SamplingConfig:
    """Distributions of the synthetic training texels (paper §6; the training code is not released)."""

    # GGX roughness, log-uniform, alpha_x and alpha_y independent: reference §3.1 ("alpha in [0.006,
    # 0.503]", the fitting default 0.006 + 0.497 sigmoid) and Kang et al. 2019 (log-uniform roughness).
    alpha_range: tuple[float, float] = (0.006, 0.5)
    # Diffuse albedo, uniform [0, 1]: the physical range (reference §3.1 gives none); grey: the network is grey,
    # RGB averaged (paper §6), so rho is one value on the 3 channels.
    rho_d_range: tuple[float, float] = (0.0, 1.0)
    # Specular albedo, uniform [0, 10]: reference §3.1 (the released code hints rho_s in [0, 10]).
    rho_s_range: tuple[float, float] = (0.0, 10.0)
    # Positions uniform over a centred square of this side (mm) on the rig's sample plane: about the area a
    # released texture map covers (1024 texels of ~0.127 mm, reference §7), inside the <= 15 cm sample
    # (reference §8; rig.sample.max_size is 150 mm).
    area_mm: float = 120.0
    # Normal tilt from the plane normal: "cosine" (density cos(theta) sin(theta), i.e. cosine-weighted
    # over the cap) or "uniform" in theta; azimuth uniform; tangent angle uniform in [0, 2 pi). No source
    # gives the frame distribution (the paper says "as in Kang et al. 2018", reference §3.1): the default
    # (cosine, at most 60 deg) is this project's choice, kept configurable.
    tilt: str = "cosine"
    max_tilt_deg: float = 60.0
    # Secondary-view augmentation (paper §6, reference §3.1): fractions of perturbed / fully random samples.
    perturbed: float = 0.30
    random: float = 0.10
    perturb_material_sigma: float = 0.05  # rho_d, rho_s, alpha_x, alpha_y each x N(1, 5%) (paper §6)
    perturb_normal_sigma: float = 0.15  # length of the orthogonal normal offset ~ N(0, 15%) (paper §6)
    # "Fully random" replaces the material and the frame by a fresh draw; the texel stays where it is
    # (both cameras look at the same point of the plane; the position is where, not what, the texel is).
    random_keeps_position: bool = True
    # Materials: "" draws rho_d, rho_s, alpha_x, alpha_y from the ranges above, independently (uniform GGX
    # parameters). Otherwise the texels' materials are drawn jointly from a table of real texels, keeping
    # the correlations of a database (paper §11.3 trains on "the distribution of our database"):
    #   "suite:S1,S2,..."   every sample of the material suite (twin.materials.suite: the nine OpenSVBRDF
    #                       categories and quadrants) at compositions (seeds) S1, S2, ... at 64² texels;
    #   "maps:DIR"          every folder of OpenSVBRDF maps at DIR or directly under it.
    # Grey (mean over RGB), clipped to the ranges above (the network's range). Frames as above.
    materials: str = ""

    def __post_init__(self):
        for name in ("alpha_range", "rho_d_range", "rho_s_range"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
                raise ValueError(f"SamplingConfig.{name} must be (lo, hi) with 0 <= lo <= hi, got {(lo, hi)}")
            object.__setattr__(self, name, (lo, hi))
        if self.alpha_range[0] <= 0:
            raise ValueError(f"SamplingConfig.alpha_range must be > 0 (log-uniform), got {self.alpha_range}")
        if not (math.isfinite(self.area_mm) and self.area_mm > 0):
            raise ValueError(f"SamplingConfig.area_mm must be positive, got {self.area_mm}")
        if self.tilt not in TILTS:
            raise ValueError(f"SamplingConfig.tilt must be one of {TILTS}, got {self.tilt!r}")
        if not (0 <= self.max_tilt_deg < 90):
            raise ValueError(f"SamplingConfig.max_tilt_deg must lie in [0, 90), got {self.max_tilt_deg}")
        if not (0 <= self.perturbed and 0 <= self.random and self.perturbed + self.random <= 1):
            raise ValueError("SamplingConfig.perturbed and .random must be >= 0 with a sum <= 1, "
                             f"got {self.perturbed} and {self.random}")
        if not (self.perturb_material_sigma >= 0 and self.perturb_normal_sigma >= 0):
            raise ValueError("SamplingConfig perturbation sigmas must be >= 0")
        if self.materials:
            material_table(self)  # checked (and cached) now: a bad spec fails before any training


MATERIAL_RESOLUTION = 64  # texels per side of each suite sample in a "suite:" table
_TABLES: dict = {}


def _suite_maps(spec: str) -> list:
    from twin.materials.samples import SUITE, load_sample

    try:
        seeds = [int(v) for v in spec.split(",")]
    except ValueError:
        seeds = []
    if not seeds or min(seeds) < 0:
        raise ValueError(f"SamplingConfig.materials 'suite:{spec}' must name seeds: suite:0,1,2")
    return [load_sample(f"{name}@{seed}", MATERIAL_RESOLUTION) for name in SUITE for seed in seeds]


def _folder_maps(spec: str) -> list:
    from pathlib import Path

    from twin.materials.samples import SAMPLE_TOML, read_maps

    root = Path(spec)
    dirs = [root] if (root / SAMPLE_TOML).is_file() else sorted(p for p in root.glob("*") if (p / SAMPLE_TOML).is_file())
    if not dirs:
        raise ValueError(f"SamplingConfig.materials 'maps:{spec}': no folder of OpenSVBRDF maps there")
    return [read_maps(d) for d in dirs]


def material_table(config: SamplingConfig) -> np.ndarray:
    """(N, 4) float64 grey materials [rho_d, rho_s, alpha_x, alpha_y] of `config.materials`, clipped to the
    config's ranges; cached per spec."""
    key = (config.materials, config.rho_d_range, config.rho_s_range, config.alpha_range)
    if key not in _TABLES:
        kind, _, arg = config.materials.partition(":")
        loaders = {"suite": _suite_maps, "maps": _folder_maps}
        if kind not in loaders or not arg:
            raise ValueError(f"SamplingConfig.materials must be '', 'suite:SEEDS' or 'maps:DIR', got "
                             f"{config.materials!r}")
        rows = []
        for m in loaders[kind](arg):
            a = m.alpha.reshape(-1, 2)
            rows.append(np.stack([m.rho_d.reshape(-1, 3).mean(1), m.rho_s.reshape(-1, 3).mean(1), a[:, 0], a[:, 1]], 1))
        t = np.concatenate(rows).astype(np.float64)
        for j, rng in enumerate((config.rho_d_range, config.rho_s_range, config.alpha_range, config.alpha_range)):
            t[:, j] = np.clip(t[:, j], *rng)
        _TABLES[key] = t
    return _TABLES[key]


# --- parameters -------------------------------------------------------------------------------------
def _plane(rig):
    s = rig.sample
    return (torch.tensor(s.origin, dtype=torch.float64), torch.tensor(s.x_axis, dtype=torch.float64),
            torch.tensor(np.asarray(s.y_axis), dtype=torch.float64), torch.tensor(s.normal, dtype=torch.float64))


def _rand(n, generator, *shape):
    return torch.rand(n, *shape, generator=generator, dtype=torch.float64, device=generator.device).cpu()


def _randn(n, generator, *shape):
    return torch.randn(n, *shape, generator=generator, dtype=torch.float64, device=generator.device).cpu()


def _unit(v):
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def sample_parameters(n: int, config: SamplingConfig, rig, generator: torch.Generator) -> dict:
    """n random texels: float32 CPU tensors position (n,3) mm, normal (n,3), tangent (n,3) (unit, world
    frame), rho_d (n,3), rho_s (n,3) (grey: one value on 3 channels), alpha_x (n,), alpha_y (n,).
    Always consumes the same amount of `generator` for a given n (computed in float64, stored float32)."""
    if config.area_mm > rig.sample.max_size:
        raise ValueError(f"SamplingConfig.area_mm = {config.area_mm} exceeds the sample plane of rig "
                         f"{rig.name!r} ({rig.sample.max_size} mm)")
    o, X, Y, N = _plane(rig)
    u = _rand(n, generator, 9)
    pos = o + ((u[:, 0:1] - 0.5) * config.area_mm) * X + ((u[:, 1:2] - 0.5) * config.area_mm) * Y
    # normal: tilt theta from N, azimuth phi; cosine: sin^2(theta) uniform on [0, sin^2(max)]
    tmax = math.radians(config.max_tilt_deg)
    if config.tilt == "cosine":
        theta = torch.asin(torch.sqrt(u[:, 2]) * math.sin(tmax))
    else:
        theta = u[:, 2] * tmax
    phi = u[:, 3] * (2 * math.pi)
    ct, st, cp, sp = (torch.cos(theta)[:, None], torch.sin(theta)[:, None], torch.cos(phi)[:, None],
                      torch.sin(phi)[:, None])
    d = cp * X + sp * Y  # tilt direction in the plane
    nrm = ct * N + st * d
    # reference tangent: the plane's x axis carried along by the rotation about N x d that takes N to n
    # (unit and exactly orthogonal to n for every tilt < 180 deg); then the tangent angle psi in [0, 2 pi)
    a = cp * Y - sp * X  # N x d
    t0 = cp * (ct * d - st * N) - sp * a
    psi = u[:, 4:5] * (2 * math.pi)
    tan = torch.cos(psi) * t0 + torch.sin(psi) * torch.linalg.cross(nrm, t0)
    if config.materials:  # one texel of the table, all four numbers together (u[:, 6:9] drawn but unused)
        table = torch.from_numpy(material_table(config))
        rd, rs, ax, ay = table[(u[:, 5] * len(table)).long().clamp_max(len(table) - 1)].unbind(1)
    else:
        lo, hi = config.rho_d_range
        rd = lo + (hi - lo) * u[:, 5]
        lo, hi = config.rho_s_range
        rs = lo + (hi - lo) * u[:, 6]
        la, lb = (math.log(v) for v in config.alpha_range)
        ax, ay = torch.exp(la + (lb - la) * u[:, 7]), torch.exp(la + (lb - la) * u[:, 8])
    f = torch.float32
    return {"position": pos.to(f), "normal": _unit(nrm).to(f), "tangent": _unit(tan).to(f),
            "rho_d": rd[:, None].expand(n, 3).to(f).contiguous(), "rho_s": rs[:, None].expand(n, 3).to(f).contiguous(),
            "alpha_x": ax.to(f), "alpha_y": ay.to(f)}


def perturb_for_secondary(params: dict, config: SamplingConfig, generator: torch.Generator, rig=None) -> dict:
    """The secondary view's parameters (paper §6): a fraction `config.perturbed` of the samples get rho_d,
    rho_s, alpha_x, alpha_y each x N(1, sigma) (clipped to the config's ranges) and the normal offset by a
    random vector orthogonal to it with length ~ N(0, sigma_n), renormalised (tangent re-orthogonalised);
    a fraction `config.random` get a fresh independent draw (needs `rig` for the sample plane; the
    position is kept when config.random_keeps_position); the rest are identical to the primary.
    Returns a new dict (float32 CPU tensors) with "augmentation" (n,) int64: SAME, PERTURBED or RANDOM.
    Every sample consumes the generator alike, whatever its fate."""
    if rig is None:
        raise ValueError("perturb_for_secondary needs `rig`: the fully random draw lies on its sample plane")
    n = params["position"].shape[0]
    g = {k: params[k].detach().cpu().to(torch.float64) for k in PARAM_KEYS}
    u = _rand(n, generator)
    mode = torch.full((n,), SAME, dtype=torch.int64)
    mode[u < config.perturbed] = PERTURBED
    mode[(u >= config.perturbed) & (u < config.perturbed + config.random)] = RANDOM
    fac = 1 + config.perturb_material_sigma * _randn(n, generator, 4)
    direction = _randn(n, generator, 3)
    length = config.perturb_normal_sigma * _randn(n, generator, 1)
    fresh = {k: v.to(torch.float64) for k, v in sample_parameters(n, config, rig, generator).items()}

    per = dict(g)
    for i, (k, rng) in enumerate((("rho_d", config.rho_d_range), ("rho_s", config.rho_s_range),
                                  ("alpha_x", config.alpha_range), ("alpha_y", config.alpha_range))):
        f = fac[:, i:i + 1] if g[k].ndim == 2 else fac[:, i]
        per[k] = (g[k] * f).clamp(*rng)
    nrm = g["normal"]
    off = direction - (direction * nrm).sum(-1, keepdim=True) * nrm  # orthogonal to n
    off_norm = torch.linalg.vector_norm(off, dim=-1, keepdim=True)
    off = torch.where(off_norm > 1e-12, off / off_norm.clamp_min(1e-12), torch.zeros_like(off))
    n2 = _unit(nrm + length * off)
    t = g["tangent"]
    per["normal"], per["tangent"] = n2, _unit(t - (t * n2).sum(-1, keepdim=True) * n2)
    if config.random_keeps_position:
        fresh["position"] = g["position"]

    out = {}
    for k in PARAM_KEYS:
        m = mode.view(n, *([1] * (g[k].ndim - 1)))
        # float32 -> float64 -> float32 is exact: SAME samples are bit-identical to the primary
        out[k] = torch.where(m == PERTURBED, per[k], torch.where(m == RANDOM, fresh[k], g[k])).to(torch.float32)
    out["augmentation"] = mode
    return out


# --- rendering ----------------------------------------------------------------------------------------
_UPPER: dict = {}


def led_directions(rig) -> np.ndarray:
    """(L_upper, 3) float32 unit vectors from the sample's centre to each lumitexel LED, world frame (the decoder's
    peak term, reconstruction.network.architecture.NetworkConfig.peak_term)."""
    d = np.asarray(rig.leds.positions)[~np.asarray(rig.is_bottom)] - np.asarray(rig.sample.origin)
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def _upper_index(rig, device: torch.device) -> torch.Tensor:
    key = (rig.digest(), str(device))
    if key not in _UPPER:
        _UPPER[key] = torch.as_tensor(np.flatnonzero(~np.asarray(rig.is_bottom)), dtype=torch.int64, device=device)
    return _UPPER[key]


def _check_camera(rig, camera: str) -> None:
    if camera not in rig.cameras:
        raise ValueError(f"rig {rig.name!r} has no camera {camera!r} (it has {list(rig.cameras)}); the "
                         "acquisition network needs every view it is trained on")


def _wp_device(device) -> str:
    d = torch.device(device)
    return "cpu" if d.type == "cpu" else f"cuda:{d.index if d.index is not None else torch.cuda.current_device()}"


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


# the grey mean and the scale in one float32 factor: m_grey = (r + g + b) * (LUMITEXEL_SCALE / 3)
GREY_FACTOR = float(np.float32(LUMITEXEL_SCALE / 3))


def synthesize(rig, params: dict, camera: str, device="cpu") -> torch.Tensor:
    """Grey upper-LED lumitexels (n, L_upper) float32 on `device` of the texels `params` seen from
    `camera`: twin.lumitexels (physical convention, visibility on, transparency 0), upper LEDs, mean
    over RGB, times LUMITEXEL_SCALE. The kernel writes straight into device memory (output="torch")."""
    _check_camera(rig, camera)
    wdev = _wp_device(device)
    p = [_np(params[k]) for k in PARAM_KEYS]
    kw = dict(convention="physical", device=wdev, camera=camera, transparency=np.zeros(len(p[0])),
              visibility=True, output="torch")
    if wdev.startswith("cuda"):  # launch on torch's current stream: the zero-copy output is read by torch next
        import warp as wp

        from twin.optics.inputs import _init

        _init()  # stream_from_torch needs an initialised Warp runtime
        with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(torch.device(wdev)))):
            m = twin.lumitexels(rig, *p, **kw)
    else:
        m = twin.lumitexels(rig, *p, **kw)
    m = m.index_select(1, _upper_index(rig, m.device))
    return (m[..., 0] + m[..., 1] + m[..., 2]) * GREY_FACTOR


def white_reference(rig, device="cpu") -> float:
    """The physical grey lumitexel (before LUMITEXEL_SCALE) of a white Lambertian texel (rho_d = 1,
    rho_s = 0) at the sample centre with the plane's frame, under the nearest top-board LED."""
    top = [i for i, b in enumerate(rig.boards) if b.face == "top"]
    sel = np.flatnonzero(np.isin(rig.leds.board, top) & ~np.asarray(rig.is_bottom))
    if sel.size == 0:
        raise ValueError(f"rig {rig.name!r} has no top-board LED")
    o = np.asarray(rig.sample.origin)
    k = sel[np.argmin(np.linalg.norm(rig.leds.positions[sel] - o, axis=1))]
    m = twin.lumitexels(rig, [o], [rig.sample.normal], [rig.sample.x_axis], [[1.0] * 3], [[0.0] * 3], [0.1],
                        [0.1], convention="physical", device=_wp_device(device), transparency=[0.0],
                        visibility=True)
    return float(m[0, k].astype(np.float64).mean())


def swap_albedos(geometry: dict, albedo: dict) -> dict:
    """`geometry`'s position, frame and roughness with `albedo`'s rho_d and rho_s."""
    out = {k: geometry[k] for k in PARAM_KEYS}
    out["rho_d"], out["rho_s"] = albedo["rho_d"], albedo["rho_s"]
    return out


def _cat(ps: list[dict]) -> dict:
    return {k: torch.cat([p[k].detach().cpu() for p in ps]) for k in PARAM_KEYS}


def pair_targets(rig, pa: dict, pb: dict, device="cpu", camera: str = "primary") -> torch.Tensor:
    """(B, 4, L) lumitexels [a, b, a with b's albedos, b with a's albedos] seen from `camera` (one launch)."""
    B = pa["position"].shape[0]
    m = synthesize(rig, _cat([pa, pb, swap_albedos(pa, pb), swap_albedos(pb, pa)]), camera, device)
    return m.view(4, B, -1).transpose(0, 1).contiguous()


def stream_seed(seed: int, stream: str, index: int) -> int:
    """The generator seed of batch `index` of `stream` ("train", "pair", "heldout", ...): a hash of the
    three, so seeds of different streams, indices or base seeds are unrelated (63 bits)."""
    h = hashlib.sha256(f"hemicube-lumitexels/{int(seed)}/{stream}/{int(index)}".encode()).digest()
    return int.from_bytes(h[:8], "little") & (2**63 - 1)


def _generator(seed: int, stream: str, index: int) -> torch.Generator:
    g = torch.Generator(device="cpu")  # CPU draws: the same stream on every training device
    g.manual_seed(stream_seed(seed, stream, index))
    return g


def _to(params: dict, device) -> dict:
    return {k: v.to(device) for k, v in params.items()}


class LumitexelStream:
    """An endless, counter-based stream of training batches rendered on `device`.

    batch(i)      -> views (B, V, L) [cameras[0] with the primary parameters, then each further camera
                     with its own secondary augmentation], target (B, L) = views[:, 0], params (the
                     primary parameters), secondary (the parameters of each further view, a list)
    pair_batch(i) -> views_a, views_b (B, V, L), targets (B, 4, L) [a, b, a with b's albedos, b with a's
                     albedos] in cameras[0], params_a, params_b
    Tensors are on `device`. Batch i of a stream depends only on (seed, i): any order, any subset.

    shard=(rank, world): this rank's contiguous slice of every batch, for training over `world` processes
    (reconstruction.network.distributed). The parameters of the whole batch are drawn (cheap, on the CPU) and only
    the slice is rendered, so the slices of the ranks are disjoint and together are the one-process batch,
    value for value (the kernels are per point). batch_size is the global batch; world must divide it."""

    def __init__(self, rig, config: SamplingConfig, batch_size: int, seed: int, device="cpu",
                 cameras=("primary", "secondary"), shard: tuple[int, int] = (0, 1)):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        rank, world = (int(v) for v in shard)
        if not (world >= 1 and 0 <= rank < world and batch_size % world == 0):
            raise ValueError(f"shard (rank {rank}, world {world}) must have 0 <= rank < world and world dividing "
                             f"the batch ({batch_size})")
        cameras = tuple(cameras)
        if not cameras:
            raise ValueError("cameras must name at least one camera")
        for c in cameras:
            _check_camera(rig, c)
        if config.area_mm > rig.sample.max_size:
            raise ValueError(f"SamplingConfig.area_mm = {config.area_mm} exceeds the sample plane of rig "
                             f"{rig.name!r} ({rig.sample.max_size} mm)")
        self.rig, self.config, self.batch_size, self.seed = rig, config, int(batch_size), int(seed)
        self.device, self.cameras = torch.device(device), cameras
        self.num_lumitexel = int((~np.asarray(rig.is_bottom)).sum())
        share = batch_size // world
        self.rows = slice(rank * share, (rank + 1) * share)

    def _views(self, g: torch.Generator, n: int, rows: slice = slice(None)):
        p = sample_parameters(n, self.config, self.rig, g)
        sec = [perturb_for_secondary(p, self.config, g, self.rig) for _ in self.cameras[1:]]
        p, sec = {k: v[rows] for k, v in p.items()}, [{k: v[rows] for k, v in s.items()} for s in sec]
        views = [synthesize(self.rig, p, self.cameras[0], self.device)]  # one launch per camera
        views += [synthesize(self.rig, s, c, self.device) for s, c in zip(sec, self.cameras[1:])]
        return p, sec, torch.stack(views, dim=1)

    def _make(self, stream: str, index: int, n: int, rows: slice = slice(None)) -> dict:
        p, sec, views = self._views(_generator(self.seed, stream, index), n, rows)
        return {"views": views, "target": views[:, 0], "params": _to(p, self.device),
                "secondary": [_to(s, self.device) for s in sec]}

    def batch(self, i: int) -> dict:
        return self._make("train", i, self.batch_size, self.rows)

    def pair_batch(self, i: int) -> dict:
        g = _generator(self.seed, "pair", i)
        pa, sa, va = self._views(g, self.batch_size, self.rows)
        pb, sb, vb = self._views(g, self.batch_size, self.rows)
        targets = pair_targets(self.rig, pa, pb, self.device, self.cameras[0])
        return {"views_a": va, "views_b": vb, "targets": targets, "params_a": _to(pa, self.device),
                "params_b": _to(pb, self.device)}


def heldout_set(rig, config: SamplingConfig, n: int, seed: int, device="cpu",
                cameras=("primary", "secondary")) -> dict:
    """A fixed held-out set of n samples built like the training batches, from the "heldout" seed
    stream (disjoint from "train" and "pair"): views (n, V, L), target (n, L), params, secondary."""
    return LumitexelStream(rig, config, n, seed, device, cameras)._make("heldout", 0, n)
