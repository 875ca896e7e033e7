"""The direct method's joint prior on roughness and specular albedo, on a grid (ours; FitConfig.alpha_prior).

After each texel's own fit, neighbouring texels of one material (4-neighbours weighted by the likeness of their
diffuse colour, _colour_weights) are coupled by a Gaussian smoothness prior on the log roughness tensor
(_joint_roughness) and then on rho_s (_joint_albedos), so that a lobe the photos barely see is pooled over its
material while a texel whose own photos pin its lobe keeps it (_pinned). Both are solved by block-preconditioned
conjugate gradients on the per-texel blocks coupled by the grid Laplacian (_block_pcg). docs/accuracy.md has what
the prior gains on the material suite.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from reconstruction.stages.fitting.config import GEOMETRY_SIZE
from reconstruction.stages.fitting.geometry import _from_tensor, _to_tensor
from reconstruction.stages.fitting.jacobian import _tensor_system
from reconstruction.stages.fitting.model import _loss
from reconstruction.stages.fitting.problem import _chunk_size, _Problem


def _joint_roughness(prob: _Problem, q: torch.Tensor, rho_d: torch.Tensor, grid_shape, resume: dict | None = None,
                     save=None, tick=None) -> tuple[torch.Tensor, dict]:
    """All texels' numbers at once under a smoothness prior on the roughness (ours;
    FitConfig.alpha_prior = tau). Minimises, over x_i = [u, v, m, c, s] (_to_tensor: the normal's two numbers,
    the mean log alpha and the anisotropy as a vector at twice the tangent angle, so that neighbours compare
    lobes, not axis labels),
        F = sum_i |r_i(x_i)|^2 / sigma^2 + sum_{i~j} w_ij |a_i - a_j|^2 / tau^2,   a = [m, c, s],
    r_i the texel's residuals (model._residuals: its photos and lumitexel, albedos in closed form), sigma^2 their
    median per-texel variance at the start (this capture's noise and misfit level), i~j 4-neighbours weighted
    by their diffuse colour's likeness (_colour_weights), by Levenberg-Marquardt on the joint problem: the
    per-texel 5 x 5 Gauss-Newton blocks coupled by the prior's grid Laplacian, each step solved by block
    conjugate gradients (_block_pcg). A texel with a clear lobe keeps its own roughness; one whose photos
    barely see the lobe takes its material's. Why: on the mini rig a rough, weak lobe (the material suite's fabric
    and paper) is a percent or two of a photo, near the per-texel noise of the extracted photos, so a texel's own
    fit errs by tens of percent and noise turns an isotropic lobe anisotropic, while the noise-free oracle fit is
    exact (docs/accuracy.md). The photos of a region are pooled, not its per-texel estimates, which noise biases.

    How it is solved, and why (docs/accuracy.md: a simpler loop stopped far from F's minimum and left paper stock's
    roughness low, where F's minimum is not):
    - The texels whose own photos pin their roughness (_pinned, at the start: a sharp lobe, ink and foil) stay where
      their own fit put them; they still enter F and hold their neighbours through the prior, and only the others
      are evaluated again. Their lobes are the most nonlinear in x, and a step that overshot one of them would refuse
      the whole trial.
    - A damping mu_i per texel (Marquardt's, scaled by the block's diagonal): after a trial, a texel whose data term
      changed as its Gauss-Newton model predicted (to half the prediction) divides its mu by 3, any other doubles
      it; a refused trial (F did not fall) multiplies the latter's by 4 (every texel's, if each held). With one mu
      for all, the worst-modelled texel would set it for all, and the flat directions of the weak lobes, where the
      pooled roughness moves by a small fraction of its distance a step, would stay damped.
    - It stops when a kept trial lowers F by less than FitConfig.tolerance times n (R_i - 5), F's size were every
      texel fitted to its noise (R_i residuals a texel), not times F, which the misfit of a few mixed texels (a
      printed edge's) can make a hundred times that.
    `resume`: the state a killed run saved (direct._fit_direct's checkpoint), from which the loop goes on as it would
    have; `save(state)` and `tick()` (progress) are called after every trial. Returns (q, info); info's
    joint_trials lists each trial's [median mu of the free texels, its relative change of F, the share of free texels
    whose model held] (a refused one's change >= 0), joint_pinned the count of pinned texels."""
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
        # a trial step is evaluated by its loss alone, and a kept one's Gauss-Newton system computed after: a pass of
        # losses costs less than half of one of systems (docs/performance.md)
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
        if tick is not None:
            tick()
    out = _from_tensor(x.float())
    out[:, 3:5] = out[:, 3:5].clamp(lo, hi)
    return out, {"joint_steps": kept, "joint_cg_iterations": cg, "joint_objective": [F0, F],
                 "joint_sigma2": sigma2, "joint_trials": trials, "joint_pinned": int(frozen.sum())}


def _joint_albedos(prob: _Problem, sums: list, rho_d: torch.Tensor, rho_s: torch.Tensor, grid_shape,
                   sigma2: float) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The albedos of every texel at once, for the albedo quadratics `sums` (model._albedo_sums per chunk of texels,
    from direct._final at the final geometry), under the same prior on rho_s as the roughness's
    (_joint_roughness; ours): minimises
        sum_i Q_i(rho_d_i, rho_s_i) / sigma^2 + sum_{i~j} w_ij |rho_s_i - rho_s_j|^2 / (tau rho_ij)^2
    per channel, Q_i the texel's albedo quadratic (model._albedo_sums, the loss to second order), w_ij the colour
    weights (_colour_weights), rho_ij the pair's mean grey rho_s from its own fit (>= 0.05): a relative change
    of tau between neighbours of one material. Linear, solved by block conjugate gradients (6 unknowns a
    texel), then clamped to the boxes. Why: once the roughness is pooled, a weak lobe's rho_s is still each
    texel's own, and its photos fix it no better than its roughness (fabric's, docs/accuracy.md). Returns
    (rho_d, rho_s, conjugate-gradient iterations)."""
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


def _residual_count(prob: _Problem) -> int:
    """The number of residuals of a texel (model._residuals): 3 per LED and per photo."""
    return 3 * prob.leds + sum(3 * int(g.W.shape[2]) for g in (prob.photos if prob.has_lines else ()))


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
