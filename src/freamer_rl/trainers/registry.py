"""Trainer registry: one CLI and one config loader for every domain.

Every recipe names its trainer with a top-level ``trainer:`` key (no key: ``minigrid_ppo``, the MiniGrid / gym PPO
trainer). :data:`TRAINERS` maps that name to a :class:`TrainerSpec`: the config schema the loader builds, and the
train / evaluate / parameter-count entry points ``freamer-rl train|eval|params`` dispatch to. A checkpoint records
its trainer (``"trainer"`` entry; older ones are recognised by their ``"format"``), so ``freamer-rl eval`` picks the
right evaluator from the file alone.

Adding a domain = one module under :mod:`freamer_rl.trainers` with its schema (validator registered in
:data:`freamer_rl.config.loader.VALIDATORS`), ``train`` / ``evaluate`` / ``params`` and ``STRUCTURAL``, plus one entry
here; the parametrised registry test (``tests/trainers/test_trainers.py``) then asks for a tiny recipe of it.

This is the one place that maps a recipe to its schema: :func:`load_recipe` reads a recipe once and builds the
schema its ``trainer:`` names (the config loader itself knows no trainer).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from freamer_rl.config.loader import TRAINER_KEY, config_from_dict, read_recipe, split_trainer
from freamer_rl.errors import CheckpointError, ConfigError, FreamerError
from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint
from freamer_rl.trainers import health, minigrid_ppo
from freamer_rl.trainers.baselines import dreamer_v3, impala, ppo_baseline

__all__ = [
    "TrainerSpec",
    "TRAINERS",
    "get_trainer",
    "load_recipe",
    "load_config",
    "recipe_trainer",
    "trainer_of_checkpoint",
    "resolve_checkpoint",
    "evaluate_any",
]


@dataclass(frozen=True)
class TrainerSpec:
    """What a domain provides.

    Attributes:
        schema: the config dataclass its recipes build (validated by ``freamer_rl.config.loader.VALIDATORS[schema]``).
        train: ``(cfg, run_dir or None, *, resume) -> summary dict``; resumes from the run directory's latest
            checkpoint unless ``resume=False`` (which refuses a directory holding checkpoints).
        evaluate: ``(checkpoint path, *, episodes, deterministic, num_envs, seed) -> result dict``.
        params: ``cfg -> rows {"component", "trainable", "frozen"}`` (last row ``Total``) without loading weights.
        checkpoint_format: the ``"format"`` entry of its checkpoints (recognises files without a ``"trainer"``).
        structural: config sections (or dotted fields) that shape its weights: a resume needs them equal.
    """

    schema: type
    train: Callable[..., dict[str, Any]]
    evaluate: Callable[..., dict[str, Any]]
    params: Callable[[Any], list[dict]]
    checkpoint_format: str
    structural: tuple[str, ...]


def _spec(module: ModuleType, schema: type, checkpoint_format: str) -> TrainerSpec:
    """The entry of a trainer module exposing ``train``, ``evaluate``, ``params`` and ``STRUCTURAL``."""
    return TrainerSpec(schema, module.train, module.evaluate, module.params, checkpoint_format, module.STRUCTURAL)


TRAINERS: dict[str, TrainerSpec] = {
    # FreamerV1 with PPO on MiniGrid, gym and Crafter envs (the default of a recipe without ``trainer:``)
    "minigrid_ppo": _spec(minigrid_ppo, minigrid_ppo.FreamerConfig, "freamer_rl/1"),
    # health world model + imagination PPO
    "health": _spec(health, health.HealthConfig, "freamer_rl.health/1"),
    # TorchRL baselines; they always write "trainer", the format string is shared
    "ppo_baseline": _spec(ppo_baseline, ppo_baseline.PPOBaselineConfig, "freamer_rl/1"),
    "impala": _spec(impala, impala.ImpalaConfig, "freamer_rl/1"),
    "dreamer_v3": _spec(dreamer_v3, dreamer_v3.DreamerConfig, "freamer_rl/1"),
}


def get_trainer(name: str, source: str = "recipe") -> TrainerSpec:
    """The registered trainer ``name``; ConfigError naming ``source`` and the known names otherwise."""
    if name not in TRAINERS:
        raise ConfigError(f"{source}: trainer: unknown trainer {name!r} (known: {', '.join(sorted(TRAINERS))})")
    return TRAINERS[name]


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or a run directory's latest checkpoint (its final ``checkpoint.pt`` for a finished
    health run)."""
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
        raise CheckpointError(
            f"checkpoint {path}: unknown trainer {name!r} / format {ckpt.get('format')!r} "
            f"(known trainers: {', '.join(sorted(TRAINERS))})"
        )
    return name


def load_recipe(
    path: str | Path | None, overrides: list[str] | None = None, *, schema: type | None = None
) -> tuple[str, Any]:
    """``(trainer name, config)`` of a recipe (the defaults when ``path`` is None), read once, with dotted
    ``overrides``, built as the schema its ``trainer:`` names (no key: ``minigrid_ppo``). An explicit ``schema``
    must match the recipe's trainer when the recipe names one."""
    source = str(path) if path is not None else "defaults"
    raw = read_recipe(path, overrides)
    name, data = split_trainer(raw, source)
    spec = get_trainer(name, source)
    if schema is not None and TRAINER_KEY in raw and spec.schema is not schema:
        raise ConfigError(
            f"{source}: {TRAINER_KEY}: {name!r} recipes are {spec.schema.__name__}s, not {schema.__name__}s"
        )
    return name, config_from_dict(data, schema if schema is not None else spec.schema)


def load_config(
    path: str | Path | None = None, overrides: list[str] | None = None, *, schema: type | None = None
) -> Any:
    """The config of a recipe built as its trainer's schema (:func:`load_recipe` without the name)."""
    return load_recipe(path, overrides, schema=schema)[1]


def recipe_trainer(path: str | Path, overrides: list[str] | None = None) -> str:
    """The trainer a recipe names (its ``trainer:`` key after ``overrides``; ``minigrid_ppo`` without one)."""
    return split_trainer(read_recipe(path, overrides), str(path))[0]


def evaluate_any(checkpoint_or_run: str | Path, **options: Any) -> dict[str, Any]:
    """Evaluate a checkpoint file or a run directory of any domain with its trainer's evaluator (``options``:
    ``episodes``, ``deterministic``, ``num_envs``, ``seed``)."""
    path = resolve_checkpoint(checkpoint_or_run)
    return get_trainer(trainer_of_checkpoint(path), str(path)).evaluate(path, **options)
