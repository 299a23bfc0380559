"""OGM-GE gate modulation (paper Section 4.3.5, Appendix K): coefficients, groups, learning rates, GE noise."""

from __future__ import annotations

import io
import math

import pytest
import torch
from torch import nn

from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.machinery.ogm import OGMGE, gradient_enhancement_noise
from freamer_rl.run.optim import optimizer_step

D = 8


def _refiners() -> nn.ModuleDict:
    torch.manual_seed(0)
    return nn.ModuleDict({m: FlowMatchingRefiner(D, hidden=16, steps=2) for m in ("state", "reward")})


def _k(alpha: float, d: float) -> float:
    return 1.0 - math.tanh(alpha * max(d - 1.0, 0.0))


def test_coefficients_closed_form():
    ogm = OGMGE(_refiners(), alpha=0.5, ema=0.9)
    assert ogm.coefficients() == {"state": 1.0, "reward": 1.0}
    ogm.observe({"state": 1.0, "reward": 2.0})  # first values: c = 1 for both, no discrepancy
    assert ogm.coefficients() == {"state": 1.0, "reward": 1.0}
    ogm.observe({"state": 0.5, "reward": 2.0})
    ogm.observe({"state": 0.25, "reward": 1.0})
    ema_s = 0.9 * (0.9 * 1.0 + 0.1 * 0.5) + 0.1 * 0.25
    ema_r = 0.9 * (0.9 * 2.0 + 0.1 * 2.0) + 0.1 * 1.0
    c_s, c_r = ema_s / 1.0, ema_r / 2.0
    mean_c = (c_s + c_r) / 2
    assert ogm.convergence() == pytest.approx({"state": c_s, "reward": c_r})
    k = ogm.coefficients()
    assert c_s < c_r  # state converges faster: dominant, suppressed
    assert k["state"] == pytest.approx(_k(0.5, mean_c / c_s))
    assert 0.0 < k["state"] < 1.0
    assert k["reward"] == 1.0
    metrics = ogm.metrics()
    assert metrics["ogm_coeff_state"] == pytest.approx(k["state"])
    assert metrics["ogm_conv_reward"] == pytest.approx(c_r)


def test_coefficients_ignore_unknown_and_non_finite_losses():
    ogm = OGMGE(_refiners())
    ogm.observe({"state": float("nan"), "reward": 1.0, "vision": 3.0})
    assert ogm.convergence() == {"reward": 1.0}
    assert ogm.coefficients() == {"state": 1.0, "reward": 1.0}  # one modality observed: nothing to compare
    ogm.observe({"state": 0.0, "reward": 1.0})  # a first loss of exactly 0 does not divide by zero
    ogm.observe({"state": 0.0, "reward": 1.0})
    # c_state = 0 / eps = 0 (fully converged), c_reward = 1: the state gate is suppressed to k = 1 - tanh(inf) = 0
    assert ogm.convergence() == {"state": 0.0, "reward": 1.0}
    assert ogm.coefficients() == {"state": pytest.approx(0.0, abs=1e-12), "reward": 1.0}


@pytest.mark.parametrize("mode", ["A", "B"])
def test_param_groups(mode):
    refiners = _refiners()
    other = nn.Linear(3, 3)
    all_params = list(refiners.parameters()) + list(other.parameters())
    groups = OGMGE(refiners, mode=mode, lr_scale=10.0).param_groups(1e-3, all_params + all_params[:2])
    assert [g["name"] for g in groups] == ["ogm_state", "ogm_reward", "base"]
    for g, (m, r) in zip(groups[:2], refiners.items()):
        assert g["ogm_modality"] == m
        if mode == "A":
            assert len(g["params"]) == 1 and g["params"][0] is r.alpha
            assert g["lr"] == pytest.approx(1e-2) and g["lr_scale"] == 10.0
        else:
            assert {id(p) for p in g["params"]} == {id(p) for p in r.parameters()}
            assert g["lr"] == pytest.approx(1e-3) and g["lr_scale"] == 1.0
    seen = [id(p) for g in groups for p in g["params"]]
    assert sorted(seen) == sorted({id(p) for p in all_params})  # every parameter exactly once
    assert groups[2]["lr_scale"] == 1.0
    torch.optim.Adam(groups, lr=1e-3)  # a valid optimiser


def test_modulate_sets_the_learning_rates():
    refiners = _refiners()
    ogm = OGMGE(refiners, alpha=1.0, noise=False)
    extra = nn.Linear(2, 2)
    opt = torch.optim.Adam(ogm.param_groups(1.0, list(refiners.parameters()) + list(extra.parameters())))
    ogm.observe({"state": 1.0, "reward": 1.0})
    ogm.observe({"state": 0.1, "reward": 1.0})
    k = ogm.coefficients()
    ogm.modulate(opt, lr=3e-4)
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs["ogm_state"] == pytest.approx(3e-4 * 10.0 * k["state"])
    assert lrs["ogm_reward"] == pytest.approx(3e-4 * 10.0)
    assert lrs["base"] == pytest.approx(3e-4)
    assert k["state"] < 1.0


