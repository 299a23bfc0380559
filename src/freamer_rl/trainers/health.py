"""``trainer: health``: the wearable-health domain (:mod:`freamer_rl.health`) as an entry of the trainer registry:
RSSM world model on real-env collection, imagination PPO, real-env evaluation."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from freamer_rl.health.agent import build_agent, parameter_table
from freamer_rl.health.config import HealthConfig
from freamer_rl.health.evaluation import evaluate_checkpoint
from freamer_rl.health.trainer import run_health

__all__ = ["HealthConfig", "STRUCTURAL", "train", "evaluate", "params"]

#: config sections that shape the health agent's weights (a resume needs them equal)
STRUCTURAL = ("env", "encoder", "world_model", "imagination.policy_hidden")


def train(cfg: HealthConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    return run_health(cfg, run_dir, resume=resume, structural=STRUCTURAL)


def evaluate(path: str | Path, *, corrupt: list | None = None, **options: Any) -> dict[str, Any]:
    """``freamer-rl eval`` of a health run; ``corrupt`` (``--corrupt imu[0:12]:gaussian:1.0``) corrupts the real
    env's observations the agent reads (:func:`freamer_rl.health.evaluation.corruption_for`)."""
    return evaluate_checkpoint(path, corrupt=corrupt, **options)


def params(cfg: HealthConfig) -> list[dict]:
    return parameter_table(build_agent(cfg))
