"""The GGX fit's per-texel sums over the LEDs (reconstruction.stages.fitting), each in one Warp launch that reads the
grey bases and the targets once, instead of a chain of torch operations on (texels x LEDs x 3) tensors.

Why: on the paper rig a texel has 12,288 upper LEDs x 3 channels. Profiled on a GPU (docs/performance.md), the fit
spent most of its time not in the forward model's Warp kernels but in torch's element-wise work on those tensors
(the albedo quadratic's weighted products, the loss's log1p, the Jacobian's (texels x 5 x LEDs x 3) rows and their
products), each operation one pass over hundreds of MB.

Notation (reconstruction.stages.fitting.model's docstring): for texel p, LED l and channel c, the grey bases D0, S0
(p, l) and their derivatives dD0, dS0 (p, j, l) along the J = 5 geometry numbers, in network units; the channels
follow from the LEDs' intensity ratios rho0, rho1 (l, c): D = D0 rho0, S = S0 rho1. m the target lumitexel, f the
loss's transform (log1p or x / scale), w = f'(m)^2 / (3 L) its Gauss-Newton weight; f(m) and w are computed here
from m, so that the fit keeps one (texels x LEDs x 3) tensor, not three.

    albedo_sums       the albedo quadratic's sums over l of w [D D, D m, D S, S S, S m] (5 x 3 a texel) and, with
                      derivatives, their derivatives along j (5 x 5 x 3): model._albedo_sums, jacobian._linearisation
    lumitexel_terms   for albedos rd, rs (3) and, with derivatives, their derivatives da, db (5 x 3): the residuals
                      r = (f(rd D + rs S) - f(m)) / sqrt(3 L), their squared sum, and the Gauss-Newton system
                      J J^T (5 x 5) and J r (5) of their Jacobian rows f'(m_hat) / sqrt(3 L) (da D + rd dD + db S
                      + rs dS), without ever storing those rows (3 L x 5 numbers a texel)

Each launch is (texels, lanes) threads: a lane sums every lanes-th LED, and torch adds the lanes' partial sums in a
fixed order, so that a result does not depend on scheduling (no atomics): the same inputs give the same bytes on
one device. Lanes: 64 on CUDA (a texel's 12,288 LEDs over 64 threads keeps ~175,000 threads busy for a chunk of
2,730 texels); 1 on the CPU, whose Warp backend runs one thread. Float32 or float64, as the inputs are (the tests
check the float64 results against the torch expressions they replace).
"""
# no `from __future__ import annotations`: Warp reads the kernels' annotations, which name closure variables
import contextlib
import functools

import torch
import warp as wp

from twin.optics.inputs import _init

DERIVATIVES = 5  # the geometry numbers (config.GEOMETRY_SIZE)
SUMS = 5  # dd, dm, ds, ss, sm
CUDA_LANES = 64
LOSS_MODES = {"log1p": 0, "mse": 1}


