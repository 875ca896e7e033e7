"""The forward model's public API: lumitexels (paper Eq. 1) and pattern measurements (Eq. 2).

    twin.lumitexels(rig, position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, *,
                    convention="physical" | "opensvbrdf", device="cpu", ...) -> (P, L, 3)
    twin.measurements(rig, ..., patterns, ...) -> (P, K, 3)

Per-point arguments are arrays (numpy or torch; a torch input gives a torch output on the same device,
differentiable through `torch.autograd`). Positions are in the rig's unit (mm); position, normal and
tangent are world coordinates (twin.rig.units).

Conventions (units and scale constant):
``physical`` (default)
    LED intensity I in W/sr at full drive (rig.leds.intensity, relative), distances converted from mm
    to metres, so m is the radiance towards the camera in W m^-2 sr^-1 per unit drive: S = 1. The LED
    profile Psi of the rig, visibility V against the holder frame (wp.Mesh ray queries) and the bottom
    LEDs through the acrylic board (transparency beta) are all on. Exact GGX (no regularisers).
``opensvbrdf``
    Reproduces the authors' released renderer (reference §2.1-2.2): point emitters with Psi = 1 (the
    Lambertian (-wi . n_l)+ factor only), I = 1, V = 1, no bottom-LED light, distances in mm with
    r^2 + 1e-6, (wi . n) < 1e-6 cut, their 1e-6 BRDF regularisers, and S = 100 pi ("renderer units";
    multiply by 3000/pi for their photo units, reference §2.1).
"""
from __future__ import annotations

import numpy as np
import warp as wp

from twin.optics import lumitexel as K
from twin.optics.inputs import (CONVENTIONS, _device_inputs, _is_torch, _led_inputs, make_options, validate_patterns,
                                validate_points)


def lumitexels(rig, position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, *, convention="physical",
               device="cpu", camera=None, transparency=None, g="separable", fresnel="schlick", eta=1.5,
               visibility=None, dtype="float32", output="numpy", fast=False):
    """Lumitexels m[p, l, c] (paper Eq. 1) of P points under each of the rig's L LEDs, seen from
    `camera` (default: the rig's first camera). Inputs: position (P, 3) mm, normal and tangent (P, 3) unit
    vectors (the tangent is alpha_x's axis), all in the rig's world frame (twin.rig.units); rho_d, rho_s (P, 3);
    alpha_x, alpha_y (P,) GGX roughness; transparency (P,) or None. Returns numpy (P, L, 3) in the convention's
    units (module docstring: W m^-2 sr^-1 per unit drive for "physical"), or torch if the inputs are
    torch tensors (then differentiable w.r.t. normal, tangent, rho_d, rho_s, alpha_x, alpha_y).
    output="torch" with array inputs returns a torch tensor on `device` that shares the kernel's output
    memory (zero-copy, no autograd): training data made on the device where the network trains.
    fast=True (array inputs): the fast-math kernel (lumitexel.lumitexel_rows_kernel_fast: faster on a GPU,
    docs/performance.md; within the float32 paths' same-work tolerance of the default)."""
    if any(_is_torch(x) for x in (position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y)):
        from twin.optics.torch_ops import lumitexels_torch

        return lumitexels_torch(rig, position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y,
                                convention=convention, device=device, camera=camera, transparency=transparency,
                                g=g, fresnel=fresnel, eta=eta, visibility=visibility)
    pts = validate_points(position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, transparency)
    arrays, wpts = _device_inputs(rig, device, dtype, camera, *pts)
    o = make_options(rig, arrays, convention, g, fresnel, eta, visibility)
    vec = wp.vec3d if dtype == "float64" else wp.vec3f
    out = wp.zeros((len(pts[0]), rig.num_leds), dtype=vec, device=device)
    K.materialise(wpts, _led_inputs(arrays, CONVENTIONS[convention]), o, out, device, fast)
    if output == "torch":
        return wp.to_torch(out)
    if output != "numpy":
        raise ValueError(f"output must be 'numpy' or 'torch', got {output!r}")
    return out.numpy()


# TF32 keeps 10 of float32's 23 mantissa bits: each factor of W m is off by at most 2^-10 relative (truncated;
# 2^-11 rounded), the product by 2 x 2^-10, and float32 sums of L = 12,288 terms add at most L 2^-24 = 7.3e-4. Every
# term is >= 0 for drives W >= 0 (m is radiance), so the sum's relative error is at most their sum, 2.7e-3.
# Measured on a GPU against a float64 projection of the same lumitexels: 5.4e-4 at most (docs/performance.md),
# against ~1% per-pixel sensor noise (docs/accuracy.md).
TF32_PROJECTION_RTOL = 3e-3


