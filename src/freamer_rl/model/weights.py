"""Weights of FreamerV1's actor-value module: loading a checkpoint's state and transfer from another run
(``run.init_from``)."""

from __future__ import annotations

from pathlib import Path

from freamer_rl.errors import CheckpointError
from freamer_rl.model.factory import FreamerModules
from freamer_rl.run.checkpoint import latest_checkpoint, load_checkpoint, structural_differences

__all__ = ["transfer_weights", "load_model_state"]


def transfer_weights(modules: FreamerModules, source: str | Path, current: dict, defaults: dict) -> Path:
    """Load the model weights of another run (``source``: its directory, whose ``latest`` checkpoint is used, or a
    checkpoint file) into ``modules``; returns the checkpoint file. ``current`` is this run's config mapping: its
    ``model`` section must equal the source's (CheckpointError naming the differences otherwise); the env may differ
    as long as the weights fit (same observation and action shapes)."""
    source = Path(source)
    path = latest_checkpoint(source) if source.is_dir() else source
    if path is None:
        raise CheckpointError(f"run.init_from: {source} holds no checkpoint (checkpoints/latest is missing)")
    if not path.is_file():
        raise CheckpointError(f"run.init_from: no such checkpoint file: {path}")
    ckpt = load_checkpoint(path)
    saved = ckpt["config"] if isinstance(ckpt["config"], dict) else None
    if saved is None or not isinstance(saved.get("model"), dict):
        raise CheckpointError(f"run.init_from: checkpoint {path} holds no readable model config")
    diffs = structural_differences(saved, current, ("model",), defaults)
    if diffs:
        raise CheckpointError(f"run.init_from: checkpoint {path} has another model ({'; '.join(diffs[:4])})")
    load_model_state(modules, ckpt["model"], path)
    return path


def load_model_state(modules: FreamerModules, state: dict, path: Path) -> None:
    try:
        modules.actor_value.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError, KeyError) as err:  # wrong shapes, or not a state dict at all
        first = (str(err).splitlines() or [type(err).__name__])[0][:200]
        raise CheckpointError(f"checkpoint {path} does not fit this model: {first}") from err
