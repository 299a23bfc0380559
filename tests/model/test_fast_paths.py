"""The throughput work's fast paths against their reference paths (same maths, tolerance of float rounding)."""

from __future__ import annotations

import logging

import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from freamer_rl.layers import dedup
from freamer_rl.layers.checks import set_value_checks
from freamer_rl.layers.compiled import CompileOrEager
from freamer_rl.layers.dedup import MIN_ROWS, dedup_rows, distinct_rows
from freamer_rl.layers.encoders import RewardEncoder
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fno import FNOFuser, StateFNOEncoder
from freamer_rl.layers.tdmodule import KeyedModule
from freamer_rl.run.rundir import Terminated


@pytest.fixture
def no_value_checks():
    old = set_value_checks(False)
    yield
    set_value_checks(old)


def _repeated_rows(n_rows: int, n_distinct: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    base = torch.randn(n_distinct, width)
    pick = torch.randint(0, n_distinct, (n_rows,))
    pick[:n_distinct] = torch.arange(n_distinct)  # every distinct row occurs
    return base[pick], pick


# ---------------------------------------------------------------------------------------------------------------
# row deduplication
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n_distinct", [1, 3, 40])
def test_distinct_rows_reconstructs_exactly(n_distinct):
    x, _ = _repeated_rows(128, n_distinct, 8)
    first, inverse = distinct_rows(x)
    assert first.shape == (n_distinct,)
    assert torch.equal(x[first][inverse], x)


def test_distinct_rows_declines_when_no_time_to_win(no_value_checks):
    x, _ = _repeated_rows(128, 2, 8)
    assert distinct_rows(x) is None  # value checks off (accelerator setting): no host reads


def test_distinct_rows_declines_small_unique_nan_and_vmap():
    x, _ = _repeated_rows(128, 2, 8)
    assert distinct_rows(x[: MIN_ROWS - 1]) is None  # a collection step: computed directly
    assert distinct_rows(torch.randn(128, 8)) is None  # every row distinct
    x_nan = x.clone()
    x_nan[5, 0] = float("nan")
    assert distinct_rows(x_nan) is None  # NaN != NaN: never merged
    seen = []
    torch.vmap(lambda row: seen.append(distinct_rows(row.expand(128, 8))) or row)(x[:3])
    assert seen == [None]


def test_hash_collision_cannot_merge_different_rows(monkeypatch):
    x, _ = _repeated_rows(128, 3, 8)
    monkeypatch.setattr(dedup, "_probe", lambda width, device: torch.zeros(width, dtype=torch.float64))
    assert distinct_rows(x) is None  # every row hashes to 0; the exact check refuses the grouping


def test_dedup_rows_same_values_and_parameter_gradients():
    net = nn.Sequential(nn.Linear(8, 16), nn.SiLU(), nn.Linear(16, 4))
    x, _ = _repeated_rows(256, 5, 8)
    ref = net(x)
    (ref * torch.arange(4.0)).sum().backward()
    ref_grads = [p.grad.clone() for p in net.parameters()]
    net.zero_grad()
    out = dedup_rows(net, x)
    (out * torch.arange(4.0)).sum().backward()
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    for g, r in zip((p.grad for p in net.parameters()), ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("batch", [(128,), (8, 16), (2, 4, 16)])
def test_refiner_dedup_matches_reference_end_to_end(batch):
    """Encoder (upstream parameters) -> refiner: outputs and every gradient equal with and without deduplication."""
    torch.manual_seed(0)
    obs, _ = _repeated_rows(int(torch.tensor(batch).prod()), 3, 6)
    obs = obs.reshape(*batch, 6)
    encoder = nn.Linear(6, 16)
    fast = FlowMatchingRefiner(16, hidden=32, steps=3, gate_init=0.5)
    slow = FlowMatchingRefiner(16, hidden=32, steps=3, gate_init=0.5, deduplicate=False)
    slow.load_state_dict(fast.state_dict())
    outs, grads = [], []
    for refiner in (fast, slow):
        encoder.zero_grad()
        out = refiner(encoder(obs))
        (out * torch.linspace(-1, 1, 16)).sum().backward()
        outs.append(out)
        grads.append([p.grad.clone() for p in [*encoder.parameters(), *refiner.parameters()]])
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-5, atol=1e-6)
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_reward_encoder_dedup_matches_reference():
    enc = RewardEncoder(history=8, out_dim=16)
    hist = torch.zeros(200, 8)
    hist[::17, -1] = 1.0  # sparse rewards: a few distinct histories
    out = enc(hist)
    out.pow(2).sum().backward()
    grads = [p.grad.clone() for p in enc.parameters()]
    enc.zero_grad()
    old = set_value_checks(False)  # the reference: every row computed
    try:
        ref = enc(hist)
        ref.pow(2).sum().backward()
    finally:
        set_value_checks(old)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    for g, p in zip(grads, enc.parameters()):
        torch.testing.assert_close(g, p.grad, rtol=1e-4, atol=1e-5)


# ---------------------------------------------------------------------------------------------------------------
# FNO layers: DFT-matmul paths against the FFT definitions
# ---------------------------------------------------------------------------------------------------------------
def _state_encoder_reference(enc: StateFNOEncoder, grid: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
    """Appendix E.2 written plainly: three embedding lookups, FFT spectral conv + 1x1 conv, GELU, flatten, Linear."""
    g = grid.long().reshape(-1, enc.seq_len, 3)
    o = enc.object_embed(g[..., 0]) + enc.color_embed(g[..., 1]) + enc.state_embed(g[..., 2])  # [B, L, C]
    o = o.transpose(1, 2)  # [B, C, L]
    h = F.gelu(enc.spectral(o) + enc.pointwise(o)).transpose(1, 2)  # [B, L, C]
    e = enc.proj(h.reshape(h.shape[0], -1)) + enc.direction_embed(direction.reshape(-1))
    return e.reshape(*grid.shape[:-3], enc.out_dim)


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_state_encoder_matches_fft_reference(batch):
    enc = StateFNOEncoder(out_dim=16, channels=8, modes=6)
    grid = torch.stack(
        [
            torch.randint(0, 11, (*batch, 7, 7)),
            torch.randint(0, 6, (*batch, 7, 7)),
            torch.randint(0, 3, (*batch, 7, 7)),
        ],
        dim=-1,
    )
    direction = torch.randint(0, 4, batch)
    out = enc(grid, direction)
    ref = _state_encoder_reference(enc, grid, direction)
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-5)
    params = list(enc.parameters())
    g_out = torch.autograd.grad(out.sum(), params, allow_unused=True)
    g_ref = torch.autograd.grad(ref.sum(), params, allow_unused=True)
    for a, b in zip(g_out, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
def test_fuser_matches_fft_reference(batch):
    fuser = FNOFuser(num_modalities=3, dim=32, modes=8, residual_scale=0.7)
    e = torch.randn(*batch, 3, 32)
    spec = fuser.spectral(e)  # FFT definition (Eq. A14)
    pw = fuser.pointwise(e.transpose(-1, -2)).transpose(-1, -2)
    e_out_ref = e + fuser.residual_scale * F.gelu(fuser.norm(spec + pw))
    fused, e_out = fuser(e)
    torch.testing.assert_close(e_out, e_out_ref, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(fused, e_out_ref.mean(-2), rtol=1e-4, atol=1e-5)


# ---------------------------------------------------------------------------------------------------------------
# torch.compile with a fallback
# ---------------------------------------------------------------------------------------------------------------
def test_compile_or_eager_falls_back_loudly(monkeypatch, caplog):
    def broken_compile(fn, **kwargs):
        def run(*a, **k):
            raise RuntimeError("backend exploded")

        return run

    monkeypatch.setattr(torch, "compile", broken_compile)
    f = CompileOrEager(lambda x: x * 2, "doubler")
    with caplog.at_level(logging.WARNING):
        assert torch.equal(f(torch.ones(2)), torch.full((2,), 2.0))
        assert torch.equal(f(torch.ones(2)), torch.full((2,), 2.0))
    assert f.fallbacks == 1
    assert (
        sum("doubler: torch.compile failed (RuntimeError: backend exploded)" in r.message for r in caplog.records) == 1
    )


def test_compile_or_eager_keeps_bad_input_errors(monkeypatch):
    compiled_calls = []

    def counting_compile(fn, **kw):
        def run(*a, **k):
            compiled_calls.append(1)
            return fn(*a, **k)

        return run

    monkeypatch.setattr(torch, "compile", counting_compile)
    f = CompileOrEager(lambda x: x.reshape(3), "reshaper")
    with pytest.raises(RuntimeError, match="shape"):
        f(torch.ones(4))
    assert f.fallbacks == 0  # the input's error, not the compiler's
    assert torch.equal(f(torch.ones(3)), torch.ones(3))
    assert len(compiled_calls) == 2  # the next call still ran the compiled function: compiling stays on


def test_compile_or_eager_raises_an_interrupt_the_compiler_wrapped_instead_of_falling_back(monkeypatch):
    # a Ctrl-C / SIGTERM during compilation that the compiler turns into its own error must stop the run: taken for
    # a failed compilation, it would be swallowed and the run would go on eagerly
    def interrupted_compile(fn, **kwargs):
        def run(*a, **k):
            try:
                raise Terminated("SIGTERM")
            except KeyboardInterrupt as err:
                raise RuntimeError("backend compiler failed") from err

        return run

    monkeypatch.setattr(torch, "compile", interrupted_compile)
    f = CompileOrEager(lambda x: x * 2, "doubler")
    with pytest.raises(Terminated):
        f(torch.ones(2))
    assert f.fallbacks == 0 and not f._failed


# ---------------------------------------------------------------------------------------------------------------
# KeyedModule
# ---------------------------------------------------------------------------------------------------------------
def test_keyed_module_is_a_drop_in_tensordict_module():
    net = nn.Linear(3, 2)
    fast = KeyedModule(net, in_keys=["x"], out_keys=[("out", "y")])
    slow = TensorDictModule(net, in_keys=["x"], out_keys=[("out", "y")])
    td = TensorDict({"x": torch.randn(4, 3)}, [4])
    assert isinstance(fast, TensorDictModule)
    assert torch.equal(fast(td.clone())["out", "y"], slow(td.clone())["out", "y"])
    assert fast.state_dict().keys() == slow.state_dict().keys()
    nested = KeyedModule(lambda x: TensorDict({"a": x}, x.shape[:1]), in_keys=["x"], out_keys=["sub"])
    assert torch.equal(nested(td.clone())["sub", "a"], td["x"])  # tensor collections: the parent's path
