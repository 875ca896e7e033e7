"""torch.autograd bridge to the Warp forward model.

`WarpForward` records the lumitexel kernel (and, for measurements, the projection kernel) on a
`wp.Tape`; its backward seeds the output adjoint with torch's gradient and replays the tape, so
gradients reach the per-point parameters (position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y,
transparency) and the pattern weights. float64 tensors run the float64 kernels (used by gradcheck).
Inputs are copied into the tape's own arrays: Warp's backward reads the arrays' current values
(warp#1350), so later in-place edits of the caller's tensors must not reach it.
"""
from __future__ import annotations

import contextlib

import numpy as np
import torch
import warp as wp

from twin.optics import lumitexel as K
from twin.optics.inputs import (CONVENTIONS, _init, _led_inputs, make_options, rig_arrays, validate_patterns,
                                validate_points)


@contextlib.contextmanager
def tf32_products(enabled: bool):
    """CUDA matrix products inside may use TF32 (tensor cores: a 10-bit mantissa, float32 range and sums) when
    `enabled`, and may not otherwise; torch's global setting is the caller's again after. The CPU's products are
    float32 either way."""
    flags = torch.backends.cuda.matmul
    before = flags.allow_tf32
    flags.allow_tf32 = bool(enabled)
    try:
        yield
    finally:
        flags.allow_tf32 = before


def _wp_device(t: torch.Tensor) -> str:
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"


def rig_setup(setup, device: str, double: bool):
    """The rig's device arrays, the kernels' Options and the camera's centre array for `setup` = (rig, convention,
    camera, g, fresnel, eta, visibility); a KeyError naming the rig's cameras for an unknown one."""
    rig, convention, camera, g, fresnel, eta, visibility = setup
    arrays = rig_arrays(rig, device, "float64" if double else "float32")
    o = make_options(rig, arrays, convention, g, fresnel, eta, visibility)
    cam_name = camera or next(iter(rig.cameras))
    if cam_name not in arrays.cameras:
        raise KeyError(f"rig {rig.name!r} has no camera {cam_name!r}; it has {list(rig.cameras)}")
    return arrays, o, arrays.cameras[cam_name]


def _launch(setup, pos, n, t, rd, rs, ax, ay, beta, w, grad: bool):
    """Run the lumitexel kernel (and, with pattern weights w, the projection) on the inputs: (output, the
    Warp input arrays, the tape). With `grad`, the inputs are copied into arrays that carry gradients (module
    docstring) and the launches are recorded on a tape; without, the kernels read torch's memory in place and
    nothing is recorded (the fit's evaluations under torch.no_grad: the same values, no copies)."""
    rig, convention = setup[:2]
    device = _wp_device(pos)
    double = pos.dtype == torch.float64
    vec, scal = (wp.vec3d, wp.float64) if double else (wp.vec3f, wp.float32)
    arrays, o, cam = rig_setup(setup, device, double)

    def copy(x, dtype):
        a = wp.from_torch(x.detach().contiguous(), dtype=dtype)
        return wp.clone(a, requires_grad=True) if grad else a

    ins = [copy(pos, vec), copy(n, vec), copy(t, vec), copy(rd, vec), copy(rs, vec), copy(ax, scal),
           copy(ay, scal), copy(beta, scal)]
    P, L = pos.shape[0], rig.num_leds
    m = (wp.zeros if grad else wp.empty)((P, L), dtype=vec, device=device, requires_grad=grad)
    tape = wp.Tape() if grad else None
    with tape or contextlib.nullcontext():
        pts = K.point_inputs(*ins, cam, device)
        wp.launch(K.lumitexel_kernel, dim=(P, L), inputs=[*pts, *_led_inputs(arrays, CONVENTIONS[convention]), o],
                  outputs=[m], device=device)
        out = m
        if w is not None:
            W = copy(w, vec)
            ins.append(W)
            out = wp.zeros((P, w.shape[0]), dtype=vec, device=device, requires_grad=grad)
            wp.launch(K.project_kernel, dim=out.shape, inputs=[m, W], outputs=[out], device=device)
    return out, ins, tape


