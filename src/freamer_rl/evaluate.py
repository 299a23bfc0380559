"""Evaluate a checkpoint: run N episodes with the saved model and report success, return and length.

:func:`evaluate_any` takes a checkpoint or run directory of any domain and dispatches on the trainer the checkpoint
records (:data:`freamer_rl.trainers.TRAINERS`); :func:`evaluate` is the MiniGrid / gym PPO evaluator.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from freamer_rl.config import ConfigError, config_from_dict
from freamer_rl.errors import CheckpointError
from freamer_rl.checkpoint import load_checkpoint, load_model_state
from freamer_rl.train import build_modules, make_batched_env

logger = logging.getLogger(__name__)


@torch.no_grad()
def evaluate(
    checkpoint: str | Path,
    *,
    episodes: int = 20,
    deterministic: bool = False,
    num_envs: int | None = None,
    seed: int = 12345,
    max_steps: int = 100_000,
) -> dict[str, Any]:
    """Run ``episodes`` complete episodes with the checkpoint's policy (sampling unless ``deterministic``)."""
    path = Path(checkpoint)
    ckpt = load_checkpoint(path)
    try:
        cfg = config_from_dict(ckpt["config"])
    except ConfigError as err:
        raise CheckpointError(f"checkpoint {path} holds a config this version cannot read: {err}") from err
    torch.set_num_threads(cfg.run.threads)
    modules = build_modules(cfg)
    load_model_state(modules, ckpt["model"], path)
    modules.actor_value.eval()
    policy = modules.policy
    n_envs = min(num_envs or cfg.env.num_envs, episodes)
    env = make_batched_env(cfg, modules.primers(), seed, num_envs=n_envs)
    returns: list[float] = []
    lengths: list[int] = []
    successes: list[bool] = []
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    try:
        td = env.reset()
        with set_exploration_type(mode):
            for _ in range(max_steps):
                td = policy(td)
                td, td_next = env.step_and_maybe_reset(td)
                nxt = td["next"]
                done = nxt["done"].reshape(-1)
                for i in done.nonzero().flatten().tolist():
                    returns.append(float(nxt["episode_reward"].reshape(n_envs, -1)[i, 0]))
                    lengths.append(int(nxt["step_count"].reshape(n_envs, -1)[i, 0]))
                    successes.append(bool(nxt["terminated"].reshape(-1)[i]) and float(nxt["reward"].reshape(-1)[i]) > 0)
                td = td_next
                if len(returns) >= episodes:
                    break
    finally:
        env.close()
    returns, lengths, successes = returns[:episodes], lengths[:episodes], successes[:episodes]
    if not returns:
        raise CheckpointError(f"no episode finished within {max_steps} steps")
    return {
        "checkpoint": str(path),
        "env": cfg.env.id,
        "episodes": len(returns),
        "success_rate": sum(successes) / len(successes),
        "return_mean": sum(returns) / len(returns),
        "length_mean": sum(lengths) / len(lengths),
        "deterministic": deterministic,
        "frames_trained": ckpt.get("frames"),
    }


def evaluate_any(checkpoint_or_run: str | Path, **options: Any) -> dict[str, Any]:
    """Evaluate a checkpoint file or a run directory of any domain with its trainer's evaluator (``options``:
    ``episodes``, ``deterministic``, ``num_envs``, ``seed``)."""
    from freamer_rl.trainers import get_trainer, resolve_checkpoint, trainer_of_checkpoint

    path = resolve_checkpoint(checkpoint_or_run)
    return get_trainer(trainer_of_checkpoint(path), str(path)).evaluate(path, **options)
