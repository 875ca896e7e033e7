"""Split-precision ("3xTF32") linear layers (reconstruction.network.split_tf32_linear) and their use in the decoder
and in fine-tuning (FinetuneConfig.precision).

The error bound (network.SPLIT_TF32_RTOL, derived next to split_tf32_linear): |result - exact| <= rtol sum_i |x_i||w_i|
for products of inner length k <= 64. On the CPU the TF32 flag changes nothing, so these tests check the split's
algebra and plumbing; on CUDA (when present) they check the tensor-core path against the same bound.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from reconstruction import network
from reconstruction.finetune import FinetuneConfig, finetune, grey_to_rgb, simulate_lines
from reconstruction.network import (PRECISIONS, SPLIT_TF32_RTOL, AcquisitionNet, NetworkConfig, _split,
                                    split_tf32_linear)
from twin.optics.tf32 import tf32_matmul

pytestmark = pytest.mark.usefixtures("one_torch_thread")

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]


def _data(device, b=32, k=64, n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    x, w, bias = torch.randn(b, k, generator=g), torch.randn(n, k, generator=g), torch.randn(n, generator=g)
    return x.to(device), w.to(device), bias.to(device)


def _tol(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The bound's scale: sum over the inner index of |a||b|, in float64."""
    return a.double().abs() @ b.double().abs()


def test_split_is_exact_and_hi_is_tf32():
    x, _, _ = _data("cpu")
    x = x * torch.logspace(-20, 20, x.shape[1])  # many exponents
    hi, lo = _split(x)
    assert torch.equal(hi + lo, x)
    assert int((hi.view(torch.int32) & 0x1FFF).abs().max()) == 0  # 10 stored mantissa bits: a TF32 number
    assert bool((lo.abs() <= 2.0 ** -10 * x.abs()).all())


@pytest.mark.parametrize("device", DEVICES)
def test_forward_within_bound_of_float64(device):
    x, w, bias = _data(device)
    y = split_tf32_linear(x, w, bias).double()
    ref = x.double() @ w.double().T + bias.double()
    assert y.dtype == torch.float64 and y.shape == (32, 40)
    err = (y - ref).abs()
    bound = SPLIT_TF32_RTOL * (_tol(x, w.T) + bias.double().abs())
    assert bool((err <= bound).all()), float((err / bound).max())
    assert torch.equal(split_tf32_linear(x, w), split_tf32_linear(x, w, None))
    # batched leading axes, as nn.Linear takes them
    np.testing.assert_allclose(split_tf32_linear(x.reshape(4, 8, 64), w, bias).reshape(32, 40).cpu().numpy(),
                               split_tf32_linear(x, w, bias).cpu().numpy(), rtol=1e-6, atol=1e-6)


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(1)
    x, w, b = (torch.randn(*s, generator=g, dtype=torch.float64, requires_grad=True) for s in ((5, 4), (3, 4), (3,)))
    assert torch.autograd.gradcheck(split_tf32_linear, (x, w, b))
    assert torch.autograd.gradcheck(split_tf32_linear, (x, w))
    assert torch.autograd.gradcheck(split_tf32_linear, (x.reshape(1, 5, 4), w, b))


@pytest.mark.parametrize("device", DEVICES)
def test_float32_gradients_within_bound_of_float64(device):
    x, w, bias = (t.requires_grad_(True) for t in _data(device))
    gout = torch.randn(32, 40, generator=torch.Generator().manual_seed(2)).to(device)
    (split_tf32_linear(x, w, bias) * gout).sum().backward()
    x64, w64, b64 = (t.detach().double().requires_grad_(True) for t in (x, w, bias))
    (torch.nn.functional.linear(x64, w64, b64) * gout.double()).sum().backward()
    g = gout.double()
    for got, ref, scale in ((x.grad, x64.grad, _tol(gout, w)), (w.grad, w64.grad, _tol(gout.T, x)),
                            (bias.grad, b64.grad, g.abs().sum(0))):
        err = (got.double() - ref).abs()
        assert bool((err <= SPLIT_TF32_RTOL * scale).all()), float((err / (SPLIT_TF32_RTOL * scale)).max())
    # gradients only where asked: a frozen weight gets none
    x2, w2 = x.detach().requires_grad_(True), w.detach()
    split_tf32_linear(x2, w2, bias.detach()).sum().backward()
    assert x2.grad is not None and w2.grad is None