def test_ge_noise_on_a_scalar_is_finite_and_scaled_by_its_magnitude():
    torch.manual_seed(0)
    with pytest.warns(UserWarning):
        assert torch.isnan(torch.tensor([0.3]).std())  # the pitfall: unbiased std of one element
    g = torch.tensor(-0.3)
    samples = torch.stack([gradient_enhancement_noise(g) for _ in range(4000)])
    assert torch.isfinite(samples).all()
    assert samples.std().item() == pytest.approx(0.3, rel=0.05)
    assert samples.mean().item() == pytest.approx(0.0, abs=0.03)
    assert (gradient_enhancement_noise(torch.zeros(())) == 0).all()  # zero gradient: no noise


def test_ge_noise_on_a_tensor_uses_the_population_std():
    g = torch.tensor([[1.0, -1.0], [1.0, -1.0]])  # population std 1, unbiased std 2/sqrt(3)
    torch.manual_seed(1)
    noise = gradient_enhancement_noise(g)
    torch.manual_seed(1)
    assert torch.allclose(noise, torch.randn(2, 2) * 1.0)
    big = torch.randn(200, 50) * 2.5
    assert torch.stack([gradient_enhancement_noise(big) for _ in range(5)]).std().item() == pytest.approx(
        big.std(unbiased=False).item(), rel=0.02
    )


def test_modulate_adds_noise_only_to_modality_groups():
    refiners = _refiners()
    ogm = OGMGE(refiners, mode="B")
    extra = nn.Parameter(torch.ones(3))
    opt = torch.optim.SGD(ogm.param_groups(0.1, list(refiners.parameters()) + [extra]), lr=0.1)
    for p in [*refiners.parameters(), extra]:
        p.grad = torch.full_like(p, 0.5)
    torch.manual_seed(0)
    ogm.modulate(opt, lr=0.1)
    assert torch.equal(extra.grad, torch.full((3,), 0.5))
    alpha_grad = refiners["state"].alpha.grad
    assert torch.isfinite(alpha_grad) and alpha_grad != 0.5  # scalar: sigma = |g| = 0.5
    weight = refiners["state"].net[0].weight
    assert torch.equal(weight.grad, torch.full_like(weight, 0.5))  # constant gradient: population std 0


def test_state_dict_round_trip_through_weights_only_load():
    ogm = OGMGE(_refiners(), alpha=0.7)
    for s, r in [(1.0, 2.0), (0.6, 1.9), (0.4, 1.5)]:
        ogm.observe({"state": s, "reward": r})
    buf = io.BytesIO()
    torch.save(ogm.state_dict(), buf)
    buf.seek(0)
    restored = OGMGE(_refiners(), alpha=0.7)
    restored.load_state_dict(torch.load(buf, weights_only=True))
    assert restored.coefficients() == ogm.coefficients()
    assert restored.state_dict() == ogm.state_dict()
    ogm.observe({"state": 0.3, "reward": 1.4})
    restored.observe({"state": 0.3, "reward": 1.4})
    assert restored.coefficients() == ogm.coefficients()


def test_one_adam_step_through_optimizer_step():
    refiners = _refiners()
    ogm = OGMGE(refiners, mode="A")
    params = list(refiners.parameters())
    opt = torch.optim.Adam(ogm.param_groups(1e-3, params), lr=1e-3)
    ogm.observe({"state": 1.0, "reward": 1.0})
    ogm.observe({"state": 0.2, "reward": 0.9})
    before = {m: r.alpha.detach().clone() for m, r in refiners.items()}
    e = torch.randn(16, D)
    loss = sum((r(e) - 1.0).pow(2).mean() + r.cfm_loss(e) for r in refiners.values())
    grad_norm = optimizer_step(loss, opt, params, max_grad_norm=1.0, before_step=lambda: ogm.modulate(opt, 1e-3))
    assert torch.isfinite(grad_norm)
    for m, r in refiners.items():
        assert r.alpha != before[m]
        assert all(torch.isfinite(p).all() for p in r.parameters())
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs["ogm_state"] < lrs["ogm_reward"] == pytest.approx(1e-2)


def test_before_step_is_not_called_on_a_skipped_step():
    p = nn.Parameter(torch.ones(2))
    opt = torch.optim.SGD([p], lr=0.1)
    calls = []
    optimizer_step((p * float("nan")).sum(), opt, [p], before_step=lambda: calls.append(1))
    assert calls == []
    optimizer_step(p.sum(), opt, [p], before_step=lambda: calls.append(1))
    assert calls == [1]


def test_invalid_arguments():
    with pytest.raises(ValueError, match="mode"):
        OGMGE(_refiners(), mode="C")
    with pytest.raises(ValueError, match="ema"):
        OGMGE(_refiners(), ema=1.0)
    with pytest.raises(ValueError, match="lr_scale"):
        OGMGE(_refiners(), lr_scale=0.0)
