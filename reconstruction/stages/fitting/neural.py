"""The "neural" method (reference §5): a learnable feature texture (channels, R, C), Xavier-uniform, sampled with
grid_sample (bilinear, align_corners=True) at the texel centres, feeds 5 MLP heads (n 2, theta 1, alpha 2, rho_d 3,
rho_s 3), each channels -> hidden -> hidden -> hidden -> k with LeakyReLU(0.2), whose outputs are the 5 geometry
numbers (reconstruction.stages.fitting.geometry) and 6 albedo numbers, rho_d = sigmoid(d) and
rho_s = rho_s_max sigmoid(s); Adam (lr 1e-3) on random texel batches from a seeded generator, after a warm start
that regresses the heads onto the initial candidates' numbers (reconstruction.stages.fitting.candidates; ours).
"""
from __future__ import annotations

import time

import torch
from torch import nn

from reconstruction.stages.fitting.candidates import _initial
from reconstruction.stages.fitting.config import FitConfig, FitResult
from reconstruction.stages.fitting.geometry import _geometry, _logit
from reconstruction.stages.fitting.model import _rendered_loss
from reconstruction.stages.fitting.problem import _chunks, _Problem, _result


HEADS = (("normal", 2), ("theta", 1), ("alpha", 2), ("rho_d", 3), ("rho_s", 3))  # reference §5's 5 heads


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


def _linear(a: int, b: int, generator: torch.Generator) -> nn.Linear:
    """nn.Linear with Xavier-uniform weights and zero bias drawn from `generator` (skip_init: the global
    generator is never touched)."""
    lin = nn.utils.skip_init(nn.Linear, a, b)
    nn.init.xavier_uniform_(lin.weight, generator=generator)
    nn.init.zeros_(lin.bias)
    return lin


def _texel_uv(grid_shape, device) -> torch.Tensor:
    """Row-major texel centres as grid_sample coordinates (align_corners=True: texel j of C at -1 + 2j/(C-1))."""
    R, C = grid_shape
    i, j = torch.meshgrid(torch.arange(R, device=device), torch.arange(C, device=device), indexing="ij")
    x = (2 * j / max(C - 1, 1) - 1).reshape(-1)
    y = (2 * i / max(R - 1, 1) - 1).reshape(-1)
    return torch.stack([x, y], dim=1).float()


def _albedo_numbers(raw: torch.Tensor, config: FitConfig) -> dict:
    """The neural heads' 6 albedo numbers -> rho_d in [0, 1], rho_s in [0, rho_s_max] (reference §5)."""
    return {"rho_d": torch.sigmoid(raw[:, 0:3]), "rho_s": config.rho_s_max * torch.sigmoid(raw[:, 3:6])}
