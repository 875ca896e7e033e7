"""The direct and neural methods' numbers <-> GGX geometry, and the derivatives of the local frame along them (paper
§7.2, reference §5).

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
    (0.006 + 0.497 sigmoid), log-spaced so that steps are relative changes of alpha, as the metric
    |log alpha| error is (_geometry). The direct method works in [u, v, theta, log alpha_x, log alpha_y]
    (_log_geometry), its Levenberg-Marquardt clamping the log alphas to the range, and its joint prior in the log
    roughness tensor's coordinates (_to_tensor).
"""
from __future__ import annotations

import math

import torch

from reconstruction.stages.fitting.config import GEOMETRY_SIZE, FitConfig
from reconstruction.stages.fitting.problem import _Problem


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


def _frame_derivatives(prob: _Problem, q: torch.Tensor) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The geometry of the numbers q and the inputs of twin.optics.jvp.basis_jvp for the 5 numbers' directions:
    d_frame (n, 5, 3, 3), the derivatives of the local frame's rows (t, n x t, n) along u, v, theta (zero along
    the log alphas), and d_log_alpha (n, 5, 2). In closed form, the chain rule through _frame_of's steps (ours: a
    few times faster than torch.func's batched forward mode; tests/reconstruction/test_fitting.py checks it against
    torch.func.jacfwd of _frame_of)."""
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