@functools.lru_cache(maxsize=None)
def _kernels(scalar):
    """The two kernels for one float type (float32 or float64)."""
    vec3 = wp.types.vector(length=3, dtype=scalar)
    vec5 = wp.types.vector(length=DERIVATIVES, dtype=scalar)
    mat53 = wp.types.matrix(shape=(DERIVATIVES, 3), dtype=scalar)
    mat55 = wp.types.matrix(shape=(DERIVATIVES, DERIVATIVES), dtype=scalar)

    @wp.func
    def transform(x: scalar, mode: int, scale: scalar):
        """(f(x), f'(x)) of the loss's transform: log1p (accurate near 0: Goldberg 1991, Theorem 4) or x / scale."""
        one = scalar(1.0)
        if mode == 1:
            return x / scale, one / scale
        u = one + x
        f = x
        if u != one:
            f = wp.log(u) * x / (u - one)
        return f, one / u

    @wp.func
    def transform3(x: vec3, mode: int, scale: scalar):
        """(f(x), f'(x)) of each channel."""
        f0, k0 = transform(x[0], mode, scale)
        f1, k1 = transform(x[1], mode, scale)
        f2, k2 = transform(x[2], mode, scale)
        return vec3(f0, f1, f2), vec3(k0, k1, k2)

    @wp.func
    def bases(val: wp.array3d(dtype=scalar), rho0: wp.array(dtype=vec3), rho1: wp.array(dtype=vec3), p: int,
              l: int):
        """(D, S) of texel p and LED l in its three channels, and the LED's ratios (rho0, rho1)."""
        r0 = rho0[l]
        r1 = rho1[l]
        return val[0, p, l] * r0, val[1, p, l] * r1, r0, r1

    @wp.func
    def grey_derivatives(d_diffuse: wp.array3d(dtype=scalar), d_specular: wp.array3d(dtype=scalar), p: int, l: int):
        """(dD0, dS0): the grey bases' derivatives along the 5 numbers, of texel p and LED l."""
        return (vec5(d_diffuse[p, 0, l], d_diffuse[p, 1, l], d_diffuse[p, 2, l], d_diffuse[p, 3, l],
                     d_diffuse[p, 4, l]),
                vec5(d_specular[p, 0, l], d_specular[p, 1, l], d_specular[p, 2, l], d_specular[p, 3, l],
                     d_specular[p, 4, l]))

    @wp.func
    def rows(v: vec3):
        """The 5 x 3 matrix whose every row is v."""
        return wp.outer(vec5(scalar(1.0)), v)

    @wp.func
    def weight(m: vec3, mode: int, scale: scalar, inv2: scalar):
        """The Gauss-Newton weights f'(m)^2 / (3 L) of a target's three channels (inv2 = 1 / (3 L))."""
        f, k = transform3(m, mode, scale)
        return wp.cw_mul(k, k) * inv2

    @wp.kernel(enable_backward=False, module="unique")
    def albedo_sums(val: wp.array3d(dtype=scalar), d_diffuse: wp.array3d(dtype=scalar),
                    d_specular: wp.array3d(dtype=scalar), target: wp.array2d(dtype=vec3),
                    rho0: wp.array(dtype=vec3), rho1: wp.array(dtype=vec3), mode: int, scale: scalar,
                    inv2: scalar, derivatives: int, lanes: int, out: wp.array3d(dtype=mat53)):
        """(texels, lanes) threads; out[p, lane, 0] rows dd, dm, ds, ss, sm (x 3 channels), out[p, lane, 1 + k]
        the derivatives of sum k along the 5 numbers (rows) and channels (columns)."""
        p, lane = wp.tid()
        n_leds = val.shape[2]
        e0 = vec5(scalar(1.0), scalar(0.0), scalar(0.0), scalar(0.0), scalar(0.0))
        e1 = vec5(scalar(0.0), scalar(1.0), scalar(0.0), scalar(0.0), scalar(0.0))
        e2 = vec5(scalar(0.0), scalar(0.0), scalar(1.0), scalar(0.0), scalar(0.0))
        e3 = vec5(scalar(0.0), scalar(0.0), scalar(0.0), scalar(1.0), scalar(0.0))
        e4 = vec5(scalar(0.0), scalar(0.0), scalar(0.0), scalar(0.0), scalar(1.0))
        sums = mat53()
        d_dd = mat53()
        d_dm = mat53()
        d_ds = mat53()
        d_ss = mat53()
        d_sm = mat53()
        l = lane
        while l < n_leds:
            D, S, r0, r1 = bases(val, rho0, rho1, p, l)
            m = target[p, l]
            w = weight(m, mode, scale, inv2)
            wD = wp.cw_mul(w, D)
            wS = wp.cw_mul(w, S)
            sums += (wp.outer(e0, wp.cw_mul(wD, D)) + wp.outer(e1, wp.cw_mul(wD, m)) + wp.outer(e2, wp.cw_mul(wD, S))
                     + wp.outer(e3, wp.cw_mul(wS, S)) + wp.outer(e4, wp.cw_mul(wS, m)))
            if derivatives != 0:
                dd0, ds0 = grey_derivatives(d_diffuse, d_specular, p, l)
                w0 = wp.cw_mul(w, r0)
                w1 = wp.cw_mul(w, r1)
                d_dd += wp.outer(dd0, scalar(2.0) * wp.cw_mul(w0, D))
                d_dm += wp.outer(dd0, wp.cw_mul(w0, m))
                d_ds += wp.outer(dd0, wp.cw_mul(w0, S)) + wp.outer(ds0, wp.cw_mul(w1, D))
                d_ss += wp.outer(ds0, scalar(2.0) * wp.cw_mul(w1, S))
                d_sm += wp.outer(ds0, wp.cw_mul(w1, m))
            l += lanes
        out[p, lane, 0] = sums
        if derivatives != 0:
            out[p, lane, 1] = d_dd
            out[p, lane, 2] = d_dm
            out[p, lane, 3] = d_ds
            out[p, lane, 4] = d_ss
            out[p, lane, 5] = d_sm

    @wp.kernel(enable_backward=False, module="unique")
    def lumitexel_terms(val: wp.array3d(dtype=scalar), d_diffuse: wp.array3d(dtype=scalar),
                        d_specular: wp.array3d(dtype=scalar), target: wp.array2d(dtype=vec3),
                        rho0: wp.array(dtype=vec3), rho1: wp.array(dtype=vec3), rd: wp.array(dtype=vec3),
                        rs: wp.array(dtype=vec3), da: wp.array(dtype=mat53), db: wp.array(dtype=mat53), mode: int,
                        scale: scalar, inv: scalar, derivatives: int, lanes: int, loss: wp.array2d(dtype=scalar),
                        jj: wp.array2d(dtype=mat55), jr: wp.array2d(dtype=vec5)):
        """(texels, lanes) threads: each lane's share of sum r^2 and, with derivatives, of J J^T and J r."""
        p, lane = wp.tid()
        n_leds = val.shape[2]
        a = rd[p]
        b = rs[p]
        e = scalar(0.0)
        A = mat55()
        g = vec5()
        l = lane
        while l < n_leds:
            D, S, r0, r1 = bases(val, rho0, rho1, p, l)
            mh = wp.cw_mul(a, D) + wp.cw_mul(b, S)
            f, k = transform3(mh, mode, scale)
            fm, km = transform3(target[p, l], mode, scale)
            r = (f - fm) * inv
            e += wp.dot(r, r)
            if derivatives != 0:
                dd0, ds0 = grey_derivatives(d_diffuse, d_specular, p, l)
                # the rows d m_hat / d q_j (j = 0..4) of the three channels, times f'(m_hat) / sqrt(3 L)
                dm = (wp.cw_mul(da[p], rows(D)) + wp.outer(dd0, wp.cw_mul(a, r0)) + wp.cw_mul(db[p], rows(S))
                      + wp.outer(ds0, wp.cw_mul(b, r1)))
                dm = wp.cw_mul(dm, rows(k * inv))
                A += dm * wp.transpose(dm)
                g += dm * r
            l += lanes
        loss[p, lane] = e
        if derivatives != 0:
            jj[p, lane] = A
            jr[p, lane] = g

    return albedo_sums, lumitexel_terms, vec3, mat53, mat55, vec5


