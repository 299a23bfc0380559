"""Real-env evaluation of a health agent (paper Section 5, Table 15).

Every evaluation runs the policy in the **real** env with a fresh env of ``eval.num_envs`` episodes (env seed
``eval.seed``: the same episodes for every evaluation, run and encoder): the policy acts (mode of the categorical
when ``eval.deterministic``) on the posterior-mean latent; per episode the return, the number of steps with heart
rate > 160 bpm (violations, counted by the env) and the length, read at each env's first ``done``. The world-model
metrics (:mod:`freamer_rl.world_model.metrics`) are computed on windows cut from those held-out episodes:
reconstruction MSE over ``eval.mse_windows`` windows of ``world_model.seq_len`` steps, the imagination horizon over
``eval.horizon_windows`` windows of ``eval.horizon_context + eval.horizon_max`` steps.

Held-out subjects (leave-one-subject-out): with ``eval.subjects`` set, the evaluation env draws its episodes from
those subjects only (a run trains on ``env.subjects``); null evaluates on the training subjects. Every evaluation
env, the reference policies' and the oracle's included (:mod:`freamer_rl.health.reference`), is built by
:func:`make_eval_env`, so "fraction of the oracle" compares the same subjects and episodes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type
from torchrl.envs.transforms import TensorDictPrimer

from freamer_rl.health.agent import HealthAgent, load_agent, make_health_env
from freamer_rl.world_model.metrics import imagination_horizon, reconstruction_mse, sample_windows

__all__ = [
    "STORE_KEYS",
    "eval_subjects",
    "make_eval_env",
    "episode_stats",
    "rollout_metrics",
    "evaluate_policy",
    "world_model_metrics",
    "evaluate_agent",
    "evaluate_checkpoint",
]


STORE_KEYS = (
    "imu",
    "hr_features",
    "action",
    ("next", "imu"),
    ("next", "hr_features"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("collector", "traj_ids"),
)


def eval_subjects(cfg: Any) -> list[int] | None:
    """The subjects an evaluation draws its episodes from: ``eval.subjects``, else ``env.subjects`` (``None``: the
    env's default set)."""
    held_out = cfg.eval.subjects
    return list(held_out) if held_out is not None else cfg.env.subjects


def make_eval_env(
    cfg: Any, *, num_envs: int | None = None, seed: int | None = None, primer: TensorDictPrimer | None = None
) -> EnvBase:
    """The real env of an evaluation: :func:`~freamer_rl.health.agent.make_health_env` with ``num_envs`` (default
    ``eval.num_envs``) episodes from env ``seed`` (default ``eval.seed``) over :func:`eval_subjects`."""
    return make_health_env(
        cfg,
        num_envs=num_envs or cfg.eval.num_envs,
        seed=cfg.eval.seed if seed is None else seed,
        primer=primer,
        subjects=eval_subjects(cfg),
    )


def episode_stats(data: TensorDictBase) -> dict[str, float]:
    """Mean return / violations / length of the episodes that ended in ``data`` (``nan`` when none)."""
    done = data.get(("next", "done")).squeeze(-1)
    n = int(done.sum())
    if n == 0:
        return {"episodes": 0, "return": float("nan"), "violations": float("nan"), "length": float("nan")}
    ep = data.get(("next", "episode"))[done]
    return {
        "episodes": n,
        "return": float(ep["return"].float().mean()),
        "violations": float(ep["violations"].float().mean()),
        "length": float(ep["length"].float().mean()),
    }


def rollout_metrics(traj: TensorDictBase) -> dict[str, float]:
    """Per-episode metrics of a real-env rollout ``[n, L]`` (``break_when_any_done=False``, ``L`` >= the episode
    length), read at each env's first ``("next", "done")``: ``return_mean``/``return_std`` (over episodes),
    ``violations_mean``, ``length_mean``, ``episodes``. Raises ``ValueError`` when an env never finished."""
    if traj.batch_dims != 2:
        raise ValueError(f"rollout_metrics: expected a rollout [num_envs, steps], got batch shape {tuple(traj.shape)}")
    n = traj.shape[0]
    done = traj.get(("next", "done")).reshape(n, -1)  # [n, L]
    if not bool(done.any(-1).all()):
        raise ValueError(
            f"rollout_metrics: {int((~done.any(-1)).sum())} of {n} envs never reached done in "
            f"{traj.shape[1]} steps; roll at least env.episode_length steps"
        )
    first = done.float().argmax(dim=-1)
    ep = traj.get(("next", "episode"))[torch.arange(n), first]
    ret = ep["return"].float().squeeze(-1)
    return {
        "return_mean": float(ret.mean()),
        "return_std": float(ret.std(unbiased=False)),
        "violations_mean": float(ep["violations"].float().mean()),
        "length_mean": float(ep["length"].float().mean()),
        "episodes": n,
    }


@torch.no_grad()
def evaluate_policy(
    agent: HealthAgent, *, num_envs: int | None = None, seed: int = 10_000, deterministic: bool = True
) -> tuple[dict[str, float], TensorDictBase]:
    """Roll the policy in the real env: ``num_envs`` episodes of ``env.episode_length`` steps (one per env, from a
    fresh env with ``seed``, over :func:`eval_subjects`). Returns (metrics, rollout ``[num_envs, episode_length]``).

    Metrics: ``return_mean``/``return_std`` (over episodes), ``violations_mean`` (steps with heart rate > 160
    bpm per episode), ``length_mean``, ``episodes``; read at each env's first ``("next", "done")``.
    """
    cfg = agent.cfg
    n = num_envs or cfg.eval.num_envs
    policy = agent.policy(sample_latent=False)
    env = make_eval_env(cfg, num_envs=n, seed=seed, primer=policy.make_tensordict_primer())
    agent.world_model.eval()
    etype = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    with set_exploration_type(etype):
        traj = env.rollout(cfg.env.episode_length, policy, break_when_any_done=False)
    env.close()
    metrics = rollout_metrics(traj)
    actions = traj.get("action").reshape(-1)
    for i in range(agent.world_model.action_dim):
        metrics[f"action_frac_{i}"] = float((actions == i).float().mean())
    keep = [k for k in STORE_KEYS if k != ("collector", "traj_ids")] + [("next", "heart_rate"), "kl"]
    return metrics, traj.select(*keep, strict=False)


def world_model_metrics(agent: HealthAgent, traj: TensorDictBase, seed: int) -> dict[str, float]:
    """Reconstruction MSE and imagination horizon on windows of a real-env rollout ``traj [E, L]`` (module
    docstring); windows drawn with a generator seeded by ``seed``."""
    cfg = agent.cfg
    g = torch.Generator().manual_seed(seed)
    out: dict[str, float] = {}
    w = sample_windows(traj, cfg.world_model.seq_len, cfg.eval.mse_windows, g)
    if w is not None:
        out.update(reconstruction_mse(agent.world_model, w))
    ctx, hmax = cfg.eval.horizon_context, cfg.eval.horizon_max
    w = sample_windows(traj, ctx + hmax, cfg.eval.horizon_windows, g)
    if w is not None:
        hz = imagination_horizon(agent.world_model, w, ctx, cfg.eval.horizon_reward_tol)
        out["imagination_horizon"] = float(hz.mean())
        out["imagination_horizon_std"] = float(hz.std(unbiased=False))
    return out


def evaluate_agent(agent: HealthAgent) -> dict[str, float]:
    """The full evaluation protocol of the module docstring: policy metrics plus world-model metrics."""
    cfg = agent.cfg
    metrics, traj = evaluate_policy(agent, seed=cfg.eval.seed, deterministic=cfg.eval.deterministic)
    metrics.update(world_model_metrics(agent, traj, cfg.eval.seed))
    return metrics


def evaluate_checkpoint(
    path: str | Path,
    *,
    episodes: int = 20,
    deterministic: bool = True,
    num_envs: int | None = None,
    seed: int = 12345,
) -> dict[str, Any]:
    """``freamer-rl eval`` of a health checkpoint: ``episodes`` real-env episodes (one per env, so ``num_envs`` is
    ``episodes``; a value given must agree) from env seed ``seed``, plus the world-model metrics on them."""

    if num_envs is not None and num_envs != episodes:
        raise ValueError(f"--num-envs ({num_envs}): a health evaluation runs one episode per env; give --episodes")
    agent = load_agent(path)
    metrics, traj = evaluate_policy(agent, num_envs=episodes, seed=seed, deterministic=deterministic)
    metrics.update(world_model_metrics(agent, traj, seed))
    return {
        "checkpoint": str(path),
        "trainer": "health",
        "encoder": agent.cfg.encoder.kind,
        "deterministic": deterministic,
        **metrics,
    }
