"""Every layer's forward is free of host syncs: torch.vmap, torch.compile and TorchRL's GAE (vmap by default) work.

``torch.vmap(module)(x)`` maps over the first batch dim, so the module sees the remaining batch dims; the result
must equal the plain batched forward. Value checks (index ranges, NaN/Inf) and counting are skipped under the
transforms (see ``freamer_rl.layers.checks``); the maths is the same.
"""

from __future__ import annotations

import functools
import warnings

import pytest
import torch

from freamer_rl.layers.checks import is_transformed, value_checks_active
from freamer_rl.layers.dnc import DNCMemory
from freamer_rl.layers.encoders import (
    CNNBackbone,
    CrossModalAttention,
    LanguageEncoder,
    RewardEncoder,
    SlotPool,
    VisionEncoder,
)
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fno import FNOFuser, StateFNOEncoder

BATCH_SHAPES = [(3,), (3, 2)]  # vmap over the first dim; the module sees () or (2,)
D = 16


def _grid(batch):
    parts = [torch.randint(0, n, (*batch, 7, 7, 1)) for n in (11, 6, 3)]
    return torch.cat(parts, dim=-1)


def _tokens(batch):
    t = torch.randint(1, 20, (*batch, 6))
    t[..., 4:] = 0  # trailing padding
    flat = t.view(-1, 6)
    flat[-1] = flat[0]  # a repeated row: the eager forward deduplicates it, vmap does not
    return t


def _case(name: str, batch: tuple[int, ...]):
    """(module, inputs) of layer ``name`` with batch dims ``batch``; eval mode (deterministic slot init)."""
    if name == "state":
        return StateFNOEncoder(D, channels=8, modes=6), (_grid(batch), torch.randint(0, 4, batch))
    if name == "reward":
        return RewardEncoder(4, D, channels=4), (torch.randn(*batch, 4),)
    if name == "language":
        return LanguageEncoder(20, D, num_slots=2, heads=2, max_len=6, slot_iters=2), (_tokens(batch),)
    if name == "cnn":
        return CNNBackbone(out_dim=8, hidden=4), (torch.randint(0, 256, (*batch, 16, 16, 3), dtype=torch.uint8),)
    if name == "vision":
        enc = VisionEncoder(CNNBackbone(out_dim=8, hidden=4), D, num_slots=2, slot_iters=2)
        return enc, (torch.rand(*batch, 16, 16, 3) * 255,)
    if name == "cross_modal":
        return CrossModalAttention(D, heads=2), (torch.randn(*batch, 3, D), torch.randn(*batch, 2, D))
    if name == "slot_pool":
        return SlotPool(), (torch.randn(*batch, 3, D),)
    if name == "flow":
        return FlowMatchingRefiner(D, hidden=8, steps=2), (torch.randn(*batch, D),)
    if name == "fuser":
        return FNOFuser(3, D, modes=4), (torch.randn(*batch, 3, D),)
    if name == "dnc":
        dnc = DNCMemory(D, memory_slots=4, memory_width=6, memory_clip=0.5)  # small clip: the clamp is exercised
        return dnc.step, (torch.randn(*batch, D), torch.rand(*batch, 4, 6) * 2 - 1)
    raise KeyError(name)


LAYERS = ["state", "reward", "language", "cnn", "vision", "cross_modal", "slot_pool", "flow", "fuser", "dnc"]


def _as_tuple(out):
    return out if isinstance(out, tuple) else (out,)


@pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
@pytest.mark.parametrize("name", LAYERS)
@pytest.mark.parametrize("grad", [False, True], ids=["no_grad", "grad"])
def test_vmap_equals_batched_forward(name, batch, grad):
    torch.manual_seed(0)
    module, inputs = _case(name, batch)
    if isinstance(module, torch.nn.Module):
        module.eval()
    with torch.set_grad_enabled(grad), warnings.catch_warnings():
        # a few ops (gru_cell, fused attention kernels) have no batching rule: vmap loops over them (same maths)
        warnings.filterwarnings("ignore", message=".*performance drop.*")
        expected = _as_tuple(module(*inputs))
        mapped = _as_tuple(torch.vmap(module)(*inputs))
    assert len(mapped) == len(expected)
    for got, want in zip(mapped, expected):
        assert got.shape == want.shape
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["language", "vision", "dnc"])
def test_vmap_over_parameters_only(name):
    """Ensembles / functional params vmap the parameters with plain inputs: no host sync, no cache fill."""
    torch.manual_seed(0)
    copies = [_case(name, (2,)) for _ in range(2)]
    inputs = copies[0][1]
    # DNCMemory.forward is DNCMemory.step; the others are eval-mode nn.Modules
    modules = [getattr(m, "__self__", m).eval() for m, _ in copies]
    params, buffers = torch.func.stack_module_state(modules)

    def call(p, b):
        return _as_tuple(torch.func.functional_call(modules[0], (p, b), inputs))

    with torch.no_grad(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*performance drop.*")
        mapped = torch.vmap(call)(params, buffers)
        if name == "language":  # the inference cache was bypassed inside vmap: an eager call encodes its rows
            embedded = []
            hook = modules[0].embed.register_forward_hook(lambda module, args, out: embedded.append(args[0].shape[0]))
            modules[0](*inputs)
            hook.remove()
            assert embedded, "served from a cache filled inside vmap"
        for i, module in enumerate(modules):
            for got, want in zip(mapped, _as_tuple(module(*inputs))):
                torch.testing.assert_close(got[i], want, atol=1e-5, rtol=1e-5)


def test_counters_are_not_touched_under_vmap():
    dnc = DNCMemory(D, memory_slots=4, memory_width=6, memory_clip=1e-3)
    torch.vmap(dnc.step)(torch.randn(3, D), torch.rand(3, 4, 6))
    assert dnc.clip_events == 0
    dnc.step(torch.randn(3, D), torch.rand(3, 4, 6))
    assert dnc.clip_events > 0


def test_checks_helper():
    x = torch.randn(3)
    assert value_checks_active(x) and not is_transformed(x, 1.0)
    flags = torch.vmap(lambda t: torch.tensor(float(is_transformed(t))) + 0 * t)(x)
    assert flags.eq(1).all()
    assert value_checks_active()  # no tensors, not compiling


@pytest.mark.parametrize("name", ["state", "language", "vision", "fuser", "dnc"])
def test_compile_fullgraph_without_graph_breaks(name):
    """``torch.compile(fullgraph=True)`` refuses any graph break (a host sync would be one)."""
    torch.manual_seed(0)
    module, inputs = _case(name, (2,))
    if isinstance(module, torch.nn.Module):
        module.eval()
    compiled = torch.compile(module, backend="eager", fullgraph=True)
    with torch.no_grad():
        for got, want in zip(_as_tuple(compiled(*inputs)), _as_tuple(module(*inputs))):
            torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    torch.compiler.reset()


def test_full_policy_through_torchrl_gae_with_default_vmap():
    """build_freamer's value network inside TorchRL's GAE with its default vmap (no deactivate_vmap)."""
    from torchrl.envs import Compose, InitTracker, SerialEnv, TransformedEnv
    from torchrl.objectives.value import GAE

    from freamer_rl.model.config import (
        DNCConfig,
        FlowConfig,
        FNOConfig,
        LanguageConfig,
        ModelConfig,
        RewardConfig,
        StateConfig,
        VisionConfig,
    )
    from freamer_rl.model.factory import build_freamer
    from freamer_rl_envs.minigrid import make_minigrid_env

    torch.manual_seed(0)
    make_env = functools.partial(
        make_minigrid_env, "MiniGrid-Empty-5x5-v0", pixels=True, reward_history=4, include_mission=False
    )
    probe = make_env()
    cfg = ModelConfig(
        modalities=["state", "vision", "language", "reward"],
        embed_dim=D,
        cross_modal_heads=2,
        head_hidden=D,
        vision=VisionConfig(backbone="cnn", num_slots=2, slot_iters=1),
        language=LanguageConfig(num_slots=2, layers=1, heads=2, slot_iters=1),
        state=StateConfig(channels=4, modes=4),
        reward=RewardConfig(channels=2),
        flow=FlowConfig(hidden=8, steps=1),
        fno=FNOConfig(modes=4),
        dnc=DNCConfig(memory_slots=4, memory_width=6),
    )
    modules = build_freamer(probe.observation_spec, probe.action_spec, cfg)
    modules.actor_value.eval()  # deterministic slot initialisation, as the trainer runs it
    env = TransformedEnv(SerialEnv(2, make_env), Compose(InitTracker(), *modules.primers()))
    env.set_seed(0)
    with torch.no_grad():
        data = env.rollout(8, modules.policy, break_when_any_done=False)
    env.close()
    assert data.batch_size == (2, 8)
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=modules.value)
    assert not gae.deactivate_vmap
    with torch.no_grad(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*performance drop.*")
        out = gae(data)
    assert out["advantage"].shape == (2, 8, 1)
    assert torch.isfinite(out["advantage"]).all() and torch.isfinite(out["value_target"]).all()
    # vmap computed the same values as a plain (eager, checked) call of the value network on the stored states
    with torch.no_grad():
        plain = modules.value(data.select(*modules.value.in_keys).clone())["state_value"]
    torch.testing.assert_close(out["state_value"], plain, atol=1e-5, rtol=1e-5)


def test_value_checks_can_be_switched_off():
    from freamer_rl.layers.checks import set_value_checks
    from freamer_rl.layers.encoders import RewardEncoder

    enc = RewardEncoder(history=3, out_dim=4)
    x = torch.tensor([[0.0, float("nan"), 1.0]])
    with pytest.raises(ValueError, match="non-finite"):
        enc(x)
    old = set_value_checks(False)
    try:
        assert torch.isnan(enc(x)).any()  # same maths, nothing checked
    finally:
        set_value_checks(old)