def _apply(setup, *args) -> torch.Tensor:
    """WarpForward where torch records gradients for one of the inputs, else a plain launch."""
    if torch.is_grad_enabled() and any(torch.is_tensor(a) and a.requires_grad for a in args):
        return WarpForward.apply(setup, *args)
    dev = args[0].device
    if dev.type != "cuda":
        return wp.to_torch(_launch(setup, *args, grad=False)[0])
    # the kernels read torch's memory in place, so they run on torch's stream: the inputs torch frees when this
    # returns (contiguous copies) are reused only by work queued after them
    _init()  # Warp's runtime, before the stream is looked up
    with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(dev))):
        return wp.to_torch(_launch(setup, *args, grad=False)[0])


class WarpForward(torch.autograd.Function):
    @staticmethod
    def forward(ctx, setup, pos, n, t, rd, rs, ax, ay, beta, w):
        out, ctx.ins, ctx.tape = _launch(setup, pos, n, t, rd, rs, ax, ay, beta, w, grad=True)
        ctx.out = out
        return wp.to_torch(out).clone()

    @staticmethod
    def backward(ctx, grad):
        vec = ctx.out.dtype
        ctx.out.grad = wp.from_torch(grad.contiguous(), dtype=vec)
        ctx.tape.backward()
        grads = [wp.to_torch(a.grad).clone() for a in ctx.ins]
        ctx.tape.zero()
        if len(grads) == 8:
            grads.append(None)
        return (None, *grads)


def _tensors(pos, n, t, rd, rs, ax, ay, transparency, device):
    """Validate (clear errors, as the numpy path) and bring every input to one torch dtype/device."""
    validate_points(pos, n, t, rd, rs, ax, ay, transparency)
    ref = next(x for x in (pos, n, t, rd, rs, ax, ay) if torch.is_tensor(x))
    dtype = torch.float64 if any(torch.is_tensor(x) and x.dtype == torch.float64 for x in (pos, n, t, rd, rs, ax, ay)) \
        else torch.float32
    dev = ref.device if device in (None, "cpu") and ref.device.type != "cpu" else torch.device(
        "cpu" if device in (None, "cpu") else device)

    def T(x):
        return (x if torch.is_tensor(x) else torch.as_tensor(np.asarray(x))).to(dev, dtype)

    P = T(pos).shape[0]
    rd_t, rs_t = T(rd), T(rs)
    rd_t = rd_t.reshape(P, 1).expand(P, 3) if rd_t.ndim == 1 else rd_t
    rs_t = rs_t.reshape(P, 1).expand(P, 3) if rs_t.ndim == 1 else rs_t
    beta = torch.zeros(P, dtype=dtype, device=dev) if transparency is None else T(transparency).reshape(P)
    return T(pos), T(n), T(t), rd_t, rs_t, T(ax).reshape(P), T(ay).reshape(P), beta


def lumitexels_torch(rig, pos, n, t, rd, rs, ax, ay, *, convention, device, camera, transparency, g, fresnel,
                     eta, visibility):
    args = _tensors(pos, n, t, rd, rs, ax, ay, transparency, device)
    return _apply((rig, convention, camera, g, fresnel, eta, visibility), *args, None)


def measurements_torch(rig, pos, n, t, rd, rs, ax, ay, patterns, *, convention, device, camera, transparency, g,
                       fresnel, eta, visibility):
    args = _tensors(pos, n, t, rd, rs, ax, ay, transparency, device)
    if hasattr(patterns, "levels"):
        patterns = patterns.weights
    validate_patterns(patterns, rig.num_leds)
    w = patterns if torch.is_tensor(patterns) else torch.as_tensor(np.asarray(patterns))
    w = w.to(args[0].device, args[0].dtype)
    if w.ndim == 2:
        w = w[..., None].expand(*w.shape, 3)
    return _apply((rig, convention, camera, g, fresnel, eta, visibility), *args, w)