def _lanes(t: torch.Tensor) -> int:
    return CUDA_LANES if t.device.type == "cuda" else 1


def _on_stream(t: torch.Tensor):
    """Run on torch's current stream (the kernels read torch's memory in place), as twin.optics.jvp does."""
    if t.device.type != "cuda":
        return contextlib.nullcontext()
    return wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(t.device)))


def _device(t: torch.Tensor) -> str:
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"


def _scalar(t: torch.Tensor):
    if t.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the fit's sums take float32 or float64 tensors, got {t.dtype}")
    return wp.float64 if t.dtype == torch.float64 else wp.float32


def _derivative_arrays(val: torch.Tensor, d_diffuse, d_specular):
    """The derivatives as given, or (without them) empty stand-ins that the kernels never read."""
    if d_diffuse is None:
        empty = val.new_zeros(0, 0, 0)
        return empty, empty, 0
    n = val.shape[1]
    for name, d in (("d_diffuse", d_diffuse), ("d_specular", d_specular)):
        if tuple(d.shape) != (n, DERIVATIVES, val.shape[2]):
            raise ValueError(f"{name} must have shape (texels, {DERIVATIVES}, LEDs) = ({n}, {DERIVATIVES}, "
                             f"{val.shape[2]}), got {tuple(d.shape)}")
    return d_diffuse.contiguous(), d_specular.contiguous(), 1


