"""Score-based adaptive FM complexity (paper Appendix G.4): hard Gumbel-Softmax choice of the Euler step count."""

from __future__ import annotations

import pytest
import torch

from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.model.factory import build_filter_mix_memory

D = 8
CHOICES = (1, 2, 3, 5, 7, 10)


def _adaptive(deduplicate: bool = True, **kwargs) -> FlowMatchingRefiner:
    torch.manual_seed(0)
    r = FlowMatchingRefiner(
        D,
        hidden=16,
        steps=4,
        gate_init=0.0,
        last_layer_scale=1.0,
        deduplicate=deduplicate,
        adaptive_steps=CHOICES,
        **kwargs,
    )
    return r.eval()


def _force(r: FlowMatchingRefiner, k: int) -> None:
    with torch.no_grad():
        r.selector.weight.zero_()
        r.selector.bias.zero_()
        r.selector.bias[k] = 1e4


def _split(r: FlowMatchingRefiner, e: torch.Tensor) -> None:
    """Eval-mode choice: 1 step for rows of complexity below the median of ``e``'s rows, 10 steps above."""
    threshold = torch.log(r.complexity(e) + 1e-6).median()
    with torch.no_grad():
        r.selector.weight.zero_()
        r.selector.bias.fill_(-100.0)
        r.selector.bias[0] = 0.0
        r.selector.weight[-1] = 1.0
        r.selector.bias[-1] = -threshold


def _fixed_copy(r: FlowMatchingRefiner, steps: int) -> FlowMatchingRefiner:
    fixed = FlowMatchingRefiner(D, hidden=16, steps=steps, last_layer_scale=1.0)
    fixed.load_state_dict({k: v for k, v in r.state_dict().items() if not k.startswith("selector")})
    return fixed.eval()


