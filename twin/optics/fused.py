"""Fused pattern measurements: B[p, k] = sum_l W[k, l] m[p, l] without ever storing the lumitexels.

CUDA: `fused_tile_kernel`. A block of BLOCK_THREADS = TILE_P x TILE_L threads owns TILE_P points. For
each chunk of TILE_L LEDs every thread evaluates one response (Eq. 1); the block gathers them into
shared-memory tiles, one per colour channel (one synchronisation each), and `wp.tile_matmul` accumulates
them against the chunk's TILE_L x TILE_K pattern tile (cuBLASDx). Lumitexels live only as one shared tile per block; patterns stream through shared memory.
Patterns are processed TILE_K at a time (more patterns = more launches over the same points).

CPU: Warp's CPU backend runs one thread per block (block_dim 1), so the tiled mapping does not apply;
`fused_loop_kernel` accumulates each point's row LED by LED, which stays in cache.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from twin.optics.lumitexel import Options, fused_loop_kernel, led_response

TILE_P = 16  # points per block
TILE_L = 16  # LEDs per chunk
TILE_K = 64  # patterns per launch
BLOCK_THREADS = 256  # = TILE_P * TILE_L (512 exceeds the register file: led_response needs > 128): each thread evaluates exactly one (point, LED) entry per chunk
TILE_PL = TILE_P * TILE_L  # tile shapes must be named compile-time constants, not expressions
assert TILE_PL == BLOCK_THREADS


@wp.kernel
def fused_tile_kernel(pos: wp.array(dtype=wp.vec3), frames: wp.array(dtype=wp.mat33), wo_l: wp.array(dtype=wp.vec3),
                      rho_d: wp.array(dtype=wp.vec3), rho_s: wp.array(dtype=wp.vec3), ax: wp.array(dtype=float),
                      ay: wp.array(dtype=float), beta: wp.array(dtype=float),
                      lpos: wp.array(dtype=wp.vec3), lnrm: wp.array(dtype=wp.vec3), lu: wp.array(dtype=wp.vec3),
                      lint: wp.array(dtype=wp.vec3), prof: wp.array2d(dtype=float), lbot: wp.array(dtype=wp.int32),
                      o: Options, num_leds: int,
                      w_r: wp.array2d(dtype=float), w_g: wp.array2d(dtype=float), w_b: wp.array2d(dtype=float),
                      out_r: wp.array2d(dtype=float), out_g: wp.array2d(dtype=float),
                      out_b: wp.array2d(dtype=float)):
    blk, lane = wp.tid()
    p0 = blk * TILE_P
    # thread `lane` owns entry (point lane // TILE_L, LED lane % TILE_L) of every chunk: its point's data
    # is loaded once, its LED changes with the chunk
    p = p0 + lane // TILE_L
    valid_p = p < pos.shape[0]
    pc = wp.min(p, pos.shape[0] - 1)
    x, frame, wol = pos[pc], frames[pc], wo_l[pc]
    rd, rs, a_x, a_y, b = rho_d[pc], rho_s[pc], ax[pc], ay[pc], beta[pc]
    acc_r = wp.tile_zeros(shape=(TILE_P, TILE_K), dtype=float)
    acc_g = wp.tile_zeros(shape=(TILE_P, TILE_K), dtype=float)
    acc_b = wp.tile_zeros(shape=(TILE_P, TILE_K), dtype=float)
    m_r = wp.tile_zeros(shape=(TILE_P, TILE_L), dtype=float, storage="shared")
    m_g = wp.tile_zeros(shape=(TILE_P, TILE_L), dtype=float, storage="shared")
    m_b = wp.tile_zeros(shape=(TILE_P, TILE_L), dtype=float, storage="shared")
    flat_r = wp.tile_reshape(m_r, shape=(TILE_PL,))
    flat_g = wp.tile_reshape(m_g, shape=(TILE_PL,))
    flat_b = wp.tile_reshape(m_b, shape=(TILE_PL,))
    for chunk in range((num_leds + TILE_L - 1) // TILE_L):
        l0 = chunk * TILE_L
        l = l0 + lane % TILE_L
        val = wp.vec3(0.0)
        if valid_p and l < num_leds:
            val = led_response(x, frame, wol, rd, rs, a_x, a_y, b, lpos[l], lnrm[l], lu[l], lint[l], prof, l,
                               lbot[l], o)
        # one value per thread -> the (TILE_P * TILE_L,) register tile is exactly the flattened m tile
        wp.tile_assign(flat_r, wp.tile(val[0]))
        wp.tile_assign(flat_g, wp.tile(val[1]))
        wp.tile_assign(flat_b, wp.tile(val[2]))
        wp.tile_matmul(m_r, wp.tile_load(w_r, shape=(TILE_L, TILE_K), offset=(l0, 0)), acc_r)
        wp.tile_matmul(m_g, wp.tile_load(w_g, shape=(TILE_L, TILE_K), offset=(l0, 0)), acc_g)
        wp.tile_matmul(m_b, wp.tile_load(w_b, shape=(TILE_L, TILE_K), offset=(l0, 0)), acc_b)
    wp.tile_store(out_r, acc_r, offset=(p0, 0))
    wp.tile_store(out_g, acc_g, offset=(p0, 0))
    wp.tile_store(out_b, acc_b, offset=(p0, 0))


def fused_measurements(wpts, leds, o: Options, w: np.ndarray, out: wp.array, device) -> None:
    """Fill `out` (P, K) vec3 with the pattern measurements; `w` is (K, L, 3) numpy."""
    dev = wp.get_device(device)
    Kn, L = w.shape[0], w.shape[1]
    P = wpts[0].shape[0]
    if not dev.is_cuda or wpts[0].dtype != wp.vec3f:
        W = wp.array(w, dtype=out.dtype, device=device)
        wp.launch(fused_loop_kernel, dim=P, inputs=[*wpts, *leds, o, W], outputs=[out], device=device)
        return
    L_pad = -(-L // TILE_L) * TILE_L
    P_pad = -(-P // TILE_P) * TILE_P
    for k0 in range(0, Kn, TILE_K):
        kk = min(TILE_K, Kn - k0)
        wc = np.zeros((3, L_pad, TILE_K), np.float32)  # channel-major, LED rows, zero-padded
        wc[:, :L, :kk] = w[k0:k0 + kk].transpose(2, 1, 0)
        ws = [wp.array(wc[c], dtype=float, device=device) for c in range(3)]
        outs = [wp.zeros((P_pad, TILE_K), dtype=float, device=device) for _ in range(3)]
        wp.launch_tiled(fused_tile_kernel, dim=[P_pad // TILE_P], inputs=[*wpts, *leds, o, L, *ws],
                        outputs=outs, block_dim=BLOCK_THREADS, device=device)
        wp.launch(_pack_kernel, dim=(P, kk), inputs=[*outs, k0], outputs=[out], device=device)


@wp.kernel
def _pack_kernel(r: wp.array2d(dtype=float), g: wp.array2d(dtype=float), b: wp.array2d(dtype=float), k0: int,
                 out: wp.array2d(dtype=wp.vec3)):
    p, k = wp.tid()
    out[p, k0 + k] = wp.vec3(r[p, k], g[p, k], b[p, k])
