"""Warp kernels for lumitexels (paper Eq. 1-2) and pattern measurements.

One function, `led_response`, evaluates Eq. 1 for one surface point and one LED:

    m[c] = S * I_l[c] * A_l(-wi) * V(l, p) * f_c(wi, wo) * (wi . n)+ / r^2          (upper LEDs)
    m[c] = S * I_l[c] * A_l(-wi) * V(l, p) * T_acrylic * beta / pi * (-wi . z)+ / r^2  (bottom LEDs)

with A_l = Psi_l * (-wi . n_l)+ (twin.optics.emitter). Bottom LEDs light the sample from below through the
diffusing acrylic board and the sample's transparency beta; both diffuse, so the transmitted radiance is
Lambertian (1/pi) and independent of the view and of the shading normal (the geometric plane normal z
sets the irradiance cosine). Refraction in the thin slab is neglected. Every kernel is generic over
float32 / float64 (float64 for gradient checks) and is defined at import time.

Kernels:
  * point_frames_kernel (P,) each point's local frame and view direction, once
  * lumitexel_kernel   (P, L)  materialises m[p, l]           (differentiable: the torch bridge's tape)
  * lumitexel_rows_kernel (P, LED_STRIDE) the same m, forward only: `materialise` on CUDA; its twin
    lumitexel_rows_kernel_fast compiled with fast math (materialise(fast=True))
  * project_kernel     (P, K)  B[p, k] = sum_l W[k, l] m[p, l] (differentiable w.r.t. m and W)
  * fused_loop_kernel  (P,)    B without storing m: portable loop, used on CPU
  * fused_tile_kernel  blocks  B without storing m: tiles in shared memory + tile_matmul, used on CUDA

`point_frames_kernel_exact` and `lumitexel_kernel_exact` are the same kernels compiled without
floating-point contraction (no FMA fusion): the two compilers place fused multiply-adds differently, so only
then do +, -, *, / and sqrt round identically on the CPU and on CUDA. The virtual capture renders with them,
so that one seed gives the same raw bytes on both devices (twin.camera.imaging); training keeps the fused
ones. They are forward only (no adjoint code, which halves a cold kernel cache's compile time).
"""
from __future__ import annotations

from typing import Any

import warp as wp

from twin.optics.emitter import led_intensity
from twin.optics.ggx import ggx_brdf, local_frame


@wp.struct
class Options:
    """Convention constants (twin.optics.inputs.CONVENTIONS), float32; kernels cast them to their float type."""

    g_mode: int
    f_mode: int
    profile_mode: int
    eta: float
    eps: float  # the authors' BRDF regulariser (1e-6) or 0
    length_scale: float  # rig unit -> unit of r in 1/r^2 (1e-3: mm -> m; 1: mm)
    r2_eps: float  # added to r^2 (the authors' 1e-6)
    min_cos_i: float  # (wi . n) below this gives 0 (the authors' 1e-6)
    scale: float  # overall constant S
    use_bottom: int  # bottom LEDs transmit through the acrylic (physical) or give 0 (OpenSVBRDF)
    acrylic_transmission: float
    plane_normal: wp.vec3
    use_visibility: int
    mesh: wp.uint64
    ray_offset: float  # start visibility rays this far (rig units) off the surface
    plane_origin: wp.vec3
    plane_x: wp.vec3
    plane_y: wp.vec3
    occluder_top: float  # every occluder lies below this height above the sample plane, inside the
    occluder_outer: float  # centred square of this half-size and outside the centred square window
    occluder_hole: float  # of this half-size (the holder frame's ring)


@wp.func
def visible(x: wp.vec3, wi: wp.vec3, r: float, o: Options):
    """V(l, p): 1 when the segment from the point to the LED misses every occluder mesh. Exact shortcuts
    first (the occluders fill at most the ring between two centred squares, below a height): a ray that
    rises above that height before its horizontal travel can reach the ring cannot hit it, nor can a ray
    leaving the ring's top face upwards. The remaining rays query the BVH (wp.Mesh)."""
    q = x - o.plane_origin
    h = wp.dot(q, o.plane_normal)
    wn = wp.dot(wi, o.plane_normal)
    if wn > 0.0:
        climb = (o.occluder_top - h) / wn  # ray length until above every occluder
        if climb <= o.ray_offset:
            return True
        travel = climb * wp.sqrt(wp.max(1.0 - wn * wn, 0.0))  # horizontal distance meanwhile
        cheb = wp.max(wp.abs(wp.dot(q, o.plane_x)), wp.abs(wp.dot(q, o.plane_y)))
        if cheb + travel < o.occluder_hole:  # stays inside the window
            return True
        if cheb - travel > o.occluder_outer:  # stays outside the ring (Euclidean >= Chebyshev distance)
            return True
    hit = wp.mesh_query_ray(o.mesh, x + wi * o.ray_offset, wi, r - o.ray_offset)
    return not hit.result


