"""DreamerV3 baseline built from TorchRL's Dreamer objectives: config schema, validator and entry points.

``trainer: dreamer_v3`` recipes (``recipes/baselines/dreamer_v3_*.yaml``) build a :class:`DreamerConfig`: the
shared :class:`freamer_rl.config.FreamerConfig` sections (env, collector, logging, run; ``ppo`` and ``model`` are
unused except that ``model.modalities`` containing ``vision`` asks the MiniGrid adapter for pixels) plus a
``dreamer`` section. This module stays light (no torch import): the trainer registry imports the schema at start-up;
the trainer itself is :class:`freamer_rl.baselines.dreamer_model.DreamerTrainer`.

    freamer-rl train recipes/baselines/dreamer_v3_n2s4.yaml run.seed=0
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from freamer_rl.config import VALIDATORS, ConfigError, FreamerConfig, validate

__all__ = ["DreamerSection", "DreamerConfig", "validate_dreamer", "train_dreamer", "evaluate_dreamer",
           "dreamer_params"]  # fmt: skip


@dataclass
class DreamerSection:
    """DreamerV3 sizes and training schedule (paper defaults in comments; CPU-sized values here)."""

    observation_keys: list[str] = field(default_factory=lambda: ["grid", "direction"])  # uint8 [H,W,C] -> CNN
    stoch_categoricals: int = 16  # paper: 32 (size S) .. 32
    stoch_classes: int = 16  # paper: 32
    deter: int = 256  # paper: 4096 (XL) / 512 (S)
    hidden: int = 256  # MLP width; paper: 512 (S) .. 1024
    mlp_layers: int = 2  # paper: 2 (S) .. 5
    cnn_depth: int = 16  # base channels of the image encoder/decoder; paper: 32 (S)
    cnn_mults: list[int] = field(default_factory=lambda: [2, 3, 4, 4])
    unimix: float = 0.01
    frames_per_batch: int = 256  # env frames collected between learning phases
    replay_capacity: int = 100_000  # env frames kept (oldest dropped)
    batch_size: int = 16  # paper: 16
    sequence_length: int = 32  # paper: 64
    train_every: int = 64  # env frames per update (train ratio = batch_size * sequence_length / train_every)
    prefill_frames: int = 2_000  # frames collected (acting with the untrained actor) before the first update
    horizon: int = 15  # imagination horizon
    gamma: float = 0.997  # paper: 1 - 1/333
    lmbda: float = 0.95
    model_lr: float = 1e-4
    actor_lr: float = 3e-5
    value_lr: float = 3e-5
    adam_eps: float = 1e-8
    model_grad_clip: float = 1000.0
    actor_grad_clip: float = 100.0
    value_grad_clip: float = 100.0
    lambda_dynamic: float = 0.5  # KL(sg(post) || prior); paper 0.5, current reference code 1.0
    lambda_representation: float = 0.1
    free_nats: float = 1.0
    entropy_bonus: float = 3e-4
    slow_critic: float = 1.0  # weight of the slow-critic regulariser (0: off)
    slow_critic_tau: float = 0.02


@dataclass
class DreamerConfig(FreamerConfig):
    dreamer: DreamerSection = field(default_factory=DreamerSection)


_POSITIVE_INTS = ("stoch_categoricals", "stoch_classes", "deter", "hidden", "mlp_layers", "cnn_depth",
                  "frames_per_batch", "replay_capacity", "batch_size", "sequence_length", "train_every", "horizon")
_POSITIVE_FLOATS = ("model_lr", "actor_lr", "value_lr", "adam_eps", "model_grad_clip", "actor_grad_clip",
                    "value_grad_clip", "slow_critic_tau")
_NON_NEGATIVE = ("lambda_dynamic", "lambda_representation", "free_nats", "entropy_bonus", "slow_critic")


def _check_section(d: DreamerSection, num_envs: int) -> None:
    for name in _POSITIVE_INTS:
        if getattr(d, name) < 1:
            raise ConfigError(f"dreamer.{name}: expected an int >= 1, got {getattr(d, name)}")
    for name in _POSITIVE_FLOATS:
        if not getattr(d, name) > 0:
            raise ConfigError(f"dreamer.{name}: expected a float > 0, got {getattr(d, name)}")
    for name in _NON_NEGATIVE:
        if not getattr(d, name) >= 0:
            raise ConfigError(f"dreamer.{name}: expected a float >= 0, got {getattr(d, name)}")
    for name in ("gamma", "lmbda"):
        if not 0 < getattr(d, name) <= 1:
            raise ConfigError(f"dreamer.{name}: expected a float in (0, 1], got {getattr(d, name)}")
    if not 0 <= d.unimix < 1:
        raise ConfigError(f"dreamer.unimix: expected a float in [0, 1), got {d.unimix}")
    if d.slow_critic_tau > 1:
        raise ConfigError(f"dreamer.slow_critic_tau: expected a float in (0, 1], got {d.slow_critic_tau}")
    if d.prefill_frames < 0:
        raise ConfigError(f"dreamer.prefill_frames: expected an int >= 0, got {d.prefill_frames}")
    if not d.observation_keys or len(set(d.observation_keys)) != len(d.observation_keys):
        raise ConfigError(f"dreamer.observation_keys: expected distinct observation keys, got {d.observation_keys}")
    if not d.cnn_mults or min(d.cnn_mults) < 1:
        raise ConfigError(f"dreamer.cnn_mults: expected a non-empty list of ints >= 1, got {d.cnn_mults}")
    if d.frames_per_batch % num_envs:
        raise ConfigError(f"dreamer.frames_per_batch: must be divisible by env.num_envs ({num_envs}), "
                          f"got {d.frames_per_batch}")  # fmt: skip
    steps = d.frames_per_batch // num_envs
    if d.sequence_length > steps:
        raise ConfigError(f"dreamer.sequence_length: must be <= the steps per env per batch ({steps} = "
                          f"dreamer.frames_per_batch / env.num_envs), got {d.sequence_length}")  # fmt: skip
    # the replay keeps whole [num_envs, steps] rows of one env: capacity_frames // steps sequences of `steps` frames
    held = (d.replay_capacity // steps) * steps
    if held < max(d.frames_per_batch, d.prefill_frames):
        raise ConfigError(f"dreamer.replay_capacity: must hold dreamer.frames_per_batch and dreamer.prefill_frames "
                          f"({max(d.frames_per_batch, d.prefill_frames)}) in whole sequences of {steps} steps "
                          f"(it holds {held} frames), got {d.replay_capacity}")  # fmt: skip


def validate_dreamer(cfg: DreamerConfig) -> None:
    """The FreamerConfig checks, then every ``dreamer`` field (the error names it)."""
    validate(cfg)
    _check_section(cfg.dreamer, cfg.env.num_envs)
    if cfg.collector.num_collectors != 1:
        raise ConfigError(f"collector.num_collectors: the DreamerV3 trainer collects in one process (1), got "
                          f"{cfg.collector.num_collectors}")  # fmt: skip


VALIDATORS[DreamerConfig] = validate_dreamer


#: ``dreamer`` fields that shape the networks: a checkpoint only resumes / loads with the same values.
ARCHITECTURE_FIELDS = ("observation_keys", "stoch_categoricals", "stoch_classes", "deter", "hidden", "mlp_layers",
                       "cnn_depth", "cnn_mults")


def train_dreamer(cfg: DreamerConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    """Train DreamerV3 with ``cfg``; returns the run summary (``summary.json``). See ``DreamerTrainer``."""
    from freamer_rl.baselines.dreamer_model import DreamerTrainer
    from freamer_rl.runloop import resolve_run_dir

    return DreamerTrainer(cfg, resolve_run_dir(cfg, run_dir), resume=resume).train()


def evaluate_dreamer(path: str | Path, **options: Any) -> dict[str, Any]:
    """Run episodes with a checkpoint's DreamerV3 policy (``options``: episodes, deterministic, num_envs, seed)."""
    from freamer_rl.baselines.dreamer_model import evaluate_checkpoint

    return evaluate_checkpoint(Path(path), **options)


def dreamer_params(cfg: DreamerConfig) -> list[dict]:
    """Rows ``{"component", "trainable", "frozen"}`` per network, then ``Total`` (probes the env's specs)."""
    from freamer_rl.baselines.dreamer_model import build_nets

    nets = build_nets(cfg)
    rows = [{"component": name, "trainable": sum(p.numel() for p in m.parameters()), "frozen": 0}
            for name, m in nets.components().items()]  # fmt: skip
    rows.append({"component": "Total", "trainable": sum(r["trainable"] for r in rows), "frozen": 0})
    return rows