def albedo_sums(val: torch.Tensor, target: torch.Tensor, ratio: torch.Tensor, loss: str, scale: float,
                d_diffuse: torch.Tensor | None = None, d_specular: torch.Tensor | None = None):
    """The albedo quadratic's sums over the LEDs: val (2, n, L) the grey bases D0, S0; target (n, L, 3) = m;
    ratio (2, L, 3) = rho0, rho1; loss "log1p" or "mse" with its scale (problem._f), whose slope weighs the sums;
    optional derivatives d_diffuse, d_specular (n, 5, L) of D0, S0. Returns the 5 sums [dd, dm, ds, ss, sm], each
    (n, 3), and (with derivatives) theirs, each (n, 5, 3), else None."""
    _init()
    scalar = _scalar(val)
    kernel, _, vec3, mat53, _, _ = _kernels(scalar)
    n, lanes = val.shape[1], _lanes(val)
    dD, dS, with_d = _derivative_arrays(val, d_diffuse, d_specular)
    out = val.new_empty(n, lanes, 1 + SUMS * with_d, DERIVATIVES, 3)
    dev = _device(val)
    with _on_stream(val):
        wp.launch(kernel, dim=(n, lanes), device=dev,
                  inputs=[wp.from_torch(val.contiguous(), dtype=scalar), wp.from_torch(dD, dtype=scalar),
                          wp.from_torch(dS, dtype=scalar), wp.from_torch(target.contiguous(), dtype=vec3),
                          wp.from_torch(ratio[0].contiguous(), dtype=vec3),
                          wp.from_torch(ratio[1].contiguous(), dtype=vec3), LOSS_MODES[loss], scalar(scale),
                          scalar(1.0 / (3 * val.shape[2])), with_d, lanes],
                  outputs=[wp.from_torch(out, dtype=mat53)])
    total = out.sum(1)
    sums = list(total[:, 0].unbind(1))
    return sums, ([total[:, 1 + k] for k in range(SUMS)] if with_d else None)


def lumitexel_terms(val: torch.Tensor, target: torch.Tensor, ratio: torch.Tensor, rd: torch.Tensor,
                    rs: torch.Tensor, loss: str, scale: float, d_diffuse: torch.Tensor | None = None,
                    d_specular: torch.Tensor | None = None, da: torch.Tensor | None = None,
                    db: torch.Tensor | None = None):
    """The lumitexel residuals' squared sum (n,) for albedos rd, rs (n, 3), and (with the bases' derivatives
    d_diffuse, d_specular (n, 5, L) and the albedos' da, db (n, 5, 3)) the Gauss-Newton system J J^T (n, 5, 5)
    and J r (n, 5) of their Jacobian (module docstring), else None, None. val (2, n, L), target (n, L, 3) = m,
    ratio (2, L, 3); loss "log1p" or "mse" with its scale (problem._f)."""
    _init()
    scalar = _scalar(val)
    _, kernel, vec3, mat53, mat55, vec5 = _kernels(scalar)
    n, L, lanes = val.shape[1], val.shape[2], _lanes(val)
    dD, dS, with_d = _derivative_arrays(val, d_diffuse, d_specular)
    if with_d:
        da, db = da.contiguous(), db.contiguous()
    else:
        da = db = val.new_zeros(0, DERIVATIVES, 3)
    e = val.new_empty(n, lanes)
    A = val.new_empty(n, lanes * with_d, DERIVATIVES, DERIVATIVES)
    g = val.new_empty(n, lanes * with_d, DERIVATIVES)
    with _on_stream(val):
        wp.launch(kernel, dim=(n, lanes), device=_device(val),
                  inputs=[wp.from_torch(val.contiguous(), dtype=scalar), wp.from_torch(dD, dtype=scalar),
                          wp.from_torch(dS, dtype=scalar), wp.from_torch(target.contiguous(), dtype=vec3),
                          wp.from_torch(ratio[0].contiguous(), dtype=vec3),
                          wp.from_torch(ratio[1].contiguous(), dtype=vec3),
                          wp.from_torch(rd.contiguous(), dtype=vec3), wp.from_torch(rs.contiguous(), dtype=vec3),
                          wp.from_torch(da, dtype=mat53), wp.from_torch(db, dtype=mat53), LOSS_MODES[loss],
                          scalar(scale), scalar(1.0 / (3 * L) ** 0.5), with_d, lanes],
                  outputs=[wp.from_torch(e, dtype=scalar), wp.from_torch(A, dtype=mat55),
                           wp.from_torch(g, dtype=vec5)])
    return e.sum(1), (A.sum(1) if with_d else None), (g.sum(1) if with_d else None)
