"""Crafter: the TorchRL adapter (specs, keys, seeding, episode ends, achievements, batched envs) and the official
Crafter score (closed forms, batch updates, resume state, report files).

The env tests need the ``crafter`` package (``pip install -e ".[crafter]"``); the score tests do not. A Crafter reset
generates a whole world (~0.5 s), so every env test keeps to a few resets.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import math
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import EnvCreator, ParallelEnv
from torchrl.envs.utils import check_env_specs

import freamer_rl_envs.crafter as crafter_adapter
from freamer_rl.errors import EnvSetupError
from freamer_rl.model.modalities import check_observation_keys
from freamer_rl.run import env_registry
from freamer_rl.run.crafter_score import CrafterScore, crafter_score
from freamer_rl.trainers.minigrid_ppo import FreamerConfig
from freamer_rl_envs.crafter import (
    ADAPTER,
    CRAFTER_ACHIEVEMENTS,
    CRAFTER_INVENTORY,
    CrafterNotInstalledError,
    make_crafter_env,
)

HAS_CRAFTER = importlib.util.find_spec("crafter") is not None
needs_crafter = pytest.mark.skipif(not HAS_CRAFTER, reason='crafter is not installed: pip install -e ".[crafter]"')
INITIAL_INVENTORY = [9.0, 9.0, 9.0, 9.0] + [0.0] * 12  # health, food, drink, energy, then materials and tools


class ActionList:
    """A policy replaying fixed actions (``[*B]`` each step)."""

    def __init__(self, actions):
        self._actions = iter(actions)

    def __call__(self, td):
        td.set("action", torch.as_tensor(next(self._actions), dtype=torch.int64).expand(td.batch_size).clone())
        return td


def random_actions(n, seed):
    return np.random.default_rng(seed).integers(0, 17, size=n).tolist()


# ------------------------------------------------------------------------------------------------------------------
# the env
# ------------------------------------------------------------------------------------------------------------------
@needs_crafter
def test_specs_keys_shapes_and_reset_values():
    env = make_crafter_env(seed=0, reward_history=4)
    check_env_specs(env)
    assert env.action_spec.space.n == 17 and env.action_spec.shape == ()
    assert set(env.observation_spec.keys()) == {"pixels", "inventory", "achievements", "reward_history"}
    td = env.rollout(3, ActionList(random_actions(3, 0)))
    expected = {
        "pixels": (torch.uint8, (3, 64, 64, 3)),
        "inventory": (torch.float32, (3, 16)),
        "achievements": (torch.bool, (3, 22)),
        "reward_history": (torch.float32, (3, 4)),
    }
    for key, (dtype, shape) in expected.items():
        for k in (key, ("next", key)):
            assert td[k].dtype == dtype and td[k].shape == shape, k
    for key in ("reward", "done", "terminated", "truncated"):
        assert td["next", key].shape == (3, 1)
    # right after a reset: a new player's inventory, nothing unlocked, no past rewards
    assert td["inventory"][0].tolist() == INITIAL_INVENTORY
    assert not td["achievements"][0].any()
    assert torch.equal(td["reward_history"][0], torch.zeros(4))
    assert torch.equal(td["next", "reward_history"][:, -1], td["next", "reward"].squeeze(-1))
    assert td["pixels"].float().std() > 0  # a rendered picture, not a blank buffer
    import crafter

    assert CRAFTER_INVENTORY == tuple(crafter.constants.items) and len(CRAFTER_INVENTORY) == 16
    assert CRAFTER_ACHIEVEMENTS == tuple(crafter.constants.achievements) and len(CRAFTER_ACHIEVEMENTS) == 22
    assert list(CRAFTER_ACHIEVEMENTS) == sorted(CRAFTER_ACHIEVEMENTS)
    env.close()


@needs_crafter
def test_same_seed_and_actions_give_the_same_pixels():
    """World generation and the first steps replay exactly. (From step 10 on crafter itself can diverge between two
    instances: it iterates sets of creatures ordered by memory address, danijar/crafter#36 -- so only 9 steps.)"""
    actions = random_actions(9, 1)
    a = make_crafter_env(seed=3).rollout(9, ActionList(actions))
    b = make_crafter_env(seed=3).rollout(9, ActionList(actions))
    assert torch.equal(a["pixels"], b["pixels"]) and torch.equal(a["next", "pixels"], b["next", "pixels"])
    assert torch.equal(a["next", "inventory"], b["next", "inventory"])
    other = make_crafter_env(seed=4).reset()
    assert not torch.equal(other["pixels"], a["pixels"][0])
    # set_seed seeds the next reset: the same first world again
    env = make_crafter_env(seed=4)
    env.reset()
    env.set_seed(3)
    assert torch.equal(env.reset()["pixels"], a["pixels"][0])


@needs_crafter
def test_unseeded_envs_do_not_share_numpys_global_state():
    """Forked workers share numpy's global random state: unseeded envs must not draw crafter's seed from it."""
    # compared by crafter's own world seed: two different worlds can show the same first frame (a player spawned
    # on open grass sees grass either way), which made a comparison of frames fail now and then
    np.random.seed(0)
    first = make_crafter_env()
    first.reset()
    np.random.seed(0)
    second = make_crafter_env()
    second.reset()
    assert first._env._seed != second._env._seed


@needs_crafter
def test_length_limit_truncates():
    env = make_crafter_env("CrafterNoReward-v1", seed=0, length=4, reward_history=0, size=(72, 64))
    check_env_specs(env)
    td = env.rollout(9, ActionList(random_actions(9, 2)), break_when_any_done=False)
    assert td["pixels"].shape == (9, 64, 72, 3)  # size is crafter's (width, height)
    ends = td["next", "done"].squeeze(-1)
    assert ends.nonzero().squeeze(-1).tolist() == [3, 7]
    assert torch.equal(td["next", "truncated"].squeeze(-1), ends)
    assert not td["next", "terminated"].any()
    assert not td["next", "reward"].any()  # CrafterNoReward-v1 pays nothing
    assert td["inventory"][4].tolist() == INITIAL_INVENTORY  # auto-reset after the limit
    assert "reward_history" not in td.keys()


@needs_crafter
def test_death_terminates_and_achievements_accumulate_then_reset():
    env = make_crafter_env(seed=1, length=10000)
    policy = ActionList(random_actions(3 * 1500, 1))
    # a random episode unlocks something ~95% of the time (wake_up, collect_sapling, ...); crafter may diverge from
    # step 10 on (danijar/crafter#36), so allow a few episodes instead of relying on one trajectory
    for _ in range(3):
        td = env.rollout(1500, policy)  # resets first, stops at the episode's end
        nxt = td["next"]
        assert nxt["done"][-1].item() and nxt["terminated"][-1].item() and not nxt["truncated"][-1].item()
        assert not nxt["done"][:-1].any()
        assert nxt["inventory"][-1, CRAFTER_INVENTORY.index("health")] == 0  # death = health 0
        ach = nxt["achievements"]
        assert not td["achievements"][0].any()  # a new episode starts with nothing
        # achieved-so-far never forgets within the episode; each new one pays +1 minus the step's health loss (< 1)
        assert (ach[1:] >= ach[:-1]).all()
        count = ach.sum(-1)
        new = count > torch.cat([torch.zeros(1, dtype=count.dtype), count[:-1]])
        assert (nxt["reward"].squeeze(-1)[new] > 0).all()
        assert torch.equal(td["achievements"][1:], ach[:-1])  # the root of step t+1 is the next of step t
        if ach[-1].any():
            break
    else:
        pytest.fail("three random episodes unlocked no achievement")
    again = env.reset()
    assert not again["achievements"].any() and again["inventory"].tolist() == INITIAL_INVENTORY


@needs_crafter
@pytest.mark.parametrize("start_method", ["fork", pytest.param("spawn", marks=pytest.mark.slow)])
def test_parallel_env(start_method):
    fn = functools.partial(make_crafter_env, "CrafterReward-v1", reward_history=4)
    env = ParallelEnv(2, EnvCreator(fn), mp_start_method=start_method)
    try:
        env.set_seed(0)
        td = env.rollout(3, ActionList(random_actions(3, 0)), break_when_any_done=False)
        assert td.batch_size == (2, 3)
        assert td["pixels"].shape == (2, 3, 64, 64, 3) and td["next", "achievements"].shape == (2, 3, 22)
        assert not torch.equal(td["pixels"][0, 0], td["pixels"][1, 0])  # each worker got its own seed
    finally:
        env.close()


# ------------------------------------------------------------------------------------------------------------------
# adapter and errors
# ------------------------------------------------------------------------------------------------------------------
def test_adapter_options_and_no_success():
    cfg = FreamerConfig()
    cfg.env.reward_history = 5
    assert ADAPTER.options(cfg) == {"reward_history": 5, "reset_workers": 0}
    assert ADAPTER.success is None and ADAPTER.make_env is make_crafter_env


@needs_crafter
def test_observations_fit_the_model_modalities():
    """Pixels feed the vision modality, the inventory the vector one (no world is generated: specs only)."""
    cfg = FreamerConfig()
    cfg.model.modalities = ["vision", "vector", "reward"]
    cfg.model.observation_keys = {"vector": ["inventory"]}
    check_observation_keys(make_crafter_env().observation_spec, cfg.model, "Crafter")


def test_entry_point(monkeypatch):
    """pyproject declares ``crafter = freamer_rl_envs.crafter:ADAPTER``; the registry resolves it (through the
    installed metadata once the project is reinstalled; before that, through the declared entry point itself)."""
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    target = pyproject["project"]["entry-points"][env_registry.ENTRY_POINT_GROUP]["crafter"]
    assert target == "freamer_rl_envs.crafter:ADAPTER"
    installed = env_registry.available_adapters()
    if "crafter" not in installed:  # metadata from before the entry point was added: pip install -e . refreshes it
        declared = EntryPoint(name="crafter", value=target, group=env_registry.ENTRY_POINT_GROUP)
        monkeypatch.setattr(env_registry, "available_adapters", lambda: {**installed, "crafter": declared})
    assert env_registry.get_adapter("crafter") is ADAPTER
    if HAS_CRAFTER:
        with pytest.raises(EnvSetupError, match=r"env.id 'Crafter-v9' \(crafter adapter\): unknown Crafter env id"):
            env_registry.make_env("crafter", "Crafter-v9")


def test_missing_crafter_is_one_friendly_line(monkeypatch):
    monkeypatch.setattr(crafter_adapter, "crafter", None)
    monkeypatch.setattr(crafter_adapter, "_CRAFTER_IMPORT_ERROR", "ModuleNotFoundError: No module named 'crafter'")
    with pytest.raises(CrafterNotInstalledError) as err:
        make_crafter_env()
    assert isinstance(err.value, ImportError) and isinstance(err.value, EnvSetupError)
    msg = str(err.value)
    assert "\n" not in msg and 'pip install -e ".[crafter]"' in msg and "No module named 'crafter'" in msg


@needs_crafter
def test_bad_ids_and_options():
    with pytest.raises(ValueError, match=r"unknown Crafter env id 'CrafterReward-v2': did you mean 'CrafterReward-v1'"):
        make_crafter_env("CrafterReward-v2")
    with pytest.raises(ValueError, match="reward_history"):
        make_crafter_env(reward_history=-1)
    with pytest.raises(ValueError, match="length"):
        make_crafter_env(length=0)


# ------------------------------------------------------------------------------------------------------------------
# the Crafter score
# ------------------------------------------------------------------------------------------------------------------
def test_score_closed_forms():
    assert crafter_score([0.0] * 22) == 0.0
    assert crafter_score([100.0] * 22) == pytest.approx(100.0)
    assert crafter_score([100.0] + [0.0] * 21) == pytest.approx(101 ** (1 / 22) - 1)  # 0.2334
    # by hand: exp((ln 11 + ln 51 + ln 1) / 3) - 1 = 561 ** (1/3) - 1 = 7.2475
    assert crafter_score([10.0, 50.0, 0.0]) == pytest.approx(7.24747, abs=1e-4)
    assert crafter_score([10.0, math.nan, 50.0, 0.0]) == pytest.approx(7.24747, abs=1e-4)  # nanmean
    assert math.isnan(crafter_score([math.nan, math.nan]))
    with pytest.raises(ValueError, match=r"percentages in \[0, 100\]"):
        crafter_score([120.0])


def _batch(done, ach):
    return TensorDict({"next": {"done": done, "achievements": ach}}, batch_size=done.shape[:-1])


def test_update_counts_only_finished_episodes():
    names = ("a", "b", "c")
    done = torch.zeros(2, 4, 1, dtype=torch.bool)
    ach = torch.zeros(2, 4, 3, dtype=torch.bool)
    ach[0, 0:2, 0] = True  # env 0: unlocks a, its episode ends at t=1 ...
    done[0, 1] = True
    ach[0, 3, 1] = True  # ... then a new episode unlocks b but has not ended: not counted yet
    ach[1, 1:, 0] = True  # env 1: unlocks a, later c, ends at t=3
    ach[1, 2:, 2] = True
    done[1, 3] = True
    score = CrafterScore(names)
    assert math.isnan(score.score()) and math.isnan(score.success_rates()["a"])
    assert score.update(_batch(done, ach)) == 2
    assert score.episodes == 2 and score.unlocked == [2, 0, 1]
    assert score.success_rates() == {"a": 100.0, "b": 0.0, "c": 50.0}
    assert score.score() == pytest.approx((101 * 51) ** (1 / 3) - 1)
    # counts instead of flags, done without its trailing 1: same result
    again = CrafterScore(names)
    again.update(_batch(done.squeeze(-1)[..., None], ach.to(torch.int64) * 3))
    assert again.unlocked == [2, 0, 1]


@pytest.mark.parametrize("batch", [(), (2,), (3, 2)])
def test_update_any_batch_shape(batch):
    gen = torch.Generator().manual_seed(0)
    T, A = 7, 5
    done = torch.rand(*batch, T, 1, generator=gen) < 0.4
    ach = torch.rand(*batch, T, A, generator=gen) < 0.3
    score = CrafterScore([f"x{i}" for i in range(A)])
    n = score.update(_batch(done, ach))
    flat_done, flat_ach = done.reshape(-1), ach.reshape(-1, A)
    assert n == score.episodes == int(flat_done.sum())
    assert score.unlocked == [int(flat_ach[flat_done, i].sum()) for i in range(A)]


def test_update_rejects_bad_batches():
    score = CrafterScore(["a", "b"])
    with pytest.raises(ValueError, match=r"expected \[\.\.\., 2\]"):
        score.update(_batch(torch.zeros(4, 1, dtype=torch.bool), torch.zeros(4, 3, dtype=torch.bool)))
    with pytest.raises(KeyError, match="achievements"):
        score.update(TensorDict({"next": {"done": torch.zeros(4, 1, dtype=torch.bool)}}, batch_size=[4]))
    with pytest.raises(ValueError, match="duplicate"):
        CrafterScore(["a", "a"])


def test_state_dict_round_trip(tmp_path):
    score = CrafterScore(CRAFTER_ACHIEVEMENTS)
    done = torch.tensor([[False], [True], [True]])
    ach = torch.zeros(3, 22, dtype=torch.bool)
    ach[1:, 0] = True
    ach[2, 5] = True
    score.update(_batch(done, ach))
    state = score.state_dict()
    json.dumps(state)  # plain types only
    torch.save(state, tmp_path / "s.pt")
    loaded = torch.load(tmp_path / "s.pt", weights_only=True)
    restored = CrafterScore(CRAFTER_ACHIEVEMENTS)
    restored.load_state_dict(loaded)
    assert restored.success_rates() == score.success_rates() and restored.score() == score.score()
    with pytest.raises(ValueError, match="saved for achievements"):
        CrafterScore(["a"]).load_state_dict(state)


@pytest.mark.parametrize("log_scale", [True, False])
def test_write_report(tmp_path, log_scale):
    score = CrafterScore(CRAFTER_ACHIEVEMENTS)
    ach = torch.zeros(4, 22, dtype=torch.bool)
    ach[:, CRAFTER_ACHIEVEMENTS.index("collect_wood")] = True
    ach[:2, CRAFTER_ACHIEVEMENTS.index("wake_up")] = True
    score.update(_batch(torch.ones(4, 1, dtype=torch.bool), ach))
    paths = score.write_report(tmp_path, log_scale=log_scale)
    assert {p.name for p in paths.values()} == {
        "crafter_score.json",
        "crafter_achievements.md",
        "crafter_achievements.png",
    }
    data = json.loads(paths["json"].read_text())
    assert data["episodes"] == 4 and data["score"] == pytest.approx(score.score())
    assert data["success_rates_percent"]["collect_wood"] == 100.0 and data["success_rates_percent"]["wake_up"] == 50.0
    md = paths["md"].read_text()
    assert f"**{score.score():.2f}**" in md
    assert "| collect_wood | 4 | 100.00 |" in md and "| wake_up | 2 | 50.00 |" in md
    assert paths["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths.values())  # no temporaries


def test_write_report_before_any_episode(tmp_path):
    paths = CrafterScore(["a", "b"]).write_report(tmp_path)
    data = json.loads(paths["json"].read_text())
    assert data["score"] is None and data["episodes"] == 0 and data["success_rates_percent"]["a"] is None
    assert "n/a" in paths["md"].read_text()
