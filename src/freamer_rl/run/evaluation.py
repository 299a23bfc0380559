"""Evaluation every collector-based trainer's evaluator shares: a checkpoint and its config
(:func:`read_checkpoint_config`), then N complete episodes of a policy in the config's env (:func:`run_episodes`)
reported as success rate, return and length. ``freamer-rl eval`` dispatches to a trainer's evaluator through the
registry (:func:`freamer_rl.trainers.registry.evaluate_any`)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from freamer_rl.config.loader import config_from_dict
from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.run import env_registry
from freamer_rl.run.checkpoint import load_checkpoint
from freamer_rl.run.corruption import corruption_transforms, eval_entries
from freamer_rl.run.envs import eval_config, make_batched_env
from freamer_rl.run.metrics import LogMeans

__all__ = ["read_checkpoint_config", "run_episodes"]

logger = logging.getLogger(__name__)


def read_checkpoint_config(path: Path, schema: type) -> tuple[dict[str, Any], Any]:
    """A checkpoint (read with ``weights_only``) and its config built with ``schema``."""
    ckpt = load_checkpoint(path)
    try:
        cfg = config_from_dict(ckpt["config"], schema, migrate=True)  # a checkpoint of an earlier release too
    except ConfigError as err:
        raise CheckpointError(f"checkpoint {path} holds a config this version cannot read: {err}") from err
    return ckpt, cfg


@torch.no_grad()
def run_episodes(
    cfg: Any,
    policy: Any,
    primers: list,
    *,
    episodes: int = 20,
    deterministic: bool = False,
    num_envs: int | None = None,
    seed: int = 12345,
    max_steps: int = 100_000,
    corrupt: list | None = None,
    step_metrics: Any = None,
) -> dict[str, Any]:
    """``episodes`` complete episodes of ``policy`` in the config's env (every trainer's evaluator uses this).

    The env is corrupted as ``corrupt`` says (``env.corrupt``-style entries), else as the config's ``env.corrupt``
    entries for evaluation (``when: eval`` or ``both``). ``step_metrics(td) -> {name: scalar tensor}`` is called on
    every step the policy wrote (e.g. FreamerV1's refiner displacement); the result holds the means over steps.
    The env takes ``env.eval_options`` over ``env.options`` (e.g. a subject left out of training)."""
    cfg = eval_config(cfg)
    n_envs = min(num_envs or cfg.env.num_envs, episodes)
    entries = eval_entries(cfg.env.corrupt, corrupt)
    corruption = corruption_transforms(entries, None)
    success_fn = env_registry.get_adapter(cfg.env.adapter).success
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    # torch's generator draws the sampled actions and the corruption: seeded here (on a forked stream), so an
    # evaluation does not depend on what its process drew before (a suite worker that trained first)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        env = make_batched_env(cfg, [*corruption, *primers], seed, num_envs=n_envs)
        try:
            with set_exploration_type(mode):
                per_env = _episodes_per_env(
                    env,
                    policy,
                    n_envs,
                    -(-episodes // n_envs),
                    success_fn,
                    max_steps,
                    step_metrics,
                    means := LogMeans(),
                )
        finally:
            env.close()
    # episode k of every env before episode k + 1 of any: choosing by finishing order would favour short episodes
    chosen = [eps[k] for k in range(max(map(len, per_env))) for eps in per_env if k < len(eps)][:episodes]
    if not chosen:
        raise CheckpointError(f"no episode finished within {max_steps} steps")
    succ = [e["success"] for e in chosen if e["success"] is not None]
    return {
        "env": cfg.env.id,
        **({"env_options": dict(cfg.env.options)} if getattr(cfg.env, "options", None) else {}),
        "episodes": len(chosen),
        # NaN when the env has no notion of success (e.g. CartPole): see EnvAdapter.success
        "success_rate": sum(succ) / len(succ) if succ else float("nan"),
        "return_mean": sum(e["return"] for e in chosen) / len(chosen),
        "length_mean": sum(e["length"] for e in chosen) / len(chosen),
        # per episode, in the order above: a one-seed report's interval over episodes (experiments.robustness)
        "episode_returns": [round(float(e["return"]), 6) for e in chosen],
        **({"episode_successes": [float(s) for s in succ]} if succ else {}),
        "deterministic": deterministic,
        "corrupt": [dataclasses.asdict(c) for c in entries],
        **means.means(),
    }


def _episodes_per_env(
    env, policy, n_envs: int, quota: int, success_fn, max_steps: int, step_metrics=None, means: LogMeans | None = None
) -> list[list[dict]]:
    """The first ``quota`` episodes of each of the ``n_envs`` envs: ``{"return", "length", "success"}`` each
    (``success`` None without a success rule)."""
    per_env: list[list[dict]] = [[] for _ in range(n_envs)]
    td = env.reset()
    for _ in range(max_steps):
        td = policy(td)
        if step_metrics is not None:
            means.add(step_metrics(td))
        td, td_next = env.step_and_maybe_reset(td)
        nxt = td["next"].reshape(n_envs)
        done = nxt["done"].reshape(n_envs)
        if done.any():
            ended = done.nonzero().flatten().tolist()
            succ = success_fn(nxt[done]).reshape(-1).tolist() if success_fn is not None else [None] * len(ended)
            for j, i in enumerate(ended):
                if len(per_env[i]) < quota:
                    per_env[i].append(
                        {
                            "return": float(nxt["episode_reward"][i].reshape(-1)[0]),
                            "length": int(nxt["step_count"][i].reshape(-1)[0]),
                            "success": succ[j],
                        }
                    )
        td = td_next
        if all(len(e) >= quota for e in per_env):
            break
    return per_env
