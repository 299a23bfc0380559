"""Slot Attention (Eq. A19-A20) and its four stabilisers (Appendix E.1)."""

import logging
import math

import pytest
import torch

from freamer_rl.layers.slot_attention import MASK_VALUE, SIGMA_MIN, SlotAttention

BATCH_SHAPES = [(), (2,), (3, 2)]
K, D, DIN, N = 4, 16, 12, 10


def _sa(**kw):
    return SlotAttention(num_slots=K, dim=D, input_dim=DIN, iters=3, **kw)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
@pytest.mark.parametrize("with_mask", [False, True])
def test_output_shape(batch, with_mask):
    sa = _sa()
    x = torch.randn(*batch, N, DIN)
    mask = torch.rand(*batch, N) > 0.3 if with_mask else None
    slots, attn = sa.forward_with_attention(x, mask)
    assert slots.shape == (*batch, K, D)
    assert attn.shape == (*batch, K, N)
    assert sa(x, mask).shape == (*batch, K, D)
    assert (sa.num_slots, sa.slot_dim, sa.out_dim) == (K, D, D)
    assert torch.isfinite(slots).all()


def test_attention_is_softmax_over_slots():
    sa = _sa()
    _, attn = sa.forward_with_attention(torch.randn(3, N, DIN))
    torch.testing.assert_close(attn.sum(dim=-2), torch.ones(3, N))


@pytest.mark.parametrize("batch", BATCH_SHAPES)
@pytest.mark.parametrize(
    "case", ["zeros", "huge", "huge_negative", "identical", "fully_masked_rows", "single_valid_token"]
)
def test_adversarial_inputs_are_finite(batch, case):
    sa = _sa()
    x = torch.randn(*batch, N, DIN)
    mask = None
    if case == "zeros":
        x = torch.zeros_like(x)
    elif case == "huge":
        x = x * 1e6
    elif case == "huge_negative":
        x = -torch.rand_like(x) * 1e6
    elif case == "identical":
        x = torch.randn(DIN).expand_as(x).clone()
    elif case == "fully_masked_rows":
        mask = torch.zeros(*batch, N, dtype=torch.bool)
        if batch:
            mask.view(-1, N)[0, :3] = True  # one row with valid tokens, the others fully masked
    elif case == "single_valid_token":
        mask = torch.zeros(*batch, N, dtype=torch.bool)
        mask[..., 0] = True
    for training in (True, False):
        sa.train(training)
        slots = sa(x, mask)
        assert torch.isfinite(slots).all(), case
        loss = slots.square().mean()
        sa.zero_grad()
        loss.backward()
        for name, p in sa.named_parameters():
            assert p.grad is None or torch.isfinite(p.grad).all(), (case, name)
    assert sa.nan_fallbacks == 0  # none of these needs the fallback


def test_masked_columns_get_uniform_attention_without_a_nan_fallback():
    """The mask logit is finite (MASK_VALUE): a masked column, even a whole masked row, is a uniform 1/K over the
    slots before the validity weights zero it, never a NaN the fallback would have to catch (-inf would be)."""
    assert math.isfinite(MASK_VALUE)
    sa = _sa()
    mask = torch.ones(2, N, dtype=torch.bool)
    mask[0, -3:] = False
    mask[1] = False  # a fully masked row
    slots, attn = sa.forward_with_attention(torch.randn(2, N, DIN), mask)
    assert sa.nan_fallbacks == 0 and torch.isfinite(slots).all()
    assert torch.equal(attn[~mask.unsqueeze(1).expand_as(attn)], torch.zeros(int((~mask).sum()) * K))


def test_nan_fallback_is_counted_and_logged(caplog):
    sa = _sa()
    x = torch.randn(2, N, DIN)
    x[0, 3] = float("nan")  # one poisoned token in row 0
    with caplog.at_level(logging.WARNING, logger="freamer_rl.layers.slot_attention"):
        sa(x)
    first = sa.nan_fallbacks
    # iteration 1: the NaN token's column; later iterations: every column of row 0 (its slots became NaN)
    assert first == 1 + 2 * N
    warnings = [r for r in caplog.records if "NaN fallback" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING
    # rate limited: a second call within the interval counts but does not warn again
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="freamer_rl.layers.slot_attention"):
        sa(x)
    assert sa.nan_fallbacks == 2 * first
    assert not [r for r in caplog.records if "NaN fallback" in r.getMessage()]
    # row 1 was never poisoned: its slots stay finite
    assert torch.isfinite(sa(x)[1]).all()


def test_nan_fallback_is_not_counted_under_vmap():
    sa = _sa().eval()
    x = torch.randn(2, N, DIN)
    x[0, 3] = float("nan")
    out = torch.vmap(sa)(x)  # the fallback still substitutes; the count (a host sync) is skipped
    assert sa.nan_fallbacks == 0
    torch.testing.assert_close(out[1], sa(x[1:])[0], atol=1e-5, rtol=1e-5)
    sa(x)
    assert sa.nan_fallbacks == 1 + 2 * N


