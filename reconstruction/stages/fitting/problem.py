"""The GGX fit's problem (paper §7.2, reference §5): its inputs checked and placed on the device (_problem), the
loss's transform f of lumitexels and photos (_f), the chunks of texels the direct method works in (_chunks), and
the FitResult a method returns (_result).

The inputs: positions (N, 3), the lumitexels m (N, L, 3) of the upper LEDs in network units (an array, or a source
that decodes a chunk's when it is fitted), and each camera's photos M (N, K, 3) under the upper-LED weights
W (K, L, 3) (reference §2.4: a line light or a learned pattern is a weighted sum of LEDs). Every check names the
first bad value, and reads a tensor piece by piece (_pieces), never making a temporary of its size.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from reconstruction.stages.fitting.config import FitConfig, FitResult


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
    # derived where they are used (the Warp sums, reconstruction.stages.fitting.sums, from m itself), not stored: at
    # 12,288 LEDs each is 147 kB a texel
    target: object
    leds: int  # L, the upper LEDs
    photos: tuple  # _Photos of each camera that has measurements (primary first); empty: lumitexels only
    upper_rig: object  # the rig with its upper LEDs only: what the fit evaluates (the bottom ones light nothing here)
    ratio: torch.Tensor  # (2, L, 3): I[l, c] / I[l, 0] and I[l, c] / I[l, 1] (model's docstring)
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
    """The loss's transform of lumitexels or measurements: log(1 + x) or x / scale (model's docstring)."""
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
    ~16 passes of 1M decoded lumitexels x 36,864 values, ~2,300 pieces a pass, and a check with a sync for each piece
    would stall the device on every one). NaN is _tensor's to report, which checks first."""
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
                         "the diffuse and specular responses from those channels (reconstruction.stages.fitting.model)")
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


# texel-LED pairs evaluated at once when FitConfig.batch is None (ours, memory and speed): every texel of a mini-rig
# grid up to 660^2 in one range; 16,384 texels on the paper rig. A pair costs one view's grey bases and their 5
# derivatives at a time (12 floats; jacobian._linearisation), the chunk's copy of its target (3 floats) and passing
# temporaries. Why this many (docs/performance.md): smaller chunks' launches are too short to fill a GPU and the fit
# of a paper-rig grid is slower, larger ones are no faster and take more of a 40 GB device's memory. The sums over the
# LEDs run in Warp (reconstruction.stages.fitting.sums) so that no (texels x LEDs x 3) tensor but the target is held.
AUTO_CHUNK_PAIRS = 3 * 2 ** 26


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
