"""The ``gym`` adapter: gymnasium ids through TorchRL's GymEnv, specs checked, reward history, clear errors."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import SerialEnv
from torchrl.envs.utils import check_env_specs

from freamer_rl.errors import EnvSetupError
from freamer_rl.run import env_registry
from freamer_rl_envs.gym import RewardHistory, make_gym_env


@pytest.mark.parametrize("env_id, reward_history", [("CartPole-v1", 0), ("CartPole-v1", 3), ("Pendulum-v1", 4)])
def test_gym_env_specs(env_id, reward_history):
    env = make_gym_env(env_id, seed=0, reward_history=reward_history)
    check_env_specs(env)
    keys = set(env.observation_spec.keys())
    assert "observation" in keys
    assert ("reward_history" in keys) == bool(reward_history)
    env.close()


def test_cartpole_actions_are_indices_and_pendulum_a_bounded_box():
    cart = make_gym_env("CartPole-v1")
    assert cart.action_spec.shape == () and cart.action_spec.space.n == 2
    pend = make_gym_env("Pendulum-v1")
    assert pend.action_spec.dtype == torch.float32
    assert float(pend.action_spec.space.high) == 2.0


def test_reward_history_rolls_and_resets_per_env():
    env = SerialEnv(2, lambda: make_gym_env("CartPole-v1", reward_history=3))
    env.set_seed(0)
    td = env.rollout(40, break_when_any_done=False)
    hist, nxt = td["reward_history"], td["next", "reward_history"]
    assert torch.equal(hist[:, 0], torch.zeros(2, 3))
    # the newest entry is this step's reward; older ones shift left
    assert torch.equal(nxt[..., -1], td["next", "reward"].squeeze(-1))
    assert torch.equal(nxt[:, :, :-1], hist[:, :, 1:])
    # after an episode ends, the env that restarts begins with zeros
    done = td["next", "done"].squeeze(-1)
    env_i, t = done[:, :-1].nonzero()[0].tolist()
    assert torch.equal(hist[env_i, t + 1], torch.zeros(3))


def test_unknown_gym_id_is_one_line():
    with pytest.raises(EnvSetupError, match=r"unknown gymnasium env id 'CartPol-v1': did you mean 'CartPole-v1'"):
        env_registry.make_env("gym", "CartPol-v1")


def test_reward_history_rejects_bad_length():
    with pytest.raises(ValueError, match="reward_history"):
        RewardHistory(0)
    with pytest.raises(EnvSetupError, match="reward_history"):
        env_registry.make_env("gym", "CartPole-v1", reward_history=-1)


@pytest.mark.parametrize("name", sorted(env_registry.available_adapters()))
def test_every_adapter_declares_options_and_builds(name):
    """Registry test over every installed adapter: its options come from a config, and it builds an env."""
    from freamer_rl.trainers.registry import load_config

    adapter = env_registry.get_adapter(name)
    ids = {"minigrid": "MiniGrid-Empty-5x5-v0", "gym": "CartPole-v1", "health": "pamap2-health"}
    if name not in ids:
        pytest.skip(f"third-party adapter {name}")
    cfg = load_config(None, [f"env.adapter={name}", f"env.id={ids[name]}"])
    options = adapter.options(cfg)
    assert isinstance(options, dict)
    if name == "health":
        options = {**options, "synthetic_duration_s": 120.0}  # keep the synthetic recording small
    env = env_registry.make_env(name, ids[name], seed=0, **options)
    check_env_specs(env)
    env.close()


def test_eval_of_a_gym_run_reports_no_success_rate(tmp_path, capsys):
    """CartPole has no notion of success: eval reports NaN, not MiniGrid's 'terminated with reward > 0' rule."""
    import json
    import math
    from pathlib import Path

    from freamer_rl import cli

    recipe = Path(__file__).resolve().parents[2] / "recipes" / "gym" / "cartpole.yaml"
    run = tmp_path / "run"
    overrides = [
        "env.num_envs=2",
        "ppo.frames_per_batch=64",
        "ppo.minibatch_size=32",
        "ppo.epochs=1",
        "run.total_frames=64",
        "logging.progress_bar=false",
    ]
    assert cli.main(["train", str(recipe), *overrides, "--run-dir", str(run)]) == 0
    capsys.readouterr()
    assert cli.main(["eval", str(run), "--episodes", "4", "--num-envs", "2"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["episodes"] == 4 and math.isnan(result["success_rate"]) and result["return_mean"] > 0
