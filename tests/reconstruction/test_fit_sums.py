"""reconstruction.stages.fitting.sums: the GGX fit's per-texel sums over the LEDs in one Warp launch, against the
torch expressions they replace (reconstruction.stages.fitting.model's docstring), in float64 within 1e-12 relative
(sums in another order) and in float32 within 1e-5 (float32 sums of ~100 terms)."""
import math

import pytest
import torch

from reconstruction.stages.fitting import sums as fit_sums

TOL = {torch.float64: 1e-12, torch.float32: 1e-5}


def _inputs(dtype, device, n=7, L=33, seed=0):
    g = torch.Generator().manual_seed(seed)

    def r(*shape, lo=0.0, hi=1.0):
        return (lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)).to(dtype).to(device)

    val, m, ratio = r(2, n, L), r(n, L, 3, hi=5.0), r(2, L, 3, lo=0.5, hi=1.5)
    m[0, :4] = 0.0  # dark LEDs: log1p's slope 1, its value 0
    dD, dS = r(n, 5, L, lo=-1.0), r(n, 5, L, lo=-1.0)
    return val, m, ratio, dD, dS, r(n, 3), r(n, 3, hi=3.0), r(n, 5, 3, lo=-1.0), r(n, 5, 3, lo=-1.0)


def _f(x, loss, scale):
    return (torch.log1p(x), 1 / (1 + x)) if loss == "log1p" else (x / scale, torch.full_like(x, 1 / scale))


def _close(a, b, dtype):
    err = float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))
    assert err < TOL[dtype], err


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("loss", ["log1p", "mse"])
def test_albedo_sums_and_their_derivatives(device, dtype, loss):
    val, m, ratio, dD, dS, *_ = _inputs(dtype, device)
    L = val.shape[2]
    w = _f(m, loss, 0.7)[1].square() / (3 * L)
    D, S = val[0][..., None] * ratio[0], val[1][..., None] * ratio[1]
    ref = [(w * D * D).sum(1), (w * D * m).sum(1), (w * D * S).sum(1), (w * S * S).sum(1), (w * S * m).sum(1)]
    dDc, dSc = dD[..., None] * ratio[0], dS[..., None] * ratio[1]  # (n, 5, L, 3)
    wD, wS, wm = (w * D)[:, None], (w * S)[:, None], (w * m)[:, None]
    ref_d = [2 * (dDc * wD).sum(2), (dDc * wm).sum(2), (dDc * wS).sum(2) + (dSc * wD).sum(2), 2 * (dSc * wS).sum(2),
             (dSc * wm).sum(2)]
    sums, dsums = fit_sums.albedo_sums(val, m, ratio, loss, 0.7, dD, dS)
    plain, none = fit_sums.albedo_sums(val, m, ratio, loss, 0.7)
    assert none is None
    for a, b, c in zip(sums, plain, ref):
        _close(a, c, dtype)
        assert torch.equal(a, b)  # the derivatives change nothing of the sums
    for a, c in zip(dsums, ref_d):
        _close(a, c, dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("loss", ["log1p", "mse"])
def test_lumitexel_terms_are_the_normal_equations_of_the_rows(device, dtype, loss):
    val, m, ratio, dD, dS, rd, rs, da, db = _inputs(dtype, device)
    n, L = val.shape[1], val.shape[2]
    D, S = val[0][..., None] * ratio[0], val[1][..., None] * ratio[1]
    m_hat = rd[:, None] * D + rs[:, None] * S
    f_hat, k_hat = _f(m_hat, loss, 0.7)
    inv = 1 / math.sqrt(3 * L)
    r = ((f_hat - _f(m, loss, 0.7)[0]) * inv).reshape(n, -1)
    dDc, dSc = dD[..., None] * ratio[0], dS[..., None] * ratio[1]
    rows = (k_hat * inv)[:, None] * (da[:, :, None] * D[:, None] + rd[:, None, None] * dDc + db[:, :, None] * S[:, None]
                                     + rs[:, None, None] * dSc)
    J = rows.reshape(n, 5, -1)
    e, A, g = fit_sums.lumitexel_terms(val, m, ratio, rd, rs, loss, 0.7, dD, dS, da, db)
    e0, none_A, none_g = fit_sums.lumitexel_terms(val, m, ratio, rd, rs, loss, 0.7)
    assert none_A is None and none_g is None and torch.equal(e, e0)
    _close(e, r.square().sum(1), dtype)
    _close(A, J @ J.transpose(1, 2), dtype)
    _close(g, (J @ r[..., None])[..., 0], dtype)


def test_log1p_keeps_its_precision_near_zero():
    """f(x) = log1p(x) for tiny x: log(1 + x) in float32 would give 0 below 6e-8, a residual off by x itself."""
    val = torch.zeros(2, 1, 4)
    m = torch.tensor([[[1e-9, 2e-8, 3e-7, 0.5]] * 3]).transpose(1, 2).contiguous()
    e = fit_sums.lumitexel_terms(val, m, torch.ones(2, 4, 3), torch.zeros(1, 3), torch.zeros(1, 3), "log1p", 1.0)[0]
    ref = (torch.log1p(m.double()).square().sum() / 12).float()
    assert torch.allclose(e, ref.reshape(1), rtol=1e-6, atol=0)


def test_other_dtypes_are_refused():
    with pytest.raises(ValueError, match="float32 or float64"):
        fit_sums.albedo_sums(torch.zeros(2, 1, 3, dtype=torch.float16), torch.zeros(1, 3, 3), torch.ones(2, 3, 3),
                             "log1p", 1.0)
