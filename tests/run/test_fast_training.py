"""The trainer's fast paths: the batched MiniGrid env, values of next states from the root pass, compiled layers."""

from __future__ import annotations

import csv
import functools
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import SerialEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import set_recurrent_mode

from freamer_rl.layers.dnc import DNCModule
from freamer_rl.layers.fno import StateFNOEncoder
from freamer_rl.run import env_registry
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config
from freamer_rl_envs.minigrid import make_minigrid_env
from freamer_rl_envs.minigrid_vec import MiniGridVecEnv

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
ENV_ID = "MiniGrid-MultiRoom-N2-S4-v0"


# ---------------------------------------------------------------------------------------------------------------
# MiniGridVecEnv
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("pixels", [False, True])
def test_vec_env_specs(pixels):
    env = MiniGridVecEnv("MiniGrid-Empty-5x5-v0", 3, pixels=pixels)
    check_env_specs(env, seed=0)
    assert env.batch_size == (3,)
    env.close()


def test_vec_env_gives_the_serial_env_data(scripted_rollout):
    """Same seed, same actions -> the same observations, rewards and ends as SerialEnv of single envs, through
    episode ends and partial resets."""
    n, steps = 4, 120
    serial = SerialEnv(n, functools.partial(make_minigrid_env, ENV_ID, include_mission=False))
    vec = MiniGridVecEnv(ENV_ID, n)
    gen = torch.Generator().manual_seed(0)
    actions = torch.randint(0, 3, (steps, n), generator=gen)  # turn / move: episodes end by truncation or goal
    a, b = (scripted_rollout(env, actions, seed=7) for env in (serial, vec))
    assert bool(a["next", "done"].any())  # the comparison crossed episode ends
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a[key], b[key]), key


def test_vec_env_refuses_options_it_cannot_serve():
    with pytest.raises(ValueError, match="include_mission=True"):
        MiniGridVecEnv(ENV_ID, 2, include_mission=True)
    with pytest.raises(ValueError, match="num_envs"):
        MiniGridVecEnv(ENV_ID, 0)


@pytest.mark.parametrize("name", sorted(env_registry.available_adapters()))
def test_batched_env_of_every_adapter_matches_its_single_env_specs(name):
    adapter = env_registry.get_adapter(name)
    if adapter.make_batched_env is None:
        pytest.skip(f"adapter {name!r} has no batched env (the trainer uses SerialEnv)")
    cfg = load_config(TINY, [])
    options = adapter.options(cfg)
    env_id = cfg.env.id
    if name == "health":  # its own ids; a short synthetic recording keeps the test fast
        env_id, options = "pamap2-health", {**options, "synthetic_duration_s": 120.0}
    single = adapter.make_env(env_id, **options)
    batched = adapter.make_batched_env(env_id, 2, **options)
    assert batched.batch_size == (2,)
    assert batched.observation_spec == single.observation_spec.expand(2, *single.observation_spec.shape)
    assert batched.action_spec == single.action_spec.expand(2, *single.action_spec.shape)
    check_env_specs(batched, seed=0)
    single.close()
    batched.close()


# ---------------------------------------------------------------------------------------------------------------
# values of next states
# ---------------------------------------------------------------------------------------------------------------
def test_next_values_from_root_pass_equal_a_full_next_pass(tmp_path):
    cfg = load_config(TINY, ["env.id=MiniGrid-Empty-5x5-v0", "ppo.frames_per_batch=256", "run.total_frames=256"])
    trainer = Trainer(cfg, tmp_path / "run", resume=False)
    data = trainer.collect_batch()
    assert bool(data["next", "done"].any())  # episode ends inside the batch (their next value is computed)
    fast = trainer.compute_advantage(data.clone())
    value = trainer.modules.value
    keys = [k for k in value.in_keys if k != "is_init"]
    with torch.no_grad():
        nxt = data["next"].select(*keys, strict=False)
        nxt.set("is_init", torch.zeros_like(data["is_init"]))
        ref_next = value(nxt)["state_value"]
        ref = data.clone()
        ref.set("state_value", value(data.select(*keys, "is_init", strict=False))["state_value"])
        ref.set(("next", "state_value"), ref_next)
        ref = trainer.gae(ref)
    torch.testing.assert_close(fast["next", "state_value"], ref_next, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fast["advantage"], ref["advantage"], rtol=1e-5, atol=1e-5)
    trainer.life.lock.release()


# ---------------------------------------------------------------------------------------------------------------
# compiled layers (model.compile) against eager
# ---------------------------------------------------------------------------------------------------------------
def _grads(module, loss):
    params = [p for p in module.parameters() if p.requires_grad]
    return torch.autograd.grad(loss, params, allow_unused=True)


