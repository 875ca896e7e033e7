"""Dense correspondence by descriptor matching (reference §6.2, paper §8): SIFT Flow descriptors at every
pixel (Liu et al.) and PatchMatch (Barnes et al.) over them, in torch, vectorised over all pixels.

    d0, d1 = dense_sift(img0, cell), dense_sift(img1, cell)     # (128, H, W) each
    cost = PatchCost(d0, d1, patch, max_offset, ...)            # SSD of 7 x 7 descriptor patches per offset
    off = patchmatch(cost, init_noise=..., jumps=..., searches=..., iterations=10, generator=g)
    sub, info = subpixel(cost, off)                             # quadratic fit around the integer optimum
    best = exhaustive(d0, d1, patch, radius, budget)            # a small window searched whole, in row bands

reconstruction.stages.alignment uses these relative to its homography (offset 0 = the coarse mapping).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["dense_sift", "PatchCost", "patchmatch", "subpixel", "exhaustive"]


# --- dense SIFT (reference §6.2; SIFT Flow, Liu et al.) ---------------------------------------------------

def dense_sift(img: torch.Tensor, cell: float, sharpness: float = 9.0, floor: float = 0.01) -> torch.Tensor:
    """(C, H, W) image -> (128, H, W) descriptors at every pixel: Sobel gradients of the channel with the
    strongest gradient, 8 orientation bins (cosine to the bin's angle, clipped at 0, ^sharpness, times the
    magnitude), each bin averaged under a tent of half-width `cell` (SIFT's bilinear spatial binning), read
    at the 4 x 4 cell centres around the pixel (bilinear for fractional cells, reflection at the border),
    then d / (|d| + floor)."""
    C, H, W = img.shape
    sob = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=img.dtype, device=img.device) / 8
    x = F.pad(img[:, None], (1, 1, 1, 1), mode="replicate")
    gx = F.conv2d(x, sob[None, None])[:, 0]
    gy = F.conv2d(x, sob.T[None, None])[:, 0]
    mag2 = gx * gx + gy * gy
    k = mag2.argmax(dim=0, keepdim=True)
    gx, gy = gx.gather(0, k)[0], gy.gather(0, k)[0]
    mag = torch.sqrt(gx * gx + gy * gy)
    ang = torch.arange(8, dtype=img.dtype, device=img.device) * (2 * np.pi / 8)
    cos = (gx[None] * torch.cos(ang)[:, None, None] + gy[None] * torch.sin(ang)[:, None, None]) / mag.clamp_min(1e-12)
    bins = cos.clamp_min(0) ** sharpness * mag[None]  # (8, H, W)
    # tent filter of half-width `cell`, separable, normalised to sum 1
    r = int(np.ceil(cell)) - 1 if float(cell).is_integer() else int(np.floor(cell))
    taps = 1 - torch.abs(torch.arange(-r, r + 1, dtype=img.dtype, device=img.device)) / cell
    taps = taps / taps.sum()
    b = bins[:, None]
    if r > 0:
        b = F.conv2d(F.pad(b, (r, r, 0, 0), mode="reflect"), taps.view(1, 1, 1, -1))
        b = F.conv2d(F.pad(b, (0, 0, r, r), mode="reflect"), taps.view(1, 1, -1, 1))
    b = b[:, 0]
    # the 4 x 4 cell centres at (i - 1.5) * cell, i = 0..3, sampled with grid_sample (reflection)
    c = (torch.arange(4, dtype=img.dtype, device=img.device) - 1.5) * cell
    yy, xx = torch.meshgrid(torch.arange(H, dtype=img.dtype, device=img.device),
                            torch.arange(W, dtype=img.dtype, device=img.device), indexing="ij")
    oy, ox = torch.meshgrid(c, c, indexing="ij")
    gxn = 2 * (xx[None] + ox.reshape(-1, 1, 1)) / max(W - 1, 1) - 1  # (16, H, W)
    gyn = 2 * (yy[None] + oy.reshape(-1, 1, 1)) / max(H - 1, 1) - 1
    grid = torch.stack([gxn, gyn], dim=-1)
    d = F.grid_sample(b[None].expand(16, -1, -1, -1), grid, mode="bilinear", padding_mode="reflection",
                      align_corners=True)  # (16 cells, 8 bins, H, W)
    d = d.reshape(128, H, W)
    return d / (torch.linalg.vector_norm(d, dim=0, keepdim=True) + floor)


# --- PatchMatch (reference §6.2) --------------------------------------------------------------------------

class PatchCost:
    """SSD over a patch x patch window between source descriptors around p and target descriptors around
    p + o, for integer offsets o with |o_x|, |o_y| <= radius: cost(p, o) = sum_d |S(r(p + d)) - T(c(r(p + d)
    + o))|^2, r reflecting into the image (the reference's reflection padding), c clamping.

    Offsets are passed as linear indices (o_y + R)(2R + 1) + (o_x + R) (`encode`); the index (2R + 1)^2 is a
    sentinel that costs +inf (no candidate). When the costs of all (2R + 1)^2 offsets fit `budget_bytes` they
    are computed once (a cost volume: each PatchMatch candidate is then a lookup), else each candidate field
    is evaluated directly: the same numbers up to float rounding (tests/test_alignment.py compares them)."""

    def __init__(self, src: torch.Tensor, tgt: torch.Tensor, patch: int, radius: int, budget_bytes: float):
        self.src, self.tgt, self.R, self.h = src, tgt, radius, patch // 2
        D, H, W = src.shape
        self.shape = (H, W)
        self.k = 2 * radius + 1
        self.sentinel = self.k ** 2
        self.volume = None
        if (self.sentinel + 1) * H * W * src.element_size() <= budget_bytes:
            vol = self._box(self._volume()).reshape(self.sentinel, -1)
            self.volume = torch.cat([vol, torch.full_like(vol[:1], float("inf"))])

    def encode(self, off: torch.Tensor) -> torch.Tensor:
        """(2, ...) integer (x, y) offsets, clamped to the window -> linear indices (...)."""
        off = off.clamp(-self.R, self.R)
        return (off[1] + self.R) * self.k + off[0] + self.R

    def decode(self, idx: torch.Tensor) -> torch.Tensor:
        return torch.stack([idx % self.k - self.R, idx // self.k - self.R])

    def _volume(self) -> torch.Tensor:
        """|S(p) - T(p + o)|^2 for every pixel and offset, (n, H, W), as |S|^2 + |T|^2 - 2 S.T with the dot
        products from batched matrix products over strips of columns (one BLAS call per strip and row offset
        instead of a pass over all descriptors per offset)."""
        R, k = self.R, self.k
        D, H, W = self.src.shape
        S = self.src.permute(1, 2, 0).contiguous()  # (H, W, D)
        T = F.pad(self.tgt[None], (R,) * 4, mode="replicate")[0].permute(1, 2, 0).contiguous()  # (H+2R, W+2R, D)
        s2, t2 = (S * S).sum(-1), (T * T).sum(-1)
        B = max(32, k)  # strip width: products of B x (B + 2R), of which the band of width 2R + 1 is kept
        band = (torch.arange(B, device=S.device)[:, None] + torch.arange(k, device=S.device)[None, :])
        vol = torch.empty(k, k, H, W, dtype=S.dtype, device=S.device)  # (oy, ox, y, x)
        for oy in range(k):
            rows = T[oy:oy + H]
            dots = torch.cat([torch.bmm(S[:, xb:xb + B], rows[:, xb:xb + B + 2 * R].transpose(1, 2))
                              .gather(2, band[:min(B, W - xb)].expand(H, -1, k)) for xb in range(0, W, B)], dim=1)
            vol[oy] = (t2[oy:oy + H].unfold(1, k, 1) - 2 * dots + s2[..., None]).permute(2, 0, 1)
        return vol.reshape(k * k, H, W).clamp_min_(0)

    def _box(self, e: torch.Tensor) -> torch.Tensor:
        h = self.h
        if h == 0:
            return e
        e = F.pad(e[:, None], (h, h, h, h), mode="reflect")
        return F.avg_pool2d(e, 2 * h + 1, stride=1)[:, 0] * (2 * h + 1) ** 2

    def __call__(self, idx: torch.Tensor) -> torch.Tensor:
        """idx (m, H, W) linear offset indices -> (m, H, W) costs."""
        H, W = self.shape
        m = idx.shape[0]
        if self.volume is not None:
            return self.volume.gather(0, idx.reshape(m, -1)).reshape(m, H, W)
        off = self.decode(idx.clamp(max=self.sentinel - 1))  # (2, m, H, W)
        dev = idx.device
        ys = torch.arange(H, device=dev)[:, None]
        xs = torch.arange(W, device=dev)[None, :]
        src = self.src.reshape(self.src.shape[0], -1)
        tgt = self.tgt.reshape(self.tgt.shape[0], -1)
        total = torch.zeros(m, H, W, dtype=self.src.dtype, device=dev)
        for dy in range(-self.h, self.h + 1):
            for dx in range(-self.h, self.h + 1):
                qy, qx = _reflect(ys + dy, H), _reflect(xs + dx, W)
                s_ = src[:, (qy * W + qx).reshape(-1)].reshape(-1, 1, H, W)
                ty = (qy + off[1]).clamp(0, H - 1)
                tx = (qx + off[0]).clamp(0, W - 1)
                t_ = tgt[:, (ty * W + tx).reshape(-1)].reshape(-1, m, H, W)
                total += ((s_ - t_) ** 2).sum(0)
        return torch.where(idx == self.sentinel, torch.full_like(total, float("inf")), total)


def _reflect(i: torch.Tensor, n: int) -> torch.Tensor:
    """Reflection without repeating the edge (torch's "reflect" padding), for |overshoot| < n."""
    i = torch.where(i < 0, -i, i)
    return torch.where(i > n - 1, 2 * (n - 1) - i, i)


def patchmatch(cost: PatchCost, *, init_noise: int, jumps, searches, iterations: int,
               generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """PatchMatch over integer offset fields (reference §6.2), vectorised over all pixels. The initial
    offsets are uniform in [-init_noise, init_noise) per axis. Each iteration: jump-flooding propagation,
    where for each jump j (largest first) every pixel considers the offsets of its 8 neighbours at distance j
    (out of the image: none), then random search, where every pixel considers its current offset plus
    uniform integer noise in [-r, r] per axis for each radius r. A pixel takes the best candidate only where
    it is strictly better than its current offset. Offsets stay within the cost's window (clamped). Returns
    the (2, H, W) integer (x, y) offsets and their (H, W) costs."""
    H, W = cost.shape
    dev = cost.src.device
    off = torch.randint(-init_noise, max(init_noise, 1), (2, H, W), generator=generator).to(dev)
    idx = cost.encode(off)
    best = cost(idx[None])[0]

    def take(cands):  # (m, H, W) candidate indices; index 0 of the stack (the current one) wins ties
        nonlocal idx, best
        c = torch.cat([best[None], cost(cands)])
        win = c.argmin(dim=0, keepdim=True)
        idx = torch.cat([idx[None], cands]).gather(0, win)[0]
        best = c.gather(0, win)[0]

    dirs = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
    for _ in range(iterations):
        for j in jumps:
            padded = F.pad(idx[None], (j, j, j, j), value=cost.sentinel)[0]
            take(torch.stack([padded[j + dy * j:j + dy * j + H, j + dx * j:j + dx * j + W] for dy, dx in dirs]))
        current = cost.decode(idx)
        noise = torch.stack([torch.randint(-r, r + 1, (2, H, W), generator=generator) for r in searches], dim=1)
        take(cost.encode(current[:, None] + noise.to(dev)))
    return cost.decode(idx), best


def subpixel(cost: PatchCost, off: torch.Tensor):
    """Quadratic fit of the cost over the 3 x 3 integer offsets around `off` (PatchMatch's integer answer):
    c(o + d) ~ c0 + g.d + d'Hd/2 by least squares on the 9 values. Returns the sub-pixel step -H^-1 g
    (clamped to [-0.5, 0.5] per axis; 0 where H is not positive definite), the fitted cost there, the Hessian
    (H, W, 2, 2) and its smallest eigenvalue (NaN where the 3 x 3 leaves the offset window)."""
    d = [(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    shifts = torch.tensor(d, device=off.device).T.reshape(2, 9, 1, 1)
    vals = cost(cost.encode(off[:, None] + shifts))
    c = {dd: vals[i] for i, dd in enumerate(d)}
    gx = (sum(c[1, dy] for dy in (-1, 0, 1)) - sum(c[-1, dy] for dy in (-1, 0, 1))) / 6
    gy = (sum(c[dx, 1] for dx in (-1, 0, 1)) - sum(c[dx, -1] for dx in (-1, 0, 1))) / 6
    hxx = sum(c[1, dy] + c[-1, dy] - 2 * c[0, dy] for dy in (-1, 0, 1)) / 3
    hyy = sum(c[dx, 1] + c[dx, -1] - 2 * c[dx, 0] for dx in (-1, 0, 1)) / 3
    hxy = (c[1, 1] + c[-1, -1] - c[1, -1] - c[-1, 1]) / 4
    c0 = vals.mean(0) - (hxx + hyy) / 3  # least-squares constant term of the 9-point quadratic
    det = hxx * hyy - hxy * hxy
    pd = (det > 0) & (hxx > 0)
    safe = torch.where(pd, det, torch.ones_like(det))
    step = torch.stack([-(hyy * gx - hxy * gy) / safe, -(hxx * gy - hxy * gx) / safe]).clamp(-0.5, 0.5)
    step = torch.where(pd[None], step, torch.zeros_like(step))
    cmin = c0 + gx * step[0] + gy * step[1] + 0.5 * (hxx * step[0] ** 2 + 2 * hxy * step[0] * step[1]
                                                    + hyy * step[1] ** 2)
    lam_min = (hxx + hyy) / 2 - torch.sqrt(((hxx - hyy) / 2) ** 2 + hxy ** 2)
    lam_min = torch.where((off.abs() >= cost.R).any(0), torch.full_like(lam_min, float("nan")), lam_min)
    hess = torch.stack([torch.stack([hxx, hxy], -1), torch.stack([hxy, hyy], -1)], -2)
    return step, cmin, hess, lam_min


def exhaustive(src: torch.Tensor, tgt: torch.Tensor, patch: int, radius: int, budget_bytes: float) -> dict:
    """Every pixel's best integer offset over the whole (2R + 1)^2 window (not PatchMatch's sample of it: for
    a window this small the cost volume costs less than PatchMatch's candidates), its `subpixel` fit and the
    cost of offset 0. The volume is computed in bands of rows that fit `budget_bytes`, each with a halo of
    R + patch // 2 rows, so that every kept row sees the same descriptors as in one volume over the whole
    image: the same numbers as PatchCost on the whole image (tests/test_alignment.py). Ties go to the lowest
    offset index. Returns a dict of (H, W) tensors: off (2, H, W), step (2, H, W), cmin, hess (H, W, 2, 2),
    lam_min, c_zero."""
    D, H, W = src.shape
    k = 2 * radius + 1
    halo = radius + patch // 2
    fit = budget_bytes / (2 * (k * k + 1) * W * src.element_size())  # rows whose volume (and its scratch) fit
    rows = H if fit >= H + 2 * halo else max(1, int(fit) - 2 * halo)
    parts = []
    for y0 in range(0, H, rows):
        y1 = min(y0 + rows, H)
        b0, b1 = max(y0 - halo, 0), min(y1 + halo, H)
        cost = PatchCost(src[:, b0:b1], tgt[:, b0:b1], patch, radius, float("inf"))
        off = cost.decode(cost.volume[:-1].argmin(dim=0).reshape(cost.shape))
        step, cmin, hess, lam_min = subpixel(cost, off)
        c_zero = cost(cost.encode(torch.zeros_like(off))[None])[0]
        keep = slice(y0 - b0, y1 - b0)
        parts.append({"off": off[:, keep], "step": step[:, keep], "cmin": cmin[keep], "hess": hess[keep],
                      "lam_min": lam_min[keep], "c_zero": c_zero[keep]})
    dims = {"off": 1, "step": 1}
    return {name: torch.cat([p[name] for p in parts], dim=dims.get(name, 0)) for name in parts[0]}
