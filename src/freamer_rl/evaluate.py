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

from freamer_rl import env_registry
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
    ckpt, cfg = read_checkpoint_config(path)
    torch.set_num_threads(cfg.run.threads)
    modules = build_modules(cfg)
    load_model_state(modules, ckpt["model"], path)
    modules.actor_value.eval()
    result = run_episodes(cfg, modules.policy, modules.primers(), episodes=episodes, deterministic=deterministic,
                          num_envs=num_envs, seed=seed, max_steps=max_steps)  # fmt: skip
    return {"checkpoint": str(path), **result, "frames_trained": ckpt.get("frames")}


def read_checkpoint_config(path: Path, schema: type | None = None) -> tuple[dict[str, Any], Any]:
    """A checkpoint (read with ``weights_only``) and its config built with ``schema`` (default FreamerConfig)."""
    ckpt = load_checkpoint(path)
    try:
        cfg = config_from_dict(ckpt["config"], schema)
    except ConfigError as err:
        raise CheckpointError(f"checkpoint {path} holds a config this version cannot read: {err}") from err
    return ckpt, cfg


@torch.no_grad()
def run_episodes(cfg: Any, policy: Any, primers: list, *, episodes: int = 20, deterministic: bool = False,
                 num_envs: int | None = None, seed: int = 12345, max_steps: int = 100_000) -> dict[str, Any]:
    """``episodes`` complete episodes of ``policy`` in the config's env (every trainer's evaluator uses this)."""
    n_envs = min(num_envs or cfg.env.num_envs, episodes)
    env = make_batched_env(cfg, primers, seed, num_envs=n_envs)
    success_fn = env_registry.get_adapter(cfg.env.adapter).success
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    try:
        with set_exploration_type(mode):
            per_env = _episodes_per_env(env, policy, n_envs, -(-episodes // n_envs), success_fn, max_steps)
    finally:
        env.close()
    # episode k of every env before episode k + 1 of any: choosing by finishing order would favour short episodes
    chosen = [eps[k] for k in range(max(map(len, per_env))) for eps in per_env if k < len(eps)][:episodes]
    if not chosen:
        raise CheckpointError(f"no episode finished within {max_steps} steps")
    succ = [e["success"] for e in chosen if e["success"] is not None]
    return {
        "env": cfg.env.id,
        "episodes": len(chosen),
        # NaN when the env has no notion of success (e.g. CartPole): see EnvAdapter.success
        "success_rate": sum(succ) / len(succ) if succ else float("nan"),
        "return_mean": sum(e["return"] for e in chosen) / len(chosen),
        "length_mean": sum(e["length"] for e in chosen) / len(chosen),
        "deterministic": deterministic,
    }


def _episodes_per_env(env, policy, n_envs: int, quota: int, success_fn, max_steps: int) -> list[list[dict]]:
    """The first ``quota`` episodes of each of the ``n_envs`` envs: ``{"return", "length", "success"}`` each
    (``success`` None without a success rule)."""
    per_env: list[list[dict]] = [[] for _ in range(n_envs)]
    td = env.reset()
    for _ in range(max_steps):
        td = policy(td)
        td, td_next = env.step_and_maybe_reset(td)
        nxt = td["next"].reshape(n_envs)
        done = nxt["done"].reshape(n_envs)
        if done.any():
            ended = done.nonzero().flatten().tolist()
            succ = success_fn(nxt[done]).reshape(-1).tolist() if success_fn is not None else [None] * len(ended)
            for j, i in enumerate(ended):
                if len(per_env[i]) < quota:
                    per_env[i].append({"return": float(nxt["episode_reward"][i].reshape(-1)[0]),
                                       "length": int(nxt["step_count"][i].reshape(-1)[0]), "success": succ[j]})
        td = td_next
        if all(len(e) >= quota for e in per_env):
            break
    return per_env


def evaluate_any(checkpoint_or_run: str | Path, **options: Any) -> dict[str, Any]:
    """Evaluate a checkpoint file or a run directory of any domain with its trainer's evaluator (``options``:
    ``episodes``, ``deterministic``, ``num_envs``, ``seed``)."""
    from freamer_rl.trainers import get_trainer, resolve_checkpoint, trainer_of_checkpoint

    path = resolve_checkpoint(checkpoint_or_run)
    return get_trainer(trainer_of_checkpoint(path), str(path)).evaluate(path, **options)
