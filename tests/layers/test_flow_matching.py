"""Layer 2 Flow Matching refiner (Section 3.3, Eq. 1-3; Appendix D.1, Eq. A13)."""

from __future__ import annotations

import math

import pytest
import torch

from freamer_rl.layers.flow_matching import FlowMatchingRefiner, cfm_interpolant

BATCH_SHAPES = [(), (2,), (3, 2)]


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_shapes_and_near_identity_at_init(batch):
    torch.manual_seed(0)
    ref = FlowMatchingRefiner(16, hidden=32)
    e = torch.randn(*batch, 16)
    e_hat = ref(e)
    assert e_hat.shape == e.shape
    assert ref.gate.item() == pytest.approx(1 / (1 + math.exp(3.0)))
    # small last layer and a 0.047 gate: the refiner starts as (nearly) the identity
    assert (e_hat - e).abs().max().item() < 1e-3
    loss = ref.cfm_loss(e)
    assert loss.shape == ()
    assert ref.velocity(e, torch.rand(batch)).shape == e.shape


class _TimeVelocity(FlowMatchingRefiner):
    """v(x, t) = t (each coordinate), to check the Euler scheme and the gate in closed form."""

    def velocity(self, x, t):
        return super().velocity(x, t) * 0 + torch.as_tensor(t, dtype=x.dtype)


class _LinearVelocity(FlowMatchingRefiner):
    """v(x, t) = -x."""

    def velocity(self, x, t):
        return -x


@pytest.mark.parametrize("steps", [1, 4, 7])
def test_euler_integration_and_gate_closed_form(steps):
    e = torch.randn(3, 5)
    ref = _TimeVelocity(5, steps=steps, gate_init=0.7)
    # x_N = e + sum_{i<N} (i/N)/N = e + (N-1)/(2N)   (Eq. 1-2)
    x_n = ref.integrate(e)
    torch.testing.assert_close(x_n, e + (steps - 1) / (2 * steps))
    # e_hat = e + sigmoid(alpha) (x_N - e)            (Eq. 3)
    gate = 1 / (1 + math.exp(-0.7))
    torch.testing.assert_close(ref(e), e + gate * (steps - 1) / (2 * steps))
    lin = _LinearVelocity(5, steps=steps)
    torch.testing.assert_close(lin.integrate(e), e * (1 - 1 / steps) ** steps)
    # per-call step override
    torch.testing.assert_close(lin.integrate(e, steps=2), e * 0.25)


def test_cfm_interpolant_closed_form():
    x0, x1 = torch.randn(4, 6), torch.randn(4, 6)
    t = torch.rand(4)
    x_t, u = cfm_interpolant(x0, x1, t)
    torch.testing.assert_close(x_t, t[:, None] * x1 + (1 - t[:, None]) * x0)
    torch.testing.assert_close(u, x1 - x0)
    torch.testing.assert_close(cfm_interpolant(x0, x1, 0.0)[0], x0)
    torch.testing.assert_close(cfm_interpolant(x0, x1, 1.0)[0], x1)
    # u is the time derivative of the path
    h = 1e-3
    xa, _ = cfm_interpolant(x0.double(), x1.double(), t.double())
    xb, _ = cfm_interpolant(x0.double(), x1.double(), t.double() + h)
    torch.testing.assert_close((xb - xa) / h, u.double())
    with pytest.raises(ValueError, match="x0 and x1"):
        cfm_interpolant(x0, x1[:, :3], t)


def test_cfm_loss_matches_formulation_and_is_detached():
    ref = FlowMatchingRefiner(8, hidden=16)
    e = torch.randn(5, 8, requires_grad=True)
    torch.manual_seed(123)
    loss = ref.cfm_loss(e, noise_std=0.5)
    # replay the same random draws: eps first, then t
    torch.manual_seed(123)
    x1 = e.detach()
    x0 = x1 + 0.5 * torch.randn_like(x1)
    t = torch.rand(5)
    x_t = t[:, None] * x1 + (1 - t[:, None]) * x0
    expected = ((ref.velocity(x_t, t) - (x1 - x0)) ** 2).mean()
    torch.testing.assert_close(loss, expected)
    loss.backward()
    assert e.grad is None  # the loss trains only the velocity field
    assert ref.net[0].weight.grad is not None and ref.net[0].weight.grad.abs().sum() > 0
    assert ref.alpha.grad is None  # the gate is not part of the CFM objective


def test_cfm_loss_of_zero_field_is_noise_variance():
    ref = FlowMatchingRefiner(32, hidden=16)
    with torch.no_grad():
        ref.net[-1].weight.zero_()
        ref.net[-1].bias.zero_()
    loss = ref.cfm_loss(torch.randn(4096, 32), noise_std=0.5)
    assert loss.item() == pytest.approx(0.25, rel=0.03)  # mean over dim: E[(sigma*eps)^2] = sigma^2


def test_training_learns_to_denoise():
    torch.manual_seed(0)
    dim = 8
    centres = torch.randn(4, dim) * 2
    ref = FlowMatchingRefiner(dim, hidden=64, steps=4)
    opt = torch.optim.Adam(ref.parameters(), lr=1e-2)
    losses = []
    for _ in range(300):
        e = centres[torch.randint(0, 4, (64,))]
        loss = ref.cfm_loss(e, noise_std=0.3)
        losses.append(loss.item())
        opt.zero_grad()
        loss.backward()
        opt.step()
    # a zero field scores sigma^2 = 0.09; the learnt field must do much better
    assert sum(losses[-30:]) / 30 < 0.5 * 0.09
    clean = centres[torch.randint(0, 4, (256,))]
    noisy = clean + 0.3 * torch.randn_like(clean)
    with torch.no_grad():
        refined = ref.integrate(noisy)  # the ungated flow x_N
    err_before = (noisy - clean).pow(2).sum(-1).mean()
    err_after = (refined - clean).pow(2).sum(-1).mean()
    assert err_after < 0.5 * err_before


def test_gate_gradient_and_errors():
    ref = FlowMatchingRefiner(4, hidden=8, gate_init=-1.0)
    ref(torch.randn(3, 4)).sum().backward()
    assert ref.alpha.grad is not None
    with pytest.raises(ValueError, match="last dim 4"):
        ref(torch.randn(3, 5))
    with pytest.raises(ValueError, match="steps"):
        FlowMatchingRefiner(4, steps=0)
    with pytest.raises(ValueError, match="noise_std"):
        ref.cfm_loss(torch.randn(2, 4), noise_std=-1.0)


def test_non_finite_input_raises_except_under_vmap():
    ref = FlowMatchingRefiner(4, hidden=8)
    e = torch.randn(3, 4)
    e[2, 1] = float("inf")
    with pytest.raises(ValueError, match=r"FlowMatchingRefiner input: 1 non-finite values \(NaN/Inf\)"):
        ref(e)
    out = torch.vmap(ref)(e)  # maths only under vmap
    assert torch.isfinite(out[:2]).all() and not torch.isfinite(out[2]).all()
    torch.testing.assert_close(out[:2], ref(e[:2]), atol=1e-6, rtol=1e-5)


def test_scalar_time_fast_path_matches_concatenated_input():
    torch.manual_seed(0)
    ref = FlowMatchingRefiner(16, hidden=32)
    x = torch.randn(5, 16)
    for t in (0.0, 0.25, 0.75):
        fast = ref.velocity(x, t)
        slow = ref.net(torch.cat([x, torch.full((5, 1), t)], dim=-1))
        assert torch.allclose(fast, slow, atol=1e-6)