def _rows(n: int = 96) -> torch.Tensor:
    torch.manual_seed(1)
    e = torch.randn(n, D)
    e[n // 4 :] = e[0]  # most rows repeat: the dedup path runs for deduplicate=True
    return e


@pytest.mark.parametrize("deduplicate", [True, False])
@pytest.mark.parametrize("train", [False, True])
@pytest.mark.parametrize("k", [0, 3, 5])
def test_forced_choice_equals_the_fixed_step_refiner(k, train, deduplicate):
    r = _adaptive(deduplicate)
    _force(r, k)
    r.train(train)
    e = _rows()
    out = r(e)
    torch.testing.assert_close(out, _fixed_copy(r, CHOICES[k])(e), rtol=1e-6, atol=1e-6)
    assert r.last_steps.item() == CHOICES[k] and r.last_steps.requires_grad is False
    assert r.expected_steps.item() == pytest.approx(CHOICES[k])


def test_gradient_reaches_the_selector():
    r = _adaptive()
    with torch.no_grad():
        r.selector.weight.fill_(0.5)
    r.train()
    r(torch.randn(32, D)).pow(2).sum().backward()
    assert r.selector.weight.grad is not None and r.selector.weight.grad.abs().sum() > 0
    assert r.selector.bias.grad.abs().sum() > 0
    assert r.alpha.grad is not None and r.net[-1].weight.grad.abs().sum() > 0


def test_eval_mode_is_deterministic_and_train_mode_samples():
    r = _adaptive()
    e = torch.randn(256, D)
    torch.manual_seed(2)
    first = r(e)
    torch.manual_seed(3)
    assert torch.equal(first, r(e))
    y_eval, probs = r.step_selection(e)
    assert torch.equal(y_eval, r.step_selection(e)[0])
    assert torch.allclose(probs.sum(-1), torch.ones(256))
    r.train()
    y1, y2 = r.step_selection(e)[0], r.step_selection(e)[0]
    assert not torch.equal(y1, y2)
    assert y1.argmax(-1).unique().numel() > 1  # different rows take different step counts
    assert torch.equal(y1.sum(-1), torch.ones(256))  # an exact one-hot per row
    assert not torch.equal(r(e), r(e))


def test_vmap_matches_the_batched_forward_and_leaves_the_logs_alone():
    r = _adaptive(deduplicate=False)
    e = torch.randn(64, D)
    _split(r, e)
    batched = r(e)
    logged = r.last_steps.clone()
    assert r.step_selection(e)[0].argmax(-1).unique().numel() > 1
    torch.testing.assert_close(torch.vmap(r)(e), batched, rtol=1e-5, atol=1e-6)
    assert torch.equal(r.last_steps, logged)


def test_last_steps_is_the_mean_chosen_count():
    r = _adaptive()
    e = torch.randn(40, D)
    r(e)
    assert r.last_steps.item() == 3  # at init: weight 0, bias on the choice nearest steps=4 (tie -> fewer)
    _split(r, e)
    r(e)
    y, probs = r.step_selection(e)
    n = torch.tensor(CHOICES, dtype=torch.float32)
    assert r.last_steps.item() == pytest.approx((y * n).sum(-1).mean().item())
    assert r.expected_steps.item() == pytest.approx((probs * n).sum(-1).mean().item())
    assert min(CHOICES) <= r.last_steps.item() <= max(CHOICES)


def test_explicit_steps_override_the_adaptive_choice():
    r = _adaptive()
    e = torch.randn(16, D)
    torch.testing.assert_close(r(e, steps=2), _fixed_copy(r, 2)(e))


def test_off_by_default_is_the_old_refiner():
    keys = ["alpha", "net.0.weight", "net.0.bias", "net.2.weight", "net.2.bias", "net.4.weight", "net.4.bias"]
    e = torch.randn(70, D)
    outs = []
    for kwargs in ({}, {"adaptive_steps": None}, {"adaptive_steps": ()}):
        torch.manual_seed(0)
        r = FlowMatchingRefiner(D, hidden=16, **kwargs)
        assert list(r.state_dict()) == keys and r.selector is None
        assert len(list(r.parameters())) == len(keys) and len(list(r.buffers())) == 0
        outs.append(r(e))
        torch.testing.assert_close(outs[-1], e + r.gate * (r.integrate(e, 4) - e), rtol=0, atol=0)
    assert torch.equal(outs[0], outs[1]) and torch.equal(outs[0], outs[2])


def test_adaptive_state_dict_and_invalid_arguments():
    r = _adaptive()
    assert {"selector.weight", "selector.bias"} <= set(r.state_dict())
    assert "last_steps" not in r.state_dict()  # logging buffers are not persistent
    with pytest.raises(ValueError, match="adaptive_steps"):
        FlowMatchingRefiner(D, adaptive_steps=(0, 2))
    with pytest.raises(ValueError, match="adaptive_steps"):
        FlowMatchingRefiner(D, adaptive_steps=(2, 2))
    with pytest.raises(ValueError, match="tau"):
        FlowMatchingRefiner(D, adaptive_steps=(1, 2), tau=0.0)
    with pytest.raises(RuntimeError, match="adaptive_steps"):
        FlowMatchingRefiner(D).step_selection(torch.randn(2, D))


def test_trunk_builder_passes_the_adaptive_settings():
    kwargs = dict(
        flow_hidden=8,
        flow_steps=2,
        gate_init={"state": -3.0, "reward": -1.0},
        fno_modes=4,
        fno_residual_scale=0.1,
        dnc=False,
    )
    _, refiners, _, _ = build_filter_mix_memory(
        ["state", "reward"], 8, flow_adaptive_steps=(1, 3), flow_tau=0.5, **kwargs
    )
    assert all(r.adaptive_steps == (1, 3) and r.tau == 0.5 for r in refiners.values())
    _, refiners, _, _ = build_filter_mix_memory(["state", "reward"], 8, **kwargs)
    assert all(r.adaptive_steps is None for r in refiners.values())


@pytest.mark.parametrize("adaptive_steps", [None, CHOICES])
def test_empty_batches(adaptive_steps):
    r = FlowMatchingRefiner(D, adaptive_steps=adaptive_steps)
    assert r(torch.randn(0, 3, D)).shape == (0, 3, D)
    assert r(torch.randn(5, 0, D)).shape == (5, 0, D)