@wp.func
def led_response(x: Any, frame: Any, wo_l: Any, rho_d: Any, rho_s: Any, ax: Any, ay: Any, beta: Any,
                 lp: Any, ln: Any, lu: Any, li: Any, prof: wp.array2d(dtype=Any), l: int, bottom: int,
                 o: Options):
    """Eq. 1 for one point and one LED (see module docstring); returns an RGB vector. `frame` is the
    point's world->local rotation and `wo_l` its local view direction (point_frames_kernel)."""
    zero = ax * type(ax)(0.0)
    d = lp - x
    r2 = wp.dot(d, d)
    r = wp.sqrt(r2)
    wi = d / r
    a = led_intensity(-wi, ln, lu, prof, l, o.profile_mode)
    if a <= zero:
        return type(wi)(zero, zero, zero)
    ls = type(ax)(o.length_scale)
    inv_r2 = type(ax)(1.0) / (r2 * ls * ls + type(ax)(o.r2_eps))
    if bottom != 0:
        c = -wp.dot(wi, type(wi)(o.plane_normal))
        if o.use_bottom == 0 or c <= zero:
            return type(wi)(zero, zero, zero)
        k = type(ax)(o.acrylic_transmission) * beta * type(ax)(0.3183098861837907) * a * c * inv_r2
        val = wp.cw_mul(li, type(li)(k, k, k))
    else:
        wi_l = frame * wi
        if wi_l[2] < type(ax)(o.min_cos_i) or wi_l[2] <= zero:
            return type(wi)(zero, zero, zero)
        f = ggx_brdf(wi_l, wo_l, rho_d, rho_s, ax, ay, o.g_mode, o.f_mode, type(ax)(o.eta), type(ax)(o.eps))
        val = wp.cw_mul(li, f) * (a * wi_l[2] * inv_r2)
    if o.use_visibility != 0:
        if not visible(wp.vec3(x), wp.vec3(wi), float(r), o):
            return type(wi)(zero, zero, zero)
    return val * type(ax)(o.scale)


def _point_frames(pos: wp.array(dtype=Any), nrm: wp.array(dtype=Any), tan: wp.array(dtype=Any),
                  cam: wp.array(dtype=Any), frames: wp.array(dtype=Any), wo_l: wp.array(dtype=Any)):
    """Per point, once: the local frame (t', b, n) (Gram-Schmidt, ggx.local_frame) and the view
    direction in it. Every LED of the point reuses them."""
    p = wp.tid()
    f = local_frame(nrm[p], tan[p])
    frames[p] = f
    wo_l[p] = f * wp.normalize(cam[0] - pos[p])


def _lumitexel(pos: wp.array(dtype=Any), frames: wp.array(dtype=Any), wo_l: wp.array(dtype=Any),
               rho_d: wp.array(dtype=Any), rho_s: wp.array(dtype=Any), ax: wp.array(dtype=Any),
               ay: wp.array(dtype=Any), beta: wp.array(dtype=Any),
               lpos: wp.array(dtype=Any), lnrm: wp.array(dtype=Any), lu: wp.array(dtype=Any),
               lint: wp.array(dtype=Any), prof: wp.array2d(dtype=Any), lbot: wp.array(dtype=wp.int32),
               o: Options, out: wp.array2d(dtype=Any)):
    p, l = wp.tid()
    out[p, l] = led_response(pos[p], frames[p], wo_l[p], rho_d[p], rho_s[p], ax[p], ay[p], beta[p],
                             lpos[l], lnrm[l], lu[l], lint[l], prof, l, lbot[l], o)


LED_STRIDE = wp.constant(512)  # threads per point in lumitexel_rows_kernel (faster than 256; docs/performance.md)


def _lumitexel_rows(pos: wp.array(dtype=Any), frames: wp.array(dtype=Any), wo_l: wp.array(dtype=Any),
                    rho_d: wp.array(dtype=Any), rho_s: wp.array(dtype=Any), ax: wp.array(dtype=Any),
                    ay: wp.array(dtype=Any), beta: wp.array(dtype=Any),
                    lpos: wp.array(dtype=Any), lnrm: wp.array(dtype=Any), lu: wp.array(dtype=Any),
                    lint: wp.array(dtype=Any), prof: wp.array2d(dtype=Any), lbot: wp.array(dtype=wp.int32),
                    o: Options, out: wp.array2d(dtype=Any)):
    """_lumitexel with thread (p, j) evaluating LEDs j, j + LED_STRIDE, ... of point p. Why (Nsight
    Compute, docs/performance.md): one thread per (p, l) spent ~300 of its ~650 instructions
    per evaluation on array indexing and loads, 24 floats of them the point's, the same for every LED; here
    they are loaded once per thread, and a warp's LEDs stay consecutive, so the stores stay coalesced."""
    p, j = wp.tid()
    x, f, w, rd, rs, a, b, be = pos[p], frames[p], wo_l[p], rho_d[p], rho_s[p], ax[p], ay[p], beta[p]
    for l in range(j, lpos.shape[0], LED_STRIDE):
        out[p, l] = led_response(x, f, w, rd, rs, a, b, be, lpos[l], lnrm[l], lu[l], lint[l], prof, l, lbot[l], o)


