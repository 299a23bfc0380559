"""Trainer registry: one CLI and one config loader for every domain.

Every recipe names its trainer with a top-level ``trainer:`` key (no key: ``minigrid_ppo``, the MiniGrid / gym PPO
trainer). :data:`TRAINERS` maps that name to a :class:`TrainerSpec`: the config schema the loader builds, and the
train / evaluate / parameter-count entry points ``freamer-rl train|eval|params`` dispatch to. A checkpoint records
its trainer (``"trainer"`` entry; older ones are recognised by their ``"format"``), so ``freamer-rl eval`` picks the
right evaluator from the file alone.

Adding a domain = one entry here (plus its schema's validator in :data:`freamer_rl.config.VALIDATORS`); the
parametrised registry test (``tests/test_trainers.py``) then asks for a tiny recipe of it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from freamer_rl.baselines.config import ImpalaConfig, PPOBaselineConfig
from freamer_rl.baselines.dreamer import DreamerConfig, dreamer_params, evaluate_dreamer, train_dreamer
from freamer_rl.config import ConfigError, FreamerConfig
from freamer_rl.errors import CheckpointError, FreamerError
from freamer_rl.health.config import HealthConfig

__all__ = ["TrainerSpec", "TRAINERS", "get_trainer", "trainer_of_checkpoint", "resolve_checkpoint"]


@dataclass(frozen=True)
class TrainerSpec:
    """What a domain provides.

    Attributes:
        schema: the config dataclass its recipes build (validated by ``freamer_rl.config.VALIDATORS[schema]``).
        train: ``(cfg, run_dir or None, *, resume) -> summary dict``; resumes from the run directory's latest
            checkpoint unless ``resume=False`` (which refuses a directory holding checkpoints).
        evaluate: ``(checkpoint path, *, episodes, deterministic, num_envs, seed) -> result dict``.
        params: ``cfg -> rows {"component", "trainable", "frozen"}`` (last row ``Total``) without loading weights.
        checkpoint_format: the ``"format"`` entry of its checkpoints (recognises files without a ``"trainer"``).
    """

    schema: type
    train: Callable[..., dict[str, Any]]
    evaluate: Callable[..., dict[str, Any]]
    params: Callable[[Any], list[dict]]
    checkpoint_format: str


def _lazy(module: str, name: str) -> Callable[..., Any]:
    """``module.name``, imported at its first call: ``freamer-rl`` starts without loading every domain's code."""

    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    return call


def _health_params(cfg: HealthConfig) -> list[dict]:
    from freamer_rl.health.agent import build_agent, parameter_table

    return parameter_table(build_agent(cfg))


_PPO, _IMPALA = "freamer_rl.baselines.ppo", "freamer_rl.baselines.impala"

TRAINERS: dict[str, TrainerSpec] = {
    # MiniGrid / gym PPO (freamer_rl.train)
    "minigrid_ppo": TrainerSpec(FreamerConfig, _lazy("freamer_rl.train", "train"),
                                _lazy("freamer_rl.evaluate", "evaluate"),
                                _lazy("freamer_rl.params", "offline_parameter_table"), "freamer_rl/1"),
    # health world model + imagination PPO (freamer_rl.health)
    "health": TrainerSpec(HealthConfig, _lazy("freamer_rl.health.trainer", "run_health"),
                          _lazy("freamer_rl.health.evaluation", "evaluate_checkpoint"), _health_params,
                          "freamer_rl.health/1"),
    # TorchRL baselines (freamer_rl.baselines); they always write "trainer", the format string is shared
    "dreamer_v3": TrainerSpec(DreamerConfig, train_dreamer, evaluate_dreamer, dreamer_params, "freamer_rl/1"),
    "ppo_baseline": TrainerSpec(PPOBaselineConfig, _lazy(_PPO, "train_ppo_baseline"),
                                _lazy(_PPO, "evaluate_ppo_baseline"), _lazy(_PPO, "ppo_baseline_params"),
                                "freamer_rl/1"),
    "impala": TrainerSpec(ImpalaConfig, _lazy(_IMPALA, "train_impala"), _lazy(_IMPALA, "evaluate_impala"),
                          _lazy(_IMPALA, "impala_params"), "freamer_rl/1"),
}  # fmt: skip


def get_trainer(name: str, source: str = "recipe") -> TrainerSpec:
    """The registered trainer ``name``; ConfigError naming ``source`` and the known names otherwise."""
    if name not in TRAINERS:
        raise ConfigError(f"{source}: trainer: unknown trainer {name!r} (known: {', '.join(sorted(TRAINERS))})")
    return TRAINERS[name]


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or a run directory's latest checkpoint (its final ``checkpoint.pt`` for a finished
    health run)."""
    from freamer_rl.checkpoint import latest_checkpoint

    path = Path(path)
    if not path.is_dir():
        return path
    final = path / "checkpoint.pt"
    found = final if final.is_file() else latest_checkpoint(path)
    if found is None:
        raise FreamerError(f"no checkpoint in run directory {path}")
    return found


def trainer_of_checkpoint(path: Path) -> str:
    """The trainer that wrote checkpoint ``path``: its ``"trainer"`` entry, else the one owning its ``"format"``."""
    from freamer_rl.checkpoint import read_checkpoint

    ckpt = read_checkpoint(path)
    name = ckpt.get("trainer")
    if name is None:
        # checkpoints written before the "trainer" entry are all FreamerV1's / health's: the first owner of a format
        # (the baselines reuse "freamer_rl/1" but always write "trainer")
        by_format: dict[str, str] = {}
        for n, spec in TRAINERS.items():
            by_format.setdefault(spec.checkpoint_format, n)
        name = by_format.get(ckpt.get("format", "freamer_rl/1"))
    if name not in TRAINERS:
        raise CheckpointError(f"checkpoint {path}: unknown trainer {name!r} / format {ckpt.get('format')!r} "
                              f"(known trainers: {', '.join(sorted(TRAINERS))})")  # fmt: skip
    return name