def test_nan_fallback_substitutes_uniform():
    sa = _sa(eval_init="fixed").eval()
    x = torch.randn(1, N, DIN)
    with torch.no_grad():
        sa.to_k.weight[0, 0] = float("inf")  # inf * 0 / inf - inf -> NaN logits for every column
    _, attn = sa.forward_with_attention(x)
    assert sa.nan_fallbacks > 0
    torch.testing.assert_close(attn, torch.full_like(attn, 1.0 / K))


def test_nan_in_padding_is_ignored():
    sa = _sa().eval()
    x = torch.randn(2, N, DIN)
    mask = torch.ones(2, N, dtype=torch.bool)
    mask[:, -3:] = False
    clean = sa(x, mask)
    x_bad = x.clone()
    x_bad[:, -3:] = float("nan")
    dirty = sa(x_bad, mask)
    assert torch.isfinite(dirty).all()
    torch.testing.assert_close(dirty, clean)
    assert sa.nan_fallbacks == 0


@pytest.mark.parametrize("training", [False, True])
def test_padding_does_not_change_output(training):
    sa = _sa().train(training)
    n_valid = 6
    x = torch.randn(3, n_valid, DIN)
    padded = torch.cat([x, 100 * torch.randn(3, N - n_valid, DIN)], dim=1)
    mask = torch.arange(N).expand(3, N) < n_valid
    torch.manual_seed(1)
    ref = sa(x)
    torch.manual_seed(1)
    out = sa(padded, mask)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    # an all-True mask is the same as no mask
    torch.manual_seed(1)
    same = sa(x, torch.ones(3, n_valid, dtype=torch.bool))
    torch.testing.assert_close(same, ref)


def test_gru_init_gains():
    sa = _sa()
    gru = sa.gru
    h = gru.hidden_size
    eye = torch.eye(h)
    bound = 0.5 * math.sqrt(6.0 / (D + h))  # xavier-uniform with gain 0.5 on each [h, D] gate block
    for g in range(3):
        w_hh = gru.weight_hh[g * h : (g + 1) * h].detach()
        torch.testing.assert_close(w_hh.T @ w_hh, 0.25 * eye, atol=1e-5, rtol=1e-5)  # 0.5 * orthogonal
        w_ih = gru.weight_ih[g * h : (g + 1) * h].detach()
        assert w_ih.abs().max() <= bound + 1e-7
        assert w_ih.std() == pytest.approx(bound / math.sqrt(3.0), rel=0.25)
    assert torch.count_nonzero(gru.bias_ih) == 0 and torch.count_nonzero(gru.bias_hh) == 0


def test_variance_clipping():
    sa = _sa()
    with torch.no_grad():
        sa.slots_log_sigma.fill_(-100.0)
    assert torch.all(sa.sigma() == SIGMA_MIN)
    assert torch.isfinite(sa(torch.randn(2, N, DIN))).all()
    with torch.no_grad():
        sa.slots_log_sigma.fill_(0.0)
    torch.testing.assert_close(sa.sigma(), torch.ones(1, 1, D))


def test_train_is_stochastic_eval_is_deterministic():
    sa = _sa()
    x = torch.randn(2, N, DIN)
    sa.train()
    assert not torch.allclose(sa(x), sa(x))
    sa.eval()
    torch.testing.assert_close(sa(x), sa(x), rtol=0, atol=0)
    # "fixed" training init is deterministic as well
    sa_fixed = _sa(train_init="fixed").train()
    torch.testing.assert_close(sa_fixed(x), sa_fixed(x), rtol=0, atol=0)


def test_eval_init_mean_is_degenerate_fixed_is_not():
    x = torch.randn(2, N, DIN)
    mean_slots = _sa(eval_init="mean").eval()(x)
    # identical initial slots stay identical (documented reason for the default eval_init="fixed")
    torch.testing.assert_close(mean_slots, mean_slots[:, :1].expand_as(mean_slots))
    fixed_slots = _sa(eval_init="fixed").eval()(x)
    assert not torch.allclose(fixed_slots[:, 0], fixed_slots[:, 1])


@pytest.mark.parametrize("train_init", ["random", "fixed"])
def test_gradients_reach_every_parameter(train_init):
    sa = _sa(train_init=train_init).train()
    x = torch.randn(3, N, DIN, requires_grad=True)
    mask = torch.rand(3, N) > 0.2
    sa(x, mask).pow(2).mean().backward()
    for name, p in sa.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name
    assert x.grad is not None and torch.isfinite(x.grad).all()


def test_errors_name_the_shapes():
    sa = _sa()
    with pytest.raises(ValueError, match=r"last dim 12"):
        sa(torch.randn(2, N, DIN + 1))
    with pytest.raises(ValueError, match=r"mask"):
        sa(torch.randn(2, N, DIN), torch.ones(2, N + 1, dtype=torch.bool))
    with pytest.raises(ValueError, match="eval_init"):
        _sa(eval_init="nope")


def test_state_dict_keeps_fixed_noise():
    a, b = _sa(), _sa()
    b.load_state_dict(a.state_dict())
    a.eval(), b.eval()
    x = torch.randn(2, N, DIN)
    torch.testing.assert_close(a(x), b(x), rtol=0, atol=0)