point_frames_kernel = wp.kernel(_point_frames)
lumitexel_kernel = wp.kernel(_lumitexel)
# Forward only: a dynamic loop has no adjoint. The fast twin is compiled with fast math: approximate division
# and square root (<= 2 ulp) and denormals flushed, which no lumitexel of alpha >= 0.006 comes near. _lumitexel
# compiled with fast math against lumitexel_kernel on a GPU, over 65,536 random points x 12,288 LEDs: largest
# difference 7.9e-5 of |m| + 1e-6 max |m|, 99.999th percentile 9.7e-6 (docs/performance.md); the rows kernels are
# checked against lumitexel_kernel (tests/test_forward.py) and the bench's torch baseline within the float32
# paths' same-work tolerance (twin.bench.LUMITEXEL_RTOL), far below the sensor's ~1% noise.
lumitexel_rows_kernel = wp.kernel(enable_backward=False, module="unique")(_lumitexel_rows)
lumitexel_rows_kernel_fast = wp.kernel(enable_backward=False, module="unique",
                                       module_options={"fast_math": True})(_lumitexel_rows)


_EXACT = {"fuse_fp": False, "fast_math": False, "enable_backward": False}
point_frames_kernel_exact = wp.kernel(module="unique", module_options=_EXACT)(_point_frames)
lumitexel_kernel_exact = wp.kernel(module="unique", module_options=_EXACT)(_lumitexel)


@wp.kernel
def project_kernel(m: wp.array2d(dtype=Any), w: wp.array2d(dtype=Any), out: wp.array2d(dtype=Any)):
    """B[p, k] = sum_l W[k, l] (.) m[p, l], channel-wise (paper Eq. 2)."""
    p, k = wp.tid()
    acc = wp.cw_mul(w[k, 0], m[p, 0])
    for l in range(1, m.shape[1]):
        acc += wp.cw_mul(w[k, l], m[p, l])
    out[p, k] = acc


@wp.kernel
def fused_loop_kernel(pos: wp.array(dtype=Any), frames: wp.array(dtype=Any), wo_l: wp.array(dtype=Any),
                      rho_d: wp.array(dtype=Any), rho_s: wp.array(dtype=Any), ax: wp.array(dtype=Any),
                      ay: wp.array(dtype=Any), beta: wp.array(dtype=Any),
                      lpos: wp.array(dtype=Any), lnrm: wp.array(dtype=Any), lu: wp.array(dtype=Any),
                      lint: wp.array(dtype=Any), prof: wp.array2d(dtype=Any), lbot: wp.array(dtype=wp.int32),
                      o: Options, w: wp.array2d(dtype=Any), out: wp.array2d(dtype=Any)):
    """One thread per point: B[p, :] accumulated LED by LED, the lumitexel never stored. The row
    out[p, :] stays in the CPU's cache; on CUDA fused_tile_kernel (twin.optics.fused) is used instead."""
    p = wp.tid()
    for l in range(lpos.shape[0]):
        m = led_response(pos[p], frames[p], wo_l[p], rho_d[p], rho_s[p], ax[p], ay[p], beta[p], lpos[l], lnrm[l],
                         lu[l], lint[l], prof, l, lbot[l], o)
        if wp.length_sq(m) > ax[p] * type(ax[p])(0.0):
            for k in range(w.shape[0]):
                out[p, k] = out[p, k] + wp.cw_mul(w[k, l], m)


def materialise(point_args: list, led_args: list, o: Options, out: wp.array, device, fast: bool = False) -> None:
    """out[p, l] = m[p, l] for the points of point_inputs and the LEDs of inputs._led_inputs, without a tape:
    lumitexel_rows_kernel on CUDA, lumitexel_kernel on the CPU (one thread gains nothing from the rows, and its
    results stay the ones the torch bridge gives to the bit); fast=True: lumitexel_rows_kernel_fast on both."""
    cuda = wp.get_device(device).is_cuda
    if fast or cuda:
        wp.launch(lumitexel_rows_kernel_fast if fast else lumitexel_rows_kernel, dim=(out.shape[0], LED_STRIDE),
                  inputs=[*point_args, *led_args, o], outputs=[out], device=device, block_dim=128 if cuda else None)
    else:
        wp.launch(lumitexel_kernel, dim=out.shape, inputs=[*point_args, *led_args, o], outputs=[out], device=device)


def point_inputs(pos, nrm, tan, rho_d, rho_s, ax, ay, beta, cam, device, exact: bool = False) -> list:
    """Launch point_frames_kernel (recorded on an active wp.Tape, so gradients reach n and t; `exact`: its
    contraction-free twin) and return the per-point argument list every kernel above takes."""
    mat = wp.mat33d if pos.dtype == wp.vec3d else wp.mat33f
    frames = wp.zeros(pos.shape[0], dtype=mat, device=device, requires_grad=pos.requires_grad)
    wo_l = wp.zeros(pos.shape[0], dtype=pos.dtype, device=device, requires_grad=pos.requires_grad)
    wp.launch(point_frames_kernel_exact if exact else point_frames_kernel, dim=pos.shape[0],
              inputs=[pos, nrm, tan, cam], outputs=[frames, wo_l], device=device)
    return [pos, frames, wo_l, rho_d, rho_s, ax, ay, beta]