def test_compiled_dnc_matches_eager_in_both_modes():
    torch.manual_seed(0)
    eager = DNCModule(16, 8, 8)
    fast = DNCModule(16, 8, 8, compile=True)
    fast.load_state_dict(eager.state_dict())
    b, t = 3, 3  # short: compiling dominates the time, and t = 3 still has a reset inside a row
    td = TensorDict(
        {
            "fused": 3 * torch.randn(b, t, 16),
            ("dnc", "memory"): torch.randn(b, t, 8, 8),
            "is_init": torch.zeros(b, t, 1, dtype=torch.bool),
        },
        [b, t],
    )
    td["is_init"][1, 1] = True
    outs = []
    for m in (eager, fast):
        with set_recurrent_mode(True):
            out = m(td.clone())
        loss = out["hidden"].pow(2).sum() + out["next", "dnc", "memory"].sum()
        outs.append((out["hidden"], out["next", "dnc", "memory"], _grads(m, loss)))
        step = m(td[:, 0].clone())  # step mode
        outs[-1] += (step["hidden"], step["next", "dnc", "memory"])
    (h0, m0, g0, s0, sm0), (h1, m1, g1, s1, sm1) = outs
    for a, c in [(h0, h1), (m0, m1), (s0, s1), (sm0, sm1), *zip(g0, g1)]:
        torch.testing.assert_close(a, c, rtol=1e-4, atol=1e-5)
    assert fast.compile_fallbacks == 0


def _saturating(module: DNCModule) -> DNCModule:
    """No erase, full gate, write vector ~ +1: every step adds ~1/N to every slot until the clamp holds it."""
    w = module.dnc.memory_width
    with torch.no_grad():
        module.dnc.interface.weight.zero_()
        bias = module.dnc.interface.bias.view(-1)
        bias.zero_()
        bias[w + 1 : 2 * w + 1] = -30.0  # erase logits
        bias[2 * w + 1 : 3 * w + 1] = 30.0  # write-vector pre-tanh
        bias[3 * w + 1] = 30.0  # gate logit
    return module


def test_compiled_dnc_counts_clamps_like_the_eager_step():
    """One count per sequence (compiled loop) equals the per-step count of DNCMemory.step."""
    t = 12
    x = torch.randn(1, t, 4)
    reference = _saturating(DNCModule(4, 2, 3, memory_clip=1.5)).dnc
    mem = reference.initial_memory((1,))
    with torch.no_grad():
        for i in range(t):
            _, mem = reference.step(x[:, i], mem)
    fast = _saturating(DNCModule(4, 2, 3, memory_clip=1.5, compile=True))
    td = TensorDict(
        {"fused": x, ("dnc", "memory"): torch.zeros(1, t, 2, 3), "is_init": torch.zeros(1, t, 1, dtype=torch.bool)},
        [1, t],
    )
    with set_recurrent_mode(True), torch.no_grad():
        out = fast(td)
    torch.testing.assert_close(out["next", "dnc", "memory"][:, -1], mem)
    assert reference.clip_events > 0 and fast.dnc.clip_events == reference.clip_events


@pytest.mark.parametrize("batch", [(6,), (2, 3)])
def test_compiled_state_encoder_matches_eager(batch):
    torch.manual_seed(0)
    grid = torch.stack(
        [
            torch.randint(0, 11, (*batch, 7, 7)),
            torch.randint(0, 6, (*batch, 7, 7)),
            torch.randint(0, 3, (*batch, 7, 7)),
        ],
        dim=-1,
    )
    direction = torch.randint(0, 4, batch)
    eager, fast = StateFNOEncoder(16, 8, 6), StateFNOEncoder(16, 8, 6, compile=True)
    fast.load_state_dict(eager.state_dict())
    a, b = eager(grid, direction), fast(grid, direction)
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    for ga, gb in zip(_grads(eager, a.pow(2).sum()), _grads(fast, b.pow(2).sum())):
        if ga is not None:
            torch.testing.assert_close(ga, gb, rtol=1e-4, atol=1e-5)
    assert fast.compile_fallbacks == 0


def test_trainer_with_compile_trains_and_logs_no_fallback(tmp_path):
    cfg = load_config(TINY, ["model.compile=true"])
    summary = Trainer(cfg, tmp_path / "run", resume=False).train()
    assert summary["frames"] == cfg.run.total_frames and summary["compile_fallbacks"] == 0
    rows = list(csv.DictReader((tmp_path / "run" / "progress.csv").open()))
    assert len(rows) == 2 and all(r["compile_fallbacks"] == "0" for r in rows)
    assert all(float(r["loss_total"]) == float(r["loss_total"]) for r in rows)  # finite, not NaN
