"""shaping.return_norm: the reward PPO trains on divided by a running std of its discounted return
(freamer_rl.machinery.return_norm), closed-form on small batches and inside every collector-based trainer."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from freamer_rl.errors import ConfigError
from freamer_rl.machinery.return_norm import CLIP, ReturnNormalizer
from freamer_rl.machinery.shaping import RewardShaper
from freamer_rl.run.checkpoint import latest_checkpoint
from freamer_rl.trainers.baselines.ppo_baseline import PPOBaselineTrainer
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config, load_recipe

ROOT = Path(__file__).resolve().parents[2]
GAMMA = 0.9


def _hand_returns(rewards: list[list[float]], dones: list[list[bool]], carry: list[float]) -> list[list[float]]:
    out = []
    for row, ends, g in zip(rewards, dones, carry):
        got = []
        for r, d in zip(row, ends):
            g = GAMMA * g + r
            got.append(g)
            g = 0.0 if d else g
        out.append(got)
    return out


def _batch(rewards, dones):
    return torch.tensor(rewards).unsqueeze(-1), torch.tensor(dones).unsqueeze(-1)


REWARDS = [[1.0, 0.0, 2.0, 0.5], [0.0, 3.0, 0.0, 1.0]]
DONES = [[False, True, False, False], [False, False, False, True]]


@pytest.mark.parametrize("batch_shape", [(2,), (1, 2)])
def test_rewards_are_divided_by_the_std_of_the_discounted_returns(batch_shape):
    reward, done = _batch(REWARDS, DONES)
    reward, done = reward.reshape(*batch_shape, 4, 1), done.reshape(*batch_shape, 4, 1)
    norm = ReturnNormalizer(GAMMA)
    out = norm(reward, done)
    want = torch.tensor(_hand_returns(REWARDS, DONES, [0.0, 0.0]), dtype=torch.float64)
    std = want.flatten().var(unbiased=False).sqrt()
    assert out.shape == reward.shape and out.dtype == reward.dtype
    assert torch.allclose(out, (reward / std).float())
    assert float(norm.count) == 8 and float(norm.mean) == pytest.approx(float(want.mean()))
    assert float(norm.diagnostics()["return_scale"]) == pytest.approx(float(1 / std))
    assert int(norm.diagnostics()["return_norm_clipped"]) == 0


def test_returns_and_statistics_carry_across_batches():
    """Two half batches give the returns and moments of the whole batch (the open episodes carry over)."""
    reward, done = _batch(REWARDS, DONES)
    whole = ReturnNormalizer(GAMMA)
    whole(reward, done)
    halves = ReturnNormalizer(GAMMA)
    halves(reward[:, :2], done[:, :2])
    assert halves.carry.tolist() == pytest.approx([0.0, 3.0])  # row 0 ended at step 1; row 1 open: 0.9 * 0 + 3
    halves(reward[:, 2:], done[:, 2:])
    for name in ("count", "mean", "var"):
        assert float(getattr(halves, name)) == pytest.approx(float(getattr(whole, name))), name
    assert halves.carry.tolist() == pytest.approx(whole.carry.tolist())


def test_a_first_sparse_reward_is_clipped_and_counted():
    """All-zero returns so far: the std is at its floor, and the one reward is clipped to CLIP and counted."""
    reward = torch.zeros(3, 5, 1)
    reward[1, 4] = 1e-2  # one rare reward
    done = torch.zeros(3, 5, 1, dtype=torch.bool)
    norm = ReturnNormalizer(GAMMA, floor=1e-4)
    norm(torch.zeros(3, 5, 1), done)  # nothing yet: std 0, divided by the floor
    assert float(norm.diagnostics()["return_scale"]) == pytest.approx(1e4)
    norm.count = torch.tensor(1e9, dtype=torch.float64)  # a long run of zero returns: one batch barely moves the std
    out = norm(reward, done)
    assert float(out[1, 4]) == CLIP and int(norm.diagnostics()["return_norm_clipped"]) == 1
    assert out.abs().sum() == CLIP  # every other step stays 0


def test_the_floor_caps_the_factor_so_goal_rewards_keep_their_size():
    """A sparse goal reward: with a floor of 1e-4 the factor is ~1e4 and the goal is clipped to CLIP; with the default
    floor 0.1 (shaping.return_norm_floor) the factor is at most 10 and the goal keeps its size, x 10."""
    reward = torch.zeros(4, 8, 1)
    reward[2, 7] = 0.7
    done = torch.zeros(4, 8, 1, dtype=torch.bool)
    small, capped = ReturnNormalizer(GAMMA, floor=1e-4), ReturnNormalizer(GAMMA)
    assert capped.floor == 0.1
    for norm in (small, capped):
        norm(torch.zeros(4, 8, 1), done)
        norm.count = torch.tensor(1e6, dtype=torch.float64)
    assert float(small(reward, done)[2, 7]) == CLIP and int(small.diagnostics()["return_norm_clipped"]) == 1
    assert (
        float(capped(reward, done)[2, 7]) == pytest.approx(7.0)
        and int(capped.diagnostics()["return_norm_clipped"]) == 0
    )
    assert float(capped.diagnostics()["return_scale"]) == pytest.approx(10.0)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="floor must be a finite number > 0"):
            ReturnNormalizer(GAMMA, floor=bad)


def test_state_round_trip_resumes_the_same_scale():
    reward, done = _batch(REWARDS, DONES)
    going = ReturnNormalizer(GAMMA)
    going(reward[:, :2], done[:, :2])
    resumed = ReturnNormalizer(GAMMA)
    resumed.load_state(going.state())
    assert torch.equal(resumed(reward[:, 2:], done[:, 2:]), going(reward[:, 2:], done[:, 2:]))
    with pytest.raises(ValueError, match="'var' missing"):
        resumed.load_state({"count": going.count, "mean": going.mean, "carry": going.carry})
    with pytest.raises(ValueError, match="gamma must be in"):
        ReturnNormalizer(0.0)


@pytest.mark.parametrize(
    "recipe", ["gym/cartpole.yaml", "baselines/ppo_mlp_cartpole.yaml", "baselines/impala_n2s4.yaml"]
)
def test_return_norm_turns_the_shaper_on_for_every_collector_trainer(recipe):
    _, cfg = load_recipe(ROOT / "recipes" / recipe, ["shaping.return_norm=true"])
    gamma = cfg.impala.gamma if hasattr(cfg, "impala") else cfg.ppo.gamma
    shaper = RewardShaper(cfg, [], 0, 0, torch.device("cpu"), gamma=gamma)
    assert shaper.active and shaper.return_norm is not None and shaper.return_norm.gamma == gamma
    reward = torch.full((2, 3, 1), 10.0)  # returns spread above the floor even after CartPole's x 0.05
    td = TensorDict({"next": {"reward": reward, "done": torch.zeros(2, 3, 1, dtype=torch.bool)}}, [2, 3])
    td["next", "terminated"] = td["next", "done"].clone()
    logs = shaper(td, 0.0)
    returns = 10 * torch.tensor([1.0, 1 + gamma, 1 + gamma + gamma**2] * 2, dtype=torch.float64)
    scale = float(1 / returns.var(unbiased=False).sqrt())
    assert torch.allclose(td["next", "shaped_reward"], torch.full((2, 3, 1), 10 * scale))
    # the normaliser sees the reward after shaping.reward_scale (CartPole's recipe: 0.05), so whatever that scale,
    # the critic's targets come out the same
    assert logs["return_scale"] == pytest.approx(scale / cfg.shaping.reward_scale)
    assert logs["return_norm_clipped"] == 0
    assert td["next", "reward"].eq(10).all()  # the logged reward stays the env's
    with pytest.raises(ValueError, match="shaping.return_norm: this trainer gives"):
        RewardShaper(cfg, [], 0, 0, torch.device("cpu"))
    with pytest.raises(ConfigError, match="shaping.return_norm"):
        load_recipe(ROOT / "recipes" / recipe, ["shaping.return_norm=3"])
    with pytest.raises(ConfigError, match="shaping.return_norm_floor"):
        load_recipe(ROOT / "recipes" / recipe, ["shaping.return_norm_floor=0"])
    floored = load_recipe(ROOT / "recipes" / recipe, ["shaping.return_norm=true", "shaping.return_norm_floor=0.1"])[1]
    assert RewardShaper(floored, [], 0, 0, torch.device("cpu"), gamma=gamma).return_norm.floor == 0.1


SMALL_GYM = ["env.num_envs=2", "ppo.frames_per_batch=128", "ppo.minibatch_size=64"]


@pytest.mark.parametrize(
    "recipe, trainer_class, sizes",
    [("tiny.yaml", Trainer, []), ("baselines/ppo_mlp_cartpole.yaml", PPOBaselineTrainer, SMALL_GYM)],
)
def test_a_run_trains_on_normalised_rewards_and_resumes_their_scale(recipe, trainer_class, sizes, tmp_path):
    """Two batches with return_norm on: progress.csv logs the scale, the checkpoint holds the statistics, and a
    resumed trainer starts from them and trains a third batch."""
    path = ROOT / "recipes" / recipe
    common = ["shaping.return_norm=true", "logging.checkpoint_every_frames=128", *sizes]
    cfg = load_config(path, [*common, "run.total_frames=256"])
    torch.manual_seed(0)
    trainer = trainer_class(cfg, tmp_path / "run")
    trainer.train()
    with open(tmp_path / "run" / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    scales = [float(r["return_scale"]) for r in rows]
    assert len(rows) == 2 and all(s > 0 for s in scales)
    saved = torch.load(latest_checkpoint(tmp_path / "run"), weights_only=True)["shaping"]["return_norm"]
    assert float(saved["count"]) == 2 * trainer.frames_per_batch
    shutil.copytree(tmp_path / "run", tmp_path / "again")
    cfg3 = load_config(path, [*common, "run.total_frames=384"])
    again = trainer_class(cfg3, tmp_path / "again")
    assert float(again.shaper.return_norm.count) == float(saved["count"])
    assert torch.equal(again.shaper.return_norm.carry, saved["carry"])
    again.train()
    assert float(again.shaper.return_norm.count) == 3 * trainer.frames_per_batch
