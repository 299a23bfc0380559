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

from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type
from torchrl.envs.transforms import TensorDictPrimer

from freamer_rl.config.sections import corruption_target
from freamer_rl.errors import ConfigError
from freamer_rl.health.agent import HealthAgent, load_agent, make_health_env
from freamer_rl.run.corruption import ModalityCorruption, corruption_transforms, eval_entries
from freamer_rl.world_model.metrics import imagination_horizon, reconstruction_mse, sample_windows

__all__ = [
    "STORE_KEYS",
    "eval_subjects",
    "make_eval_env",
    "episode_stats",
    "rollout_metrics",
    "corruption_for",
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


def corruption_for(agent: HealthAgent, entries: list | None, phase: str | None = None) -> list[ModalityCorruption]:
    """The ``--corrupt`` / ``env.corrupt`` entries (:class:`~freamer_rl.config.sections.CorruptionConfig`) as
    transforms of an env; ``phase`` ``"train"`` / ``"eval"`` keeps the entries whose ``when`` names it (None: all).
    Only the observations the agent reads (the world model's ``obs_dims``: imu, hr_features) may be corrupted: a
    corruption of a key nobody reads would change nothing and read as robustness. One site of the IMU is
    ``imu[0:12]`` (hand), ``imu[12:24]`` (chest), ``imu[24:36]`` (ankle)."""
    entries = list(entries or [])
    reads = list(agent.world_model.obs_dims)
    for i, e in enumerate(entries):
        key, _ = corruption_target(e, f"env.corrupt[{i}]")
        if key not in reads:
            raise ConfigError(
                f"env.corrupt[{i}].key: the health agent reads {', '.join(reads)}, not {key!r} "
                "(one IMU site: imu[0:12] hand, imu[12:24] chest, imu[24:36] ankle)"
            )
    return corruption_transforms(entries, phase)


@torch.no_grad()
def evaluate_policy(
    agent: HealthAgent,
    *,
    num_envs: int | None = None,
    seed: int = 10_000,
    deterministic: bool = True,
    corrupt: list | None = None,
) -> tuple[dict[str, float], TensorDictBase]:
    """Roll the policy in the real env: ``num_envs`` episodes of ``env.episode_length`` steps (one per env, from a
    fresh env with ``seed``, over :func:`eval_subjects`). Returns (metrics, rollout ``[num_envs, episode_length]``).
    ``corrupt`` (:func:`corruption_for`) corrupts the env's observations before the policy's filter reads them, so
    the rollout (and the world-model metrics computed on it) holds what the encoder saw.

    Metrics: ``return_mean``/``return_std`` (over episodes), ``violations_mean`` (steps with heart rate > 160
    bpm per episode), ``length_mean``, ``episodes``; read at each env's first ``("next", "done")``; ``kl_mean`` /
    ``kl_std``: the filter's per-step ``KL(q || p)`` over all steps (the anomaly statistic, J.5).
    """
    cfg = agent.cfg
    n = num_envs or cfg.eval.num_envs
    policy = agent.policy(sample_latent=False)
    transforms = corruption_for(agent, corrupt)
    env = make_eval_env(cfg, num_envs=n, seed=seed, primer=policy.make_tensordict_primer())
    for t in transforms:
        env.append_transform(t)
    agent.world_model.eval()
    etype = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    with set_exploration_type(etype):
        traj = env.rollout(cfg.env.episode_length, policy, break_when_any_done=False)
    env.close()
    metrics = rollout_metrics(traj)
    actions = traj.get("action").reshape(-1)
    for i in range(agent.world_model.action_dim):
        metrics[f"action_frac_{i}"] = float((actions == i).float().mean())
    kl = traj.get("kl", None)
    if kl is not None:
        metrics["kl_mean"], metrics["kl_std"] = float(kl.float().mean()), float(kl.float().std(unbiased=False))
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
    """The full evaluation protocol of the module docstring: policy metrics plus world-model metrics, under the
    recipe's evaluation corruptions (``env.corrupt`` entries with ``when`` eval or both; none by default)."""
    cfg = agent.cfg
    corrupt = eval_entries(cfg.env.corrupt, None)
    metrics, traj = evaluate_policy(agent, seed=cfg.eval.seed, deterministic=cfg.eval.deterministic, corrupt=corrupt)
    metrics.update(world_model_metrics(agent, traj, cfg.eval.seed))
    return metrics


def evaluate_checkpoint(
    path: str | Path,
    *,
    episodes: int = 20,
    deterministic: bool = True,
    num_envs: int | None = None,
    seed: int = 12345,
    corrupt: list | None = None,
) -> dict[str, Any]:
    """``freamer-rl eval`` of a health checkpoint: ``episodes`` real-env episodes (one per env, so ``num_envs`` is
    ``episodes``; a value given must agree) from env seed ``seed``, plus the world-model metrics on them;
    ``corrupt``: ``--corrupt`` entries (:func:`corruption_for`), recorded in the result; None: the run's recipe's
    evaluation corruptions (``env.corrupt`` with ``when`` eval or both), ``[]``: none."""

    if num_envs is not None and num_envs != episodes:
        raise ConfigError(f"--num-envs ({num_envs}): a health evaluation runs one episode per env; give --episodes")
    agent = load_agent(path)
    corrupt = eval_entries(agent.cfg.env.corrupt, corrupt)
    metrics, traj = evaluate_policy(agent, num_envs=episodes, seed=seed, deterministic=deterministic, corrupt=corrupt)
    metrics.update(world_model_metrics(agent, traj, seed))
    return {
        "checkpoint": str(path),
        "trainer": "health",
        "encoder": agent.cfg.encoder.kind,
        "deterministic": deterministic,
        "corrupt": [asdict(e) for e in corrupt or []],
        **metrics,
    }
