"""Smoke tests of the benchmark harness (tiny budgets; the real figures come from the benchmark commands)."""

import sys
from pathlib import Path

from torchrl.data import Categorical

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import minigrid_benchmark  # noqa: E402
from ppo_mlp_baseline import make_flat_env  # noqa: E402


def test_baseline_env_takes_integer_actions():
    """GymWrapper defaults to one-hot actions; an integer Categorical policy then always turns left."""
    env = make_flat_env("MiniGrid-MultiRoom-N2-S4-v0", seed=0)
    assert isinstance(env.action_spec, Categorical)
    rollout = env.rollout(30)
    assert rollout["action"].unique().numel() > 1
    env.close()


def test_benchmark_harness_writes_report(tmp_path):
    minigrid_benchmark.main(
        ["--frames", "512", "--seeds", "0", "--workers", "1", "--out", str(tmp_path),
         "env.num_envs=2", "ppo.frames_per_batch=256", "ppo.minibatch_size=128", "ppo.epochs=1"]
    )
    text = (tmp_path / "results.md").read_text()
    assert "FreamerV1" in text and "PPO-MLP" in text and "Throughput ratio" in text
    assert (tmp_path / "learning_curves.png").is_file()
    assert (tmp_path / "results.csv").read_text().count("\n") == 3
