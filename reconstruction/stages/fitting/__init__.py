"""GGX and local-frame fitting per texel (paper §7.2, reference §5): the decoded RGB lumitexels (and the
line-light measurements) -> anisotropic GGX parameters and a world-frame shading frame -> OpenSVBRDF maps.

    result = fit_ggx(rig, positions, lumitexels, lines=..., line_weights=..., config=FitConfig())
    maps = to_maps(result, grid_shape, size_mm, transparency, name)      # twin.materials.samples.SVBRDFMaps

Methods (FITTING_METHODS, dispatched by `fit_method`, one function each):
  * "direct" (ours): Levenberg-Marquardt on the 5 geometry numbers per texel, the albedos in closed form at
    every evaluation (variable projection), with an analytic Jacobian, in chunks of texels; on a grid, neighbour
    propagation, then the joint prior on roughness and specular albedo, which couples neighbouring texels of one
    material so that a lobe the photos barely see is pooled (the module direct).
  * "neural" (reference §5): a feature texture and 5 MLP heads trained by Adam (the module neural).
Both start from the best of a few candidate geometries per texel (the module candidates).

The modules, in the order a fit uses them:
    config       FitConfig, FitResult and the names of the choices (why the defaults)
    problem      the inputs checked on a device, the loss's transform, chunks of texels
    geometry     the unconstrained numbers <-> normal, tangent and roughness (the parameterisation)
    model        the forward model, the albedos in closed form, the loss (the physics)
    sums         the per-texel sums over the LEDs, in Warp
    jacobian     the Gauss-Newton system, analytic or by forward differences
    candidates   the initial candidates
    solver       Levenberg-Marquardt, neighbour propagation
    joint        the joint prior on roughness and specular albedo
    direct       the direct method: chunks, propagation, joint prior, checkpoints, refits
    neural       the neural method
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from twin.materials.samples import ALPHA_RANGE, RHO_D_RANGE, RHO_S_RANGE, SVBRDFMaps, canonical_anisotropy

from reconstruction.stages.fitting.config import LOSSES, METHODS, FitConfig, FitResult
from reconstruction.stages.fitting.direct import _fit_direct
from reconstruction.stages.fitting.neural import _fit_neural
from reconstruction.stages.fitting.problem import _problem

__all__ = ["FitConfig", "FitResult", "fit_ggx", "fit_method", "to_maps", "FITTING_METHODS", "METHODS", "LOSSES"]


# one function per method, all (problem, grid_shape) -> FitResult (colour-science style dispatch)
FITTING_METHODS = {"direct": _fit_direct, "neural": _fit_neural}


def fit_method(rig, positions, lumitexels, *, method: str | None = None, lines=None, line_weights=None,
               secondary=None, grid_shape=None, config: FitConfig = FitConfig(), checkpoint=None,
               start=None, progress: bool = False) -> FitResult:
    """Dispatch to FITTING_METHODS[method] (None: config.method) after checking the inputs (fit_ggx)."""
    if not isinstance(config, FitConfig):
        raise ValueError(f"config must be a FitConfig, got {type(config).__name__}")
    if method is not None and method != config.method:
        config = replace(config, method=method)
    direct = {k: v for k, v in (("checkpoint", checkpoint), ("start", start)) if v is not None}
    if direct and config.method != "direct":
        raise ValueError(f"a checkpoint or a refit's start belongs to the direct method only, not {config.method!r}")
    if progress and config.method == "direct":  # the direct method's bar (the neural one's steps show none)
        direct["progress"] = True
    prob = _problem(rig, positions, lumitexels, lines, line_weights, grid_shape, config, secondary)
    return FITTING_METHODS[config.method](prob, grid_shape, **direct)


def fit_ggx(rig, positions, lumitexels, *, lines=None, line_weights=None, secondary=None, grid_shape=None,
            config: FitConfig = FitConfig(), checkpoint=None, start=None, progress: bool = False) -> FitResult:
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
    state so that a killed fit resumes (direct._fit_direct); start (direct method): a refit of some texels after
    their photos changed, from an earlier fit's numbers (direct._fit_direct). Raises ValueError on NaN/Inf or
    mis-shaped input (a source's, when the fit asks for those texels). Deterministic on the CPU: the same inputs and
    seed give the same result. progress: a bar on a terminal (twin.progress; the direct method's)."""
    return fit_method(rig, positions, lumitexels, lines=lines, line_weights=line_weights, secondary=secondary,
                      grid_shape=grid_shape, config=config, checkpoint=checkpoint, start=start, progress=progress)


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
