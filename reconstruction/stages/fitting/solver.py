"""The direct method's per-texel solver (paper §7.2; ours): Levenberg-Marquardt on the 5 geometry numbers of every
texel at once, the albedos in closed form at every evaluation (variable projection: the 6 linear unknowns never slow
it), and, on a grid, neighbour propagation, which restarts it from a neighbour's numbers where those fit better.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from reconstruction.stages.fitting.config import GEOMETRY_SIZE
from reconstruction.stages.fitting.jacobian import _system
from reconstruction.stages.fitting.model import _loss
from reconstruction.stages.fitting.problem import _chunk_size, _chunks, _Problem


def _levenberg_marquardt(prob: _Problem, q: torch.Tensor, history: np.ndarray, tick=None) -> torch.Tensor:
    """Levenberg-Marquardt on the numbers q (n, 5) = [u, v, theta, log alpha_x, log alpha_y] of every texel at
    once (texels are independent: each has its own 5 x 5 system and damping mu). The Jacobian of the residuals
    (model._residuals, the closed-form albedos re-solved at every evaluation: variable projection) is analytic or by
    forward differences, 5 more evaluations of the residuals per iteration (FitConfig.jacobian). A step is
    kept where it lowers the texel's loss (then mu / 3), else refused (mu x 4; Marquardt's scaling by the
    diagonal, plus a floor for the tangent angle of an isotropic texel, which moves nothing). A trial step is
    evaluated with its Gauss-Newton system (_system: the loss comes with it), which a kept step then uses and a
    refused one drops, keeping the texel's last: a loss and then a kept step's system would evaluate the forward
    model and decode the lumitexels twice, and most steps are kept. log alpha is clamped to alpha_range after each
    step. Texels whose last kept step changed their loss by less than FitConfig.tolerance (relative) or whose mu
    exceeds 1e10 drop out. history[i] += the sum of the losses after iteration i; tick() after each (progress)."""
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
            if tick is not None:
                tick()
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
    every other texel would compare the same numbers as that round did and decide as it did (after the first round
    few texels restart, and a round over all of them would cost as much as the first). Returns (q, texels
    restarted, the mask of those texels)."""
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
    # restarted in chunks like every other pass: some samples (paper stock at 1024^2) restart so many texels that all
    # at once would not fit a GPU's memory
    for k in (sel.split(_chunk_size(prob, prob.config.batch)) if sel.numel() else ()):
        idx = region[k]
        q[idx] = _levenberg_marquardt(prob.part(idx), best[k], np.zeros(prob.config.steps))
    mask = torch.zeros(prob.n, dtype=torch.bool, device=q.device)
    mask[moved] = True
    return q, int(moved.numel()), mask