def test_tf32_flag_restored_also_after_an_exception():
    flags = torch.backends.cuda.matmul
    before = flags.allow_tf32
    try:
        x, w, b = _data("cpu")
        for value in (False, True):
            flags.allow_tf32 = value
            split_tf32_linear(x, w, b)
            assert flags.allow_tf32 is value
            with pytest.raises(RuntimeError):
                split_tf32_linear(x, w[:, :10], b)  # shapes do not match: the product raises inside the block
            assert flags.allow_tf32 is value
            with tf32_matmul(not value):
                assert flags.allow_tf32 is (not value)
            assert flags.allow_tf32 is value
    finally:
        flags.allow_tf32 = before


@pytest.mark.parametrize("architecture", ["paper", "compact"])
def test_decoder_split_close_to_float32(architecture, monkeypatch):
    torch.manual_seed(0)
    net = AcquisitionNet(NetworkConfig(num_leds=64, patterns_per_view=4, architecture=architecture)).eval()
    g = torch.Generator().manual_seed(3)
    albedo, shape = torch.randn(16, 8, generator=g), torch.randn(16, 48, generator=g)
    calls = []
    monkeypatch.setattr(network, "split_tf32_linear", lambda *a: calls.append(1) or split_tf32_linear(*a))
    with torch.no_grad():
        ref = net.decode(albedo, shape)
        assert not calls
        split = net.decode(albedo, shape, precision="split_tf32")
        assert len(calls) == sum(isinstance(m, torch.nn.Linear) for m in net.decoder.modules())
        np.testing.assert_allclose(split.numpy(), ref.numpy(), rtol=1e-5, atol=1e-5)
        assert torch.equal(net.decode_lumitexel(albedo, shape, precision="split_tf32"), network.log_to_lumitexel(split))
        assert torch.equal(net.decoder(torch.cat([albedo, shape], 1), "float32"), ref)
    assert PRECISIONS == ("float32", "split_tf32")
    for bad in ("tf32", "float64", None):
        with pytest.raises(ValueError, match="precision must be one of"):
            net.decode(albedo, shape, precision=bad)


def test_finetune_config_precision():
    assert FinetuneConfig().precision == "float32"
    assert FinetuneConfig(precision="split_tf32").precision == "split_tf32"
    with pytest.raises(ValueError, match="FinetuneConfig.precision"):
        FinetuneConfig(precision="bad")


def test_finetune_split_tf32_matches_float32():
    torch.manual_seed(0)
    net = AcquisitionNet(NetworkConfig(num_leds=64, patterns_per_view=4)).eval()
    rng = np.random.default_rng(0)
    weights = ((rng.random((8, 64)) < 0.15)[..., None] * rng.uniform(0.5, 1.0, (8, 64, 3))).astype(np.float32)
    z = rng.standard_normal((12, 56)).astype(np.float32)
    target = grey_to_rgb(z)
    target[:, :24] += 0.3 * rng.standard_normal((12, 24)).astype(np.float32)
    lines = simulate_lines(net, target, weights)
    start = z + 0.1 * rng.standard_normal(z.shape).astype(np.float32)
    runs = {p: finetune(net, start, lines, weights, FinetuneConfig(iterations=(10, 5, 10), holdout=(1,), precision=p))
            for p in PRECISIONS}
    a, b = runs["float32"], runs["split_tf32"]
    assert a.iterations == b.iterations
    for p in ("pass1", "pass2", "pass3"):
        np.testing.assert_allclose(b.objective[p], a.objective[p], rtol=1e-4)
        assert a.objective[p][1] < a.objective[p][0]  # the passes did work
    np.testing.assert_allclose(b.latent, a.latent, rtol=1e-3, atol=1e-4)