def project(m, w, tensor_cores: bool = False):
    """B[p, k, c] = sum_l W[k, l, c] m[p, l, c] (paper Eq. 2) for torch tensors m (P, L, 3) and w (K, L, 3), as one
    GEMM (P, 3L) x (3L, 3K) against the block-diagonal matrix of the channels' patterns: m is read in place, where a
    batched product per channel would first copy it into channel planes (most of its time on a GPU,
    docs/performance.md). tensor_cores=True lets that GEMM use TF32 (CUDA only; relative error <=
    TF32_PROJECTION_RTOL of sum_l |W| m), several times faster. Returns (P, K, 3)."""
    import torch

    from twin.optics.torch_ops import tf32_products

    if m.ndim != 3 or m.shape[2] != 3 or w.ndim != 3 or w.shape[1:] != m.shape[1:]:
        raise ValueError(f"project needs lumitexels (P, L, 3) and patterns (K, L, 3), got {tuple(m.shape)} and "
                         f"{tuple(w.shape)}")
    P, L, _ = m.shape
    Kn = w.shape[0]
    block = torch.zeros(L, 3, Kn, 3, dtype=m.dtype, device=m.device)
    for c in range(3):
        block[:, c, :, c] = w[:, :, c].T
    with tf32_products(tensor_cores):
        return (m.reshape(P, 3 * L) @ block.reshape(3 * L, 3 * Kn)).view(P, Kn, 3)


def measurements(rig, position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, patterns, *,
                 convention="physical", device="cpu", camera=None, transparency=None, g="separable",
                 fresnel="schlick", eta=1.5, visibility=None, method="fused", dtype="float32",
                 fast=False, tensor_cores=False):
    """Pattern measurements B[p, k, c] = sum_l W[k, l, c] m[p, l, c] (paper Eq. 2) of P points: (P, K, 3), the
    points as `lumitexels` takes them ((P, 3) mm positions, world frame), in lumitexels' units times the drive.
    `patterns`: (K, L, 3) or (K, L) relative drive (an LED's full drive is 1; a device's patterns lie in [0, 1]), or
    a twin.capture.patterns.PatternSet. method="fused" never stores the lumitexels
    (a tiled kernel on CUDA, a loop kernel on CPU); "materialise" computes them (fast: as `lumitexels` does), then
    projects (`project`, cuBLAS, on CUDA, where tensor_cores=True allows TF32 within TF32_PROJECTION_RTOL; the
    projection kernel on the CPU). On a GPU materialise with fast=True and tensor_cores=True is the fastest
    path (docs/performance.md)."""
    if any(_is_torch(x) for x in (position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, patterns)):
        from twin.optics.torch_ops import measurements_torch

        return measurements_torch(rig, position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, patterns,
                                  convention=convention, device=device, camera=camera, transparency=transparency,
                                  g=g, fresnel=fresnel, eta=eta, visibility=visibility)
    if method == "fused" and (fast or tensor_cores):
        raise ValueError("fast and tensor_cores apply to method='materialise' only")
    pts = validate_points(position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, transparency)
    w = validate_patterns(patterns, rig.num_leds)
    arrays, wpts = _device_inputs(rig, device, dtype, camera, *pts)
    o = make_options(rig, arrays, convention, g, fresnel, eta, visibility)
    vec = wp.vec3d if dtype == "float64" else wp.vec3f
    npd = np.float64 if dtype == "float64" else np.float32
    P, Kn = len(pts[0]), w.shape[0]
    leds = _led_inputs(arrays, CONVENTIONS[convention])
    out = wp.zeros((P, Kn), dtype=vec, device=device)
    if method == "materialise":
        m = wp.zeros((P, rig.num_leds), dtype=vec, device=device)
        K.materialise(wpts, leds, o, m, device, fast)
        W = wp.array(w.astype(npd), dtype=vec, device=device)
        if wp.get_device(device).is_cuda:
            res = project(wp.to_torch(m), wp.to_torch(W), tensor_cores)
            wp.copy(out, wp.from_torch(res.contiguous(), dtype=vec))
        else:
            wp.launch(K.project_kernel, dim=out.shape, inputs=[m, W], outputs=[out], device=device)
    elif method == "fused":
        from twin.optics.fused import fused_measurements

        fused_measurements(wpts, leds, o, w.astype(npd), out, device)
    else:
        raise ValueError(f"unknown method {method!r}; expected 'fused' or 'materialise'")
    return out.numpy()
