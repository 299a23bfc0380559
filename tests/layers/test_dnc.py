"""Layer 4 DNC memory (Appendix F.1) and its TorchRL stateful wrapper (LSTMModule pattern)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode

from freamer_rl.layers.dnc import DNCMemory, DNCModule

BATCH_SHAPES = [(), (2,), (3, 2)]
N, W, D = 5, 6, 8


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_memory_step_shapes(batch):
    dnc = DNCMemory(D, memory_slots=N, memory_width=W, output_dim=3)
    out, mem = dnc.step(torch.randn(*batch, D), dnc.initial_memory(batch))
    assert out.shape == (*batch, 3)
    assert mem.shape == (*batch, N, W)
    assert DNCMemory(D, N, W).output_dim == D
    with pytest.raises(ValueError, match=r"N=5, W=6"):
        dnc.step(torch.randn(*batch, D), torch.zeros(*batch, N, W + 1))
    with pytest.raises(ValueError, match="input_dim=8"):
        dnc.step(torch.randn(*batch, D + 1), dnc.initial_memory(batch))


def test_content_addressing_picks_most_similar_slot():
    memory = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0]])
    key = torch.tensor([0.1, 0.9, 0.05]) * 7.0  # cosine ignores the key's scale
    w = DNCMemory.content_weights(key, memory, torch.tensor(5.0))
    assert w.shape == (4,)
    assert w.argmax().item() == 1
    torch.testing.assert_close(w.sum(), torch.tensor(1.0))
    # closed form: softmax(beta * cos)
    cos = (memory @ key) / (memory.norm(dim=-1) * key.norm())
    torch.testing.assert_close(w, torch.softmax(5.0 * cos, -1))
    # sharper with a larger strength
    w_sharp = DNCMemory.content_weights(key, memory, torch.tensor(50.0))
    assert w_sharp[1] > w[1] and w_sharp[1] > 0.99
    # batched
    keys = torch.stack([memory[2], memory[0]])
    wb = DNCMemory.content_weights(keys, memory.expand(2, 4, 3), torch.tensor([20.0, 20.0]))
    assert wb.argmax(-1).tolist() == [2, 0]


def test_zero_memory_gives_uniform_weights_and_finite_grads():
    memory = torch.zeros(3, 4, requires_grad=True)
    key = torch.randn(4, requires_grad=True)
    w = DNCMemory.content_weights(key, memory, torch.tensor(3.0))
    torch.testing.assert_close(w, torch.full((3,), 1 / 3))
    (w * torch.arange(3.0)).sum().backward()
    assert torch.isfinite(memory.grad).all() and torch.isfinite(key.grad).all()


def test_write_erase_and_read_closed_form():
    memory = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    w = torch.tensor([0.25, 0.75])
    erase = torch.tensor([0.5, 1.0])
    add = torch.tensor([-1.0, 2.0])
    g = torch.tensor(0.8)
    new = DNCMemory.write(memory, w, erase, add, g)
    expected = torch.empty(2, 2)
    for i in range(2):
        for j in range(2):
            gw = float(g) * float(w[i])
            expected[i, j] = memory[i, j] * (1 - gw * erase[j]) + gw * add[j]
    # slot 0: gw = 0.2 -> [1*(0.9) - 0.2, 2*(0.8) + 0.4] = [0.7, 2.0]
    torch.testing.assert_close(expected[0], torch.tensor([0.7, 2.0]))
    torch.testing.assert_close(new, expected)
    r = DNCMemory.read(new, torch.tensor([0.4, 0.6]))
    torch.testing.assert_close(r, 0.4 * new[0] + 0.6 * new[1])
    # gate 0 leaves the memory untouched; full erase + gate 1 + one-hot weights overwrite the slot
    torch.testing.assert_close(DNCMemory.write(memory, w, erase, add, torch.tensor(0.0)), memory)
    over = DNCMemory.write(memory, torch.tensor([0.0, 1.0]), torch.ones(2), add, torch.tensor(1.0))
    torch.testing.assert_close(over, torch.stack([memory[0], add]))


@pytest.mark.parametrize("write", ["additive", "bounded"])
def test_step_reads_after_write_and_stays_bounded(write):
    torch.manual_seed(0)
    dnc = DNCMemory(D, N, W, write=write)
    mem = dnc.initial_memory((4,))
    for _ in range(50):
        x = torch.randn(4, D) * 1e3
        out, mem = dnc.step(x, mem)
        assert torch.isfinite(out).all() and torch.isfinite(mem).all()
        assert mem.abs().max() <= dnc.memory_clip
    # step = write with content weights, then read from the *written* memory
    x = torch.randn(4, D)
    c = dnc.interface_vectors(x)
    w_w = dnc.content_weights(c["write_key"], mem, c["write_strength"])
    m2 = (dnc.write_bounded if write == "bounded" else dnc.write)(
        mem, w_w, c["erase"], c["write_vector"], c["write_gate"]
    )
    r = dnc.read(m2, dnc.content_weights(c["read_key"], m2, c["read_strength"]))
    out, new = dnc.step(x, mem)
    torch.testing.assert_close(new, m2)
    torch.testing.assert_close(out, torch.nn.functional.gelu(dnc.out(torch.cat([x, r], -1))))


def test_memory_clamp_is_counted_and_logged(caplog):
    dnc = DNCMemory(D, N, W, memory_clip=1.5)
    with torch.no_grad():  # no erase, full gate, write vector ~ +1: every step adds ~1/N to every slot
        bias = dnc.interface.bias.view(-1)
        dnc.interface.weight.zero_()
        bias.zero_()
        bias[W + 1 : 2 * W + 1] = -30.0  # erase logits
        bias[2 * W + 1 : 3 * W + 1] = 30.0  # write-vector pre-tanh
        bias[3 * W + 1] = 30.0  # gate logit
    mem = dnc.initial_memory((2,))
    with caplog.at_level("WARNING", logger="freamer_rl.layers.dnc"):
        for _ in range(3 * N):
            _, mem = dnc.step(torch.randn(2, D), mem)
    assert dnc.clip_events > 0
    assert "clamped" in caplog.text
    torch.testing.assert_close(mem, torch.full_like(mem, 1.5))
    unclamped = DNCMemory(D, N, W, memory_clip=None)
    unclamped.load_state_dict(dnc.state_dict())
    m = unclamped.initial_memory((2,))
    for _ in range(3 * N):
        _, m = unclamped.step(torch.randn(2, D), m)
    assert m.max() > 2.5 and unclamped.clip_events == 0  # the DNC update itself is not bounded
    with pytest.raises(ValueError, match="memory_clip"):
        DNCMemory(D, N, W, memory_clip=0.0)


def test_bounded_write_closed_form():
    memory = torch.tensor([[1.0, -0.5], [0.25, 0.75]])
    w = torch.tensor([0.25, 0.75])
    erase = torch.tensor([0.5, 1.0])
    add = torch.tensor([-1.0, 0.5])
    new = DNCMemory.write_bounded(memory, w, erase, add, torch.tensor(0.8))
    # lambda = g w_i e_j: slot 0 [0.1, 0.2], slot 1 [0.3, 0.6]; M' = (1 - lambda) M + lambda a
    expected = torch.tensor(
        [[0.9 * 1.0 + 0.1 * -1.0, 0.8 * -0.5 + 0.2 * 0.5], [0.7 * 0.25 + 0.3 * -1.0, 0.4 * 0.75 + 0.6 * 0.5]]
    )
    torch.testing.assert_close(new, expected)
    # erase 0 writes nothing (the additive write would add g w a); full erase, gate 1, one-hot: overwrite the slot
    torch.testing.assert_close(DNCMemory.write_bounded(memory, w, torch.zeros(2), add, torch.tensor(1.0)), memory)
    assert not torch.allclose(DNCMemory.write(memory, w, torch.zeros(2), add, torch.tensor(1.0)), memory)
    over = DNCMemory.write_bounded(memory, torch.tensor([0.0, 1.0]), torch.ones(2), add, torch.tensor(1.0))
    torch.testing.assert_close(over, torch.stack([memory[0], add]))


def _extreme_controls(dnc: DNCMemory) -> None:
    """Large random interface weights (gates and write vector near 0/1 and +-1, sharp keys) and an erase gate near 0
    (logit -5): the case whose additive fixed point ``a / e`` lies far beyond the clamp."""
    with torch.no_grad():
        dnc.interface.weight.normal_(0.0, 3.0)
        dnc.interface.weight[W + 1 : 2 * W + 1] = 0.0
        dnc.interface.bias.view(-1)[W + 1 : 2 * W + 1] = -5.0


def test_bounded_step_stays_in_unit_bound_where_additive_saturates():
    torch.manual_seed(0)
    bounded = DNCMemory(D, N, W, write="bounded")
    _extreme_controls(bounded)
    additive = DNCMemory(D, N, W, write="additive")
    additive.load_state_dict({k: v for k, v in bounded.state_dict().items() if k != "write_code"})
    mb, ma = bounded.initial_memory((8,)), additive.initial_memory((8,))
    worst_b, worst_a = torch.zeros(()), torch.zeros(())
    with torch.no_grad():
        for _ in range(2_000):
            x = torch.randn(8, D) * 5.0
            _, mb = bounded.step(x, mb)
            _, ma = additive.step(x, ma)
            worst_b, worst_a = torch.maximum(worst_b, mb.abs().max()), torch.maximum(worst_a, ma.abs().max())
    assert float(worst_b) <= 1.0 + 1e-6 and bounded.clip_events == 0
    # the same controls drive the additive write to its clamp: the bound is the write's, not the inputs'
    assert float(worst_a) == additive.memory_clip and additive.clip_events > 0


def test_bounded_write_random_convex_steps():
    """10,000 random steps of the write itself with worst-case gates (g = 1, e in {0, 1} or uniform, one-hot or
    random weights, |a| = 1): never above 1."""
    gen = torch.Generator().manual_seed(1)
    memory, worst = torch.zeros(16, N, W), torch.zeros(())
    for step in range(10_000):
        weights = torch.softmax(torch.randn(16, N, generator=gen) * (100.0 if step % 2 else 1.0), -1)
        erase = torch.rand(16, W, generator=gen)
        erase = erase.round() if step % 3 == 0 else erase
        add = torch.where(torch.rand(16, W, generator=gen) < 0.5, -1.0, 1.0)
        memory = DNCMemory.write_bounded(memory, weights, erase, add, torch.ones(16))
        worst = torch.maximum(worst, memory.abs().max())
    assert 0.99 < float(worst) <= 1.0 + 1e-6


def test_output_norm_is_a_layer_norm_of_e_aug():
    torch.manual_seed(0)
    dnc = DNCMemory(D, N, W, output_dim=5, output_norm=True)
    x, mem = torch.randn(3, D) * 10.0, torch.rand(3, N, W)
    out, new = dnc.step(x, mem)
    plain = DNCMemory(D, N, W, output_dim=5)
    plain.load_state_dict({k: v for k, v in dnc.state_dict().items() if not k.startswith("out_norm.")})
    raw, new_plain = plain.step(x, mem)
    torch.testing.assert_close(new, new_plain)
    torch.testing.assert_close(
        out, (raw - raw.mean(-1, keepdim=True)) / (raw.var(-1, unbiased=False, keepdim=True) + 1e-5).sqrt()
    )
    assert {"out_norm.weight", "out_norm.bias"} <= set(dnc.state_dict())


def test_write_choice_travels_with_the_state_dict(caplog):
    torch.manual_seed(0)
    trained = DNCMemory(D, N, W, write="additive")
    legacy = {k: v for k, v in trained.state_dict().items() if k != "write_code"}  # a checkpoint of before the choice
    built = DNCMemory(D, N, W, write="bounded")
    with caplog.at_level("WARNING", logger="freamer_rl.layers.dnc"):
        built.load_state_dict(legacy)
    assert built.write_mode == "additive" and "predates" in caplog.text and "model.dnc.write" in caplog.text
    x, mem = torch.randn(2, D), torch.rand(2, N, W)
    torch.testing.assert_close(built.step(x, mem), trained.step(x, mem))
    # a state that records bounded loads as bounded into a module built additive
    again = DNCMemory(D, N, W)
    again.load_state_dict(DNCMemory(D, N, W, write="bounded").state_dict())
    assert again.write_mode == "bounded" and int(again.write_code) == 1
    with pytest.raises(RuntimeError, match="write_code"):
        again.load_state_dict({**legacy, "write_code": torch.tensor(7, dtype=torch.uint8)})
    with pytest.raises(ValueError, match="write must be one of additive, bounded"):
        DNCMemory(D, N, W, write="convex")


def test_bounded_step_under_vmap_matches_batched():
    torch.manual_seed(0)
    dnc = DNCMemory(D, N, W, write="bounded", output_norm=True)
    x, mem = torch.randn(3, D), torch.rand(3, N, W) * 2 - 1
    out_v, mem_v = torch.vmap(dnc.step)(x, mem)
    out_b, mem_b = dnc.step(x, mem)
    torch.testing.assert_close(out_v, out_b)
    torch.testing.assert_close(mem_v, mem_b)


def test_clamp_counting_is_skipped_under_vmap():
    dnc = DNCMemory(D, N, W, memory_clip=1e-3)
    out, mem = torch.vmap(dnc.step)(torch.randn(3, D), torch.rand(3, N, W))
    assert mem.abs().max() <= 1e-3 and dnc.clip_events == 0


def _module(**kw):
    return DNCModule(D, memory_slots=N, memory_width=W, output_dim=4, **kw)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_module_step_mode_and_is_init_reset(batch):
    torch.manual_seed(0)
    module = _module()
    assert module.in_keys == ["fused", ("dnc", "memory"), "is_init"]
    assert module.out_keys == ["hidden", ("next", "dnc", "memory")]
    x = torch.randn(*batch, D)
    memory = torch.rand(*batch, N, W) * 2 - 1
    is_init = torch.zeros(*batch, 1, dtype=torch.bool)
    if batch:
        is_init.view(-1, 1)[0] = True
    else:
        is_init[...] = True
    td = TensorDict({"fused": x, ("dnc", "memory"): memory, "is_init": is_init}, batch_size=batch)
    module(td)
    assert td["hidden"].shape == (*batch, 4)
    assert td["next", "dnc", "memory"].shape == (*batch, N, W)
    expected_mem = torch.where(is_init[..., None], torch.zeros_like(memory), memory)
    out, new = module.dnc.step(x, expected_mem)
    torch.testing.assert_close(td["hidden"], out)
    torch.testing.assert_close(td["next", "dnc", "memory"], new)
    # root memory is left untouched (it is the state *before* the step)
    torch.testing.assert_close(td["dnc", "memory"], memory)


def test_module_missing_keys_raise_clear_errors():
    module = _module()
    with pytest.raises(KeyError, match="make_tensordict_primer"):
        module(TensorDict({"fused": torch.randn(D), "is_init": torch.ones(1, dtype=torch.bool)}, []))
    with pytest.raises(KeyError, match="InitTracker"):
        module(TensorDict({"fused": torch.randn(D), ("dnc", "memory"): torch.zeros(N, W)}, []))
    with pytest.raises(ValueError, match="must have shape"):
        module(
            TensorDict(
                {"fused": torch.randn(D), ("dnc", "memory"): torch.zeros(N, W), "is_init": torch.ones(2).bool()}, []
            )
        )


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_recurrent_mode_equals_stepping(batch):
    torch.manual_seed(0)
    module = _module(in_key="obs_embed", out_key="h", memory_key="mem", is_init_key="start")
    T = 6
    x = torch.randn(*batch, T, D)
    memory0 = torch.rand(*batch, N, W) * 2 - 1
    is_init = torch.zeros(*batch, T, 1, dtype=torch.bool)
    is_init[..., 3, :] = True  # an episode boundary in the middle of every row
    if batch:
        is_init.view(-1, T, 1)[0, 1] = True  # and another one for the first row only
    # step one t at a time, carrying ("next", mem) -> mem as a rollout would
    outs, nexts, roots = [], [], []
    mem = memory0
    for t in range(T):
        td_t = TensorDict({"obs_embed": x[..., t, :], "mem": mem, "start": is_init[..., t, :]}, batch_size=batch)
        module(td_t)
        roots.append(mem)
        outs.append(td_t["h"])
        nexts.append(td_t["next", "mem"])
        mem = td_t["next", "mem"]
    stacked_roots = torch.stack(roots, dim=len(batch))
    # recurrent mode only reads the root memory at t = 0: poison the others
    garbage = torch.randn_like(stacked_roots) * 100
    garbage.select(len(batch), 0).copy_(memory0)
    td = TensorDict({"obs_embed": x, "mem": garbage, "start": is_init}, batch_size=(*batch, T))
    with set_recurrent_mode(True):
        # recurrent mode needs >= 2 batch dims: one unbatched trajectory is passed as [1, T]
        td = module(td) if batch else module(td.unsqueeze(0)).squeeze(0)
    torch.testing.assert_close(td["h"], torch.stack(outs, dim=len(batch)), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(td["next", "mem"], torch.stack(nexts, dim=len(batch)), atol=1e-5, rtol=1e-5)
    # and outside recurrent mode the same tensordict is T independent steps from the stored roots
    td2 = TensorDict({"obs_embed": x, "mem": stacked_roots, "start": is_init}, batch_size=(*batch, T))
    module(td2)
    torch.testing.assert_close(td2["h"], torch.stack(outs, dim=len(batch)), atol=1e-5, rtol=1e-5)


def test_recurrent_mode_needs_time_dim_and_default_mode():
    module = _module()
    td = TensorDict({"fused": torch.randn(D), ("dnc", "memory"): torch.zeros(N, W), "is_init": torch.ones(1).bool()})
    with set_recurrent_mode(True), pytest.raises(ValueError, match=r"needs \[B, T\] sequences"):
        module(td)
    assert not module.recurrent_mode
    assert _module(default_recurrent_mode=True).recurrent_mode
    with set_recurrent_mode(False):
        assert not _module(default_recurrent_mode=True).recurrent_mode


def test_recurrent_mode_refuses_a_flat_batch():
    """A flattened (possibly shuffled) 1-D minibatch must not be threaded through time as one sequence."""
    module = _module()
    T = 6
    td = TensorDict(
        {"fused": torch.randn(T, D), ("dnc", "memory"): torch.zeros(T, N, W), "is_init": torch.zeros(T, 1).bool()},
        batch_size=(T,),
    )
    with set_recurrent_mode(True), pytest.raises(ValueError) as err:
        module(td)
    msg = str(err.value)
    assert "\n" not in msg
    for part in (
        "[B, T]",
        "(6,)",
        "shuffled",
        "split_sequences",
        "SliceSampler",
        "Sequences for stateful layers",
        "unsqueeze(0)",
    ):
        assert part in msg, part
    with set_recurrent_mode(True):  # the advertised fix works
        out = module(td.unsqueeze(0))
    assert out["hidden"].shape == (1, T, 4)
    module(td)  # step mode treats the 1-D batch as T independent steps, as before
    assert td["hidden"].shape == (T, 4)


def test_non_finite_input_raises_except_under_vmap():
    dnc = DNCMemory(D, N, W)
    x = torch.randn(3, D)
    x[1, 2] = float("nan")
    with pytest.raises(ValueError, match=r"DNCMemory input: 1 non-finite values \(NaN/Inf\)"):
        dnc.step(x, dnc.initial_memory((3,)))
    out, _ = torch.vmap(dnc.step)(x, dnc.initial_memory((3,)))  # maths only under vmap: NaN propagates to its row
    assert torch.isnan(out[1]).all() and torch.isfinite(out[[0, 2]]).all()
    module = _module()
    td = TensorDict(
        {"fused": x.unsqueeze(0), ("dnc", "memory"): torch.zeros(1, 3, N, W), "is_init": torch.zeros(1, 3, 1).bool()},
        batch_size=(1, 3),
    )
    with set_recurrent_mode(True), pytest.raises(ValueError, match="DNCModule 'fused': 1 non-finite"):
        module(td)
    with pytest.raises(ValueError, match="DNCModule .fused.: 1 non-finite"):  # step mode
        module(td)


def test_gradients_flow_through_time():
    torch.manual_seed(0)
    module = _module()
    B, T = 2, 5
    x = torch.randn(B, T, D, requires_grad=True)
    td = TensorDict(
        {"fused": x, ("dnc", "memory"): torch.zeros(B, T, N, W), "is_init": torch.zeros(B, T, 1, dtype=torch.bool)},
        batch_size=(B, T),
    )
    with set_recurrent_mode(True):
        module(td)
    td["hidden"][:, -1].pow(2).sum().backward()
    assert x.grad[:, 0].abs().sum() > 0  # the first input influences the last output only through the memory


class _ToyEnv(EnvBase):
    """Unbatched env: 8-d random observation, 1-d continuous action, episodes of ``episode_len`` steps."""

    def __init__(self, episode_len: int = 4):
        super().__init__(batch_size=torch.Size([]))
        self.episode_len = episode_len
        self.observation_spec = Composite(observation=Unbounded(shape=(8,)))
        self.action_spec = Bounded(low=-1.0, high=1.0, shape=(1,))
        self.reward_spec = Unbounded(shape=(1,))
        self.done_spec = Composite(
            done=Categorical(2, shape=(1,), dtype=torch.bool),
            terminated=Categorical(2, shape=(1,), dtype=torch.bool),
            truncated=Categorical(2, shape=(1,), dtype=torch.bool),
        )
        self._t = 0
        self._rng = torch.Generator().manual_seed(0)

    def _reset(self, tensordict):
        self._t = 0
        false = torch.zeros(1, dtype=torch.bool)
        return TensorDict(
            {"observation": torch.randn(8, generator=self._rng), "done": false, "terminated": false, "truncated": false}
        )

    def _step(self, tensordict):
        self._t += 1
        done = torch.tensor([self._t >= self.episode_len])
        obs = torch.randn(8, generator=self._rng) + tensordict["action"]
        return TensorDict(
            {
                "observation": obs,
                "reward": torch.zeros(1),
                "done": done,
                "terminated": done.clone(),
                "truncated": torch.zeros(1, dtype=torch.bool),
            }
        )

    def _set_seed(self, seed):
        self._rng.manual_seed(int(seed) if seed is not None else 0)


def _policy(dnc_module):
    return TensorDictSequential(
        TensorDictModule(nn.Linear(8, D), in_keys=["observation"], out_keys=["fused"]),
        dnc_module,
        TensorDictModule(nn.Sequential(nn.Linear(4, 1), nn.Tanh()), in_keys=["hidden"], out_keys=["action"]),
    )


def test_primer_rollout_carries_memory():
    torch.manual_seed(0)
    module = _module()
    policy = _policy(module)
    env = TransformedEnv(_ToyEnv(episode_len=4), Compose(InitTracker(), module.make_tensordict_primer()))
    td0 = env.reset()
    torch.testing.assert_close(td0["dnc", "memory"], torch.zeros(N, W))
    with torch.no_grad():
        rollout = env.rollout(10, policy, break_when_any_done=False)
    assert rollout.batch_size == (10,)
    is_init = rollout["is_init"].squeeze(-1)
    assert is_init[0] and is_init[4] and is_init[8] and is_init.sum() == 3
    root, nxt = rollout["dnc", "memory"], rollout["next", "dnc", "memory"]
    assert nxt.abs().sum() > 0
    for t in range(9):
        expected = torch.zeros(N, W) if is_init[t + 1] else nxt[t]
        torch.testing.assert_close(root[t + 1], expected)
    # the stored trajectory replays exactly in recurrent mode (what the PPO loss will see)
    replay = rollout.exclude("hidden", ("next", "dnc")).clone().unsqueeze(0)  # one trajectory as [1, T]
    with torch.no_grad(), set_recurrent_mode(True):
        replay = module(replay).squeeze(0)
    torch.testing.assert_close(replay["hidden"], rollout["hidden"], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(replay["next", "dnc", "memory"], nxt, atol=1e-5, rtol=1e-5)


def test_collector_auto_registers_primer():
    from torchrl.collectors import Collector

    torch.manual_seed(0)
    module = _module()
    collector = Collector(
        _ToyEnv(episode_len=3),
        _policy(module),
        frames_per_batch=7,
        total_frames=7,
        auto_register_policy_transforms=True,
    )
    try:
        batch = next(iter(collector))
    finally:
        collector.shutdown()
    assert ("dnc", "memory") in batch.keys(include_nested=True)
    root, nxt = batch["dnc", "memory"], batch["next", "dnc", "memory"]
    is_init = batch["is_init"].squeeze(-1)
    for t in range(batch.shape[-1] - 1):
        expected = torch.zeros(N, W) if is_init[t + 1] else nxt[t]
        torch.testing.assert_close(root[t + 1], expected)
