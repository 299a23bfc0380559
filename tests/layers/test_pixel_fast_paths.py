"""The pixel path's fast code against its reference code: same outputs (float rounding) and the same gradients.

* ``SlotAttention._iterate`` (fused k/v projection, bmm, masked_fill fallback) vs ``_iterate_reference``;
* ``CNNBackbone`` with in-place ReLUs vs the same convolutions through out-of-place ``F.relu``;
* ``pixels_to_unit``'s in-place divide vs ``permute -> float -> / 255``;
* ``render_pov`` (the MiniGrid adapter's ``"pixels"``) vs MiniGrid's own ``get_frame(agent_pov=True)``, pixel for pixel.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from freamer_rl.layers.encoders import CNNBackbone, VisionEncoder, pixels_to_unit
from freamer_rl.layers.slot_attention import SlotAttention

BATCH_SHAPES = [(), (2,), (3, 2)]


def _grads(module: torch.nn.Module, *tensors: torch.Tensor) -> list[torch.Tensor]:
    return [p.grad.clone() for p in module.parameters() if p.grad is not None] + [t.grad.clone() for t in tensors]


def _run_slots(sa: SlotAttention, fast: bool, inputs: torch.Tensor, mask: torch.Tensor | None, seed: int):
    """Forward + backward of ``sa`` on a fresh leaf copy of ``inputs``; returns (slots, attn, grads)."""
    sa.fast = fast
    sa.zero_grad(set_to_none=True)
    x = inputs.clone().requires_grad_(True)
    torch.manual_seed(seed)  # the same random slot initialisation on both paths (training mode)
    slots, attn = sa.forward_with_attention(x, mask)
    # a loss that weighs every slot coordinate differently (a plain sum would hide permuted gradients)
    weight = torch.linspace(-1.0, 1.0, slots.numel()).reshape(slots.shape)
    ((slots * weight).sum() + attn.square().sum()).backward()
    return slots.detach(), attn.detach(), _grads(sa, x)


@pytest.mark.parametrize("batch_shape", BATCH_SHAPES)
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("training", [False, True])
def test_slot_attention_fast_matches_reference(batch_shape, masked, training):
    torch.manual_seed(0)
    sa = SlotAttention(num_slots=4, dim=16, input_dim=12, iters=3).train(training)
    inputs = torch.randn(*batch_shape, 9, 12)
    mask = None
    if masked:
        mask = torch.rand(*batch_shape, 9) > 0.3
        mask[..., 0] = True
    ref = _run_slots(sa, False, inputs, mask, seed=5)
    fast = _run_slots(sa, True, inputs, mask, seed=5)
    torch.testing.assert_close(fast[0], ref[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fast[1], ref[1], rtol=1e-5, atol=1e-6)
    assert len(fast[2]) == len(ref[2]) == len(list(sa.parameters())) + 1  # every parameter got a gradient
    for g_fast, g_ref in zip(fast[2], ref[2]):
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-4, atol=1e-6)


def test_slot_attention_fast_counts_the_same_nan_fallbacks():
    """Huge query weights make some logits inf -> NaN softmax columns: both paths substitute and count them alike."""
    torch.manual_seed(1)
    sa = SlotAttention(num_slots=3, dim=8, iters=2).eval()
    with torch.no_grad():
        sa.to_q.weight.mul_(1e38)
    inputs = torch.randn(4, 6, 8)
    out = {}
    for fast in (False, True):
        sa.fast, sa.nan_fallbacks = fast, 0
        slots, attn = sa.forward_with_attention(inputs)
        out[fast] = (slots, attn, sa.nan_fallbacks)
    assert out[False][2] > 0
    assert out[True][2] == out[False][2]
    torch.testing.assert_close(out[True][0], out[False][0], equal_nan=True)
    torch.testing.assert_close(out[True][1], out[False][1], equal_nan=True)


def test_slot_attention_fast_runs_under_vmap():
    torch.manual_seed(2)
    sa = SlotAttention(num_slots=2, dim=8, iters=2).eval()
    inputs = torch.randn(3, 5, 8)
    vmapped = torch.vmap(sa)(inputs)
    torch.testing.assert_close(vmapped, sa(inputs), rtol=1e-5, atol=1e-6)


def _cnn_reference(cnn: CNNBackbone, pixels: torch.Tensor) -> torch.Tensor:
    """CNNBackbone.forward with out-of-place ReLUs and the plain ``permute -> float -> / 255`` conversion."""
    batch_shape = pixels.shape[:-3]
    x = pixels.reshape(-1, *pixels.shape[-3:]).permute(0, 3, 1, 2).to(torch.float32) / 255.0
    c1, _, c2, _, c3 = cnn.net
    feats = c3(F.relu(c2(F.relu(c1(x)))))
    h, w = feats.shape[-2:]
    tokens = feats.flatten(2).transpose(1, 2) + cnn.pos_proj(cnn._grid(h, w, feats.device, feats.dtype))
    return tokens.reshape(*batch_shape, h * w, cnn.out_dim)


@pytest.mark.parametrize("batch_shape", BATCH_SHAPES)
def test_cnn_inplace_relu_matches_reference(batch_shape):
    torch.manual_seed(3)
    cnn = CNNBackbone(in_channels=3, out_dim=16, hidden=8)
    assert all(m.inplace for m in cnn.net if isinstance(m, torch.nn.ReLU))
    base = torch.rand(*batch_shape, 20, 24, 3) * 255.0
    results = []
    for forward in (lambda px: _cnn_reference(cnn, px), cnn):
        cnn.zero_grad(set_to_none=True)
        px = base.clone().requires_grad_(True)
        tokens = forward(px)
        (tokens * torch.linspace(-1.0, 1.0, tokens.numel()).reshape(tokens.shape)).sum().backward()
        results.append((tokens.detach(), _grads(cnn, px)))
    (ref, ref_grads), (fast, fast_grads) = results
    assert fast.shape == (*batch_shape, 3 * 3, 16)
    torch.testing.assert_close(fast, ref, rtol=0, atol=0)
    assert len(fast_grads) == len(ref_grads) == len(list(cnn.parameters())) + 1
    for g_fast, g_ref in zip(fast_grads, ref_grads):
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-6, atol=1e-7)


def test_pixels_to_unit_in_place_divide_is_exact_and_leaves_float_inputs_alone():
    torch.manual_seed(4)
    px = torch.randint(0, 256, (5, 7, 6, 3), dtype=torch.uint8)
    assert torch.equal(pixels_to_unit(px), px.permute(0, 3, 1, 2).to(torch.float32) / 255.0)
    assert pixels_to_unit(px).is_contiguous(memory_format=torch.channels_last)
    floats = px.to(torch.float32)
    before = floats.clone()
    assert torch.equal(pixels_to_unit(floats), before.permute(0, 3, 1, 2) / 255.0)
    assert torch.equal(floats, before)  # the caller's float tensor is not divided in place


@pytest.mark.parametrize("batch_shape", BATCH_SHAPES)
def test_vision_encoder_fast_matches_reference(batch_shape):
    """The whole encoder (uint8 pixels -> slots) with every fast path on vs every one off."""
    torch.manual_seed(5)
    enc = VisionEncoder(CNNBackbone(3, out_dim=16, hidden=8), out_dim=24, num_slots=3, slot_iters=2).eval()
    pixels = torch.randint(0, 256, (*batch_shape, 24, 24, 3), dtype=torch.uint8)
    results = []
    for fast in (False, True):
        enc.slot_attention.fast = fast
        for m in enc.backbone.net:
            if isinstance(m, torch.nn.ReLU):
                m.inplace = fast
        enc.zero_grad(set_to_none=True)
        slots = enc(pixels)
        (slots * torch.linspace(-1.0, 1.0, slots.numel()).reshape(slots.shape)).sum().backward()
        results.append((slots.detach(), _grads(enc)))
    (ref, ref_grads), (fast, fast_grads) = results
    assert fast.shape == (*batch_shape, 3, 24)
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)
    assert len(fast_grads) == len(ref_grads) == len(list(enc.parameters()))
    for g_fast, g_ref in zip(fast_grads, ref_grads):
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("env_id", ["MiniGrid-MultiRoom-N2-S4-v0", "MiniGrid-DoorKey-5x5-v0"])
def test_render_pov_is_minigrid_get_frame(env_id):
    """Random play (pickups, doors, episode ends): every frame identical to MiniGrid's own rendering."""
    from freamer_rl_envs.minigrid import PIXEL_TILE_SIZE, make_minigrid_env, render_pov

    env = make_minigrid_env(env_id, pixels=True, seed=0)
    env.reset()
    raw = env._unwrapped
    rng = np.random.default_rng(0)
    for _ in range(150):
        fast = render_pov(raw, PIXEL_TILE_SIZE)
        ref = raw.get_frame(tile_size=PIXEL_TILE_SIZE, agent_pov=True)
        assert fast.dtype == ref.dtype == np.uint8 and fast.shape == ref.shape == (56, 56, 3)
        np.testing.assert_array_equal(fast, ref)
        _, _, terminated, truncated, _ = raw.step(int(rng.integers(6)))
        if terminated or truncated:
            raw.reset()
    env.close()


def test_minigrid_env_pixels_same_with_fast_render_on_and_off():
    from freamer_rl_envs.minigrid import make_minigrid_env

    rollouts = []
    for fast in (False, True):
        env = make_minigrid_env("MiniGrid-DoorKey-5x5-v0", pixels=True, seed=3)
        env.fast_render = fast
        torch.manual_seed(0)
        rollouts.append(env.rollout(40, break_when_any_done=False))
        env.close()
    assert torch.equal(rollouts[0]["pixels"], rollouts[1]["pixels"])
    assert torch.equal(rollouts[0]["next", "pixels"], rollouts[1]["next", "pixels"])
