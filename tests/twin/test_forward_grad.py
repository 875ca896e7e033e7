"""Gradients of the forward model (wp.Tape through torch.autograd), checked in float64 on CPU
(Kornia's practice: analytic gradients against central finite differences in double precision).

torch.autograd.gradcheck perturbs each input by eps = 1e-6 and compares with the analytic Jacobian at
atol 1e-5, rtol 1e-3 (its defaults), which float64 kernels meet with room to spare. Points are chosen
away from visibility edges and horizons, where Eq. 1 is smooth.
"""
from __future__ import annotations

import numpy as np
import pytest

import twin

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def rig():
    from dataclasses import replace

    mini = twin.load_rig("mini")
    # a handful of LEDs keeps the numerical Jacobian small: every 23rd LED, upper and bottom
    return replace(mini, leds=mini.leds.subset(np.arange(0, mini.num_leds, 23)))


def _inputs(P=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    pos = torch.cat([torch.rand(P, 2, generator=g, dtype=torch.float64) * 60 - 30,
                     torch.full((P, 1), -122.0, dtype=torch.float64)], 1)
    n = torch.nn.functional.normalize(torch.tensor([[0.1, -0.05, 1.0]], dtype=torch.float64).repeat(P, 1), dim=1)
    t = torch.nn.functional.normalize(torch.tensor([[1.0, 0.2, 0.0]], dtype=torch.float64).repeat(P, 1), dim=1)
    rd = torch.rand(P, 3, generator=g, dtype=torch.float64)
    rs = torch.rand(P, 3, generator=g, dtype=torch.float64) * 5
    ax = torch.tensor([0.15, 0.3], dtype=torch.float64)[:P]
    ay = torch.tensor([0.25, 0.1], dtype=torch.float64)[:P]
    beta = torch.tensor([0.4, 0.7], dtype=torch.float64)[:P]
    return pos, n, t, rd, rs, ax, ay, beta


@pytest.mark.slow
def test_lumitexel_gradcheck_float64(rig):
    pos, n, t, rd, rs, ax, ay, beta = _inputs()
    leaves = [x.clone().requires_grad_(True) for x in (n, t, rd, rs, ax, ay, beta)]

    def f(n_, t_, rd_, rs_, ax_, ay_, beta_):
        return twin.lumitexels(rig, pos, n_, t_, rd_, rs_, ax_, ay_, transparency=beta_)

    out = f(*leaves)
    assert out.dtype == torch.float64 and out.shape == (2, rig.num_leds, 3)
    assert (out > 0).any()
    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.slow
def test_measurement_gradcheck_float64_patterns(rig):
    """Gradients reach the pattern weights and the material through the projection kernel."""
    pos, n, t, rd, rs, ax, ay, beta = _inputs()
    w = torch.rand(3, rig.num_leds, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    leaves = [w.requires_grad_(True), rs.clone().requires_grad_(True), ax.clone().requires_grad_(True)]

    def f(w_, rs_, ax_):
        return twin.measurements(rig, pos, n, t, rd, rs_, ax_, ay, w_, transparency=beta)

    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_pattern_gradient_is_lumitexel(rig):
    """dB[p,k,c]/dW[k,l,c] = m[p,l,c] exactly (Eq. 2 is linear in W): a closed-form gradient check."""
    pos, n, t, rd, rs, ax, ay, beta = _inputs(P=1)
    w = torch.rand(2, rig.num_leds, 3, dtype=torch.float64, requires_grad=True)
    B = twin.measurements(rig, pos, n, t, rd, rs, ax, ay, w)
    B[0, 1, 2].backward()
    m = twin.lumitexels(rig, pos, n, t, rd, rs, ax, ay)
    assert torch.equal(w.grad[1, :, 2], m[0, :, 2])
    assert torch.count_nonzero(w.grad[0]) == 0 and torch.count_nonzero(w.grad[1, :, :2]) == 0


def test_float32_and_float64_agree(rig):
    """The float64 kernels (used for gradcheck) compute the same model as the float32 production ones."""
    args = _inputs()
    m64 = twin.lumitexels(rig, *args[:7], transparency=args[7])
    m32 = twin.lumitexels(rig, *[a.float() for a in args[:7]], transparency=args[7].float())
    torch.testing.assert_close(m32.double(), m64, rtol=2e-5, atol=1e-6 * float(m64.abs().max()))
