"""The health domain's pipeline, by concern (this module only re-exports; import from the modules themselves):

* :mod:`freamer_rl.health.config` -- :class:`HealthConfig` (recipes ``recipes/health/health_*.yaml``, ``trainer:
  health``), loaded by :func:`freamer_rl.config.load_config`.
* :mod:`freamer_rl.health.agent` -- the real env, world model + encoder, actor-value, :class:`HealthPolicy` (the online
  posterior filter acting in the real env), :class:`HealthAgent`, ``checkpoint.pt`` (:func:`load_agent`).
* :mod:`freamer_rl.health.trainer` -- :class:`HealthTrainer` / :func:`run_health`: collection -> world model ->
  imagination PPO, resumable (the run-directory layout and the loop are described there).
* :mod:`freamer_rl.health.evaluation` -- the real-env evaluation protocol.
* :mod:`freamer_rl.world_model.metrics` -- reconstruction MSE, imagination horizon (definition there), seed latents.
* :mod:`freamer_rl.health.anomaly_report` -- :func:`anomaly_report` (J.5 / Fig. 4).
"""

from __future__ import annotations

from freamer_rl.health.agent import (
    CHECKPOINT_FORMAT, CHECKPOINT_NAME, HealthAgent, HealthPolicy, build_actor_value, build_agent, build_world_model,
    load_agent, make_health_env, save_agent,
)
from freamer_rl.health.anomaly_report import anomaly_report, record_episode
from freamer_rl.health.config import (
    HealthCollectConfig, HealthConfig, HealthEncoderConfig, HealthEnvConfig, HealthEvalConfig,
    HealthImaginationConfig, HealthRunConfig, HealthWorldModelConfig, health_config_from_dict, health_config_to_dict,
    load_health_config, validate_health_config,
)
from freamer_rl.health.evaluation import evaluate_policy, rollout_metrics
from freamer_rl.health.trainer import HealthTrainer, default_run_dir, run_health, train_world_model_step
from freamer_rl.world_model.metrics import imagination_horizon, reconstruction_mse, seed_latents

__all__ = [
    "HealthEnvConfig", "HealthEncoderConfig", "HealthWorldModelConfig", "HealthImaginationConfig",
    "HealthCollectConfig", "HealthEvalConfig", "HealthRunConfig", "HealthConfig", "validate_health_config",
    "load_health_config", "health_config_from_dict", "health_config_to_dict", "HealthAgent", "HealthPolicy",
    "build_agent", "build_world_model", "build_actor_value", "load_agent", "save_agent", "make_health_env",
    "CHECKPOINT_NAME", "CHECKPOINT_FORMAT", "train_world_model_step", "evaluate_policy", "rollout_metrics",
    "reconstruction_mse", "imagination_horizon", "seed_latents", "HealthTrainer", "run_health", "default_run_dir",
    "record_episode", "anomaly_report",
]  # fmt: skip
