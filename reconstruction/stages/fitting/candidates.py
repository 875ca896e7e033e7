"""The GGX fit's initial candidates (paper §7.2; ours), where both methods start.

Candidate geometries: the plane normal, and for texels whose specular peak or diffuse shading points elsewhere the
half vector of that peak (_peak_normal) and the photometric-stereo normal (_diffuse_normal); times a few isotropic
and anisotropic roughness pairs and tangent angles (FitConfig.init_alphas, init_thetas), each with its closed-form
albedos. Each texel starts from its lowest-loss candidate, ranked on the primary view's lumitexels and photos
(_initial). The neural method first regresses its heads onto these numbers (warm start).
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch

from reconstruction.stages.fitting.config import GEOMETRY_SIZE, FitConfig
from reconstruction.stages.fitting.geometry import _encode_geometry, _geometry, _unit
from reconstruction.stages.fitting.model import _grey, _projected_loss
from reconstruction.stages.fitting.problem import _Problem


def _initial(prob: _Problem):
    """(geometry numbers (n, 5), rho_d, rho_s) of the best initial candidate per texel. The normal first: the plane
    normal, and where they point elsewhere (> 1 deg off), the specular peak's half vector (_peak_normal) and the
    diffuse shading's normal (_diffuse_normal), each with the isotropic roughness candidates; then the
    anisotropic candidates at each texel's best normal (_candidate_pairs)."""
    # candidates are ranked on config.camera's lumitexels and photos alone (ours): the other view's photos, with
    # albedos of their own (model._projected), inform the geometry that Levenberg-Marquardt refines, and ranking with
    # them doubles the candidates' cost for no gain on the material suite (docs/accuracy.md).
    # The anisotropic candidates at the best normal only (ours): by default they are 18 of the 22 candidates, and at
    # each of up to three normals they were a large share of the fit's time on the paper rig; which normal is best is
    # decided by where the lobe points, which the isotropic candidates see as well (docs/performance.md)
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
    paper rig these projections are a large share of the candidates' time (docs/performance.md)."""
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
    whose ratio lies between a tenth of those ratios' median and the median (below the highlight). Why: where the
    mirror direction of a steeply tilted texel leaves the LED dome, the brightest LED sits at the dome's edge and its
    half vector (_peak_normal) points far from the normal: on the paper rig, random texels tilted 43-59 deg fell into
    a rough-lobe basin less than half as often with this candidate as without it (docs/performance.md). The plane
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
