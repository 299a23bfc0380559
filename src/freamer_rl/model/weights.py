"""Weights of FreamerV1's actor-value module: loading a checkpoint's state (a resume, an evaluation, or a transfer
from another run through ``run.init_from``: :meth:`freamer_rl.run.loop.RunLoop._after_open`)."""

from __future__ import annotations

from pathlib import Path

from freamer_rl.errors import CheckpointError
from freamer_rl.model.factory import FreamerModules

__all__ = ["load_model_state"]


def load_model_state(modules: FreamerModules, state: dict, path: Path) -> None:
    try:
        modules.actor_value.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError, KeyError) as err:  # wrong shapes, or not a state dict at all
        first = (str(err).splitlines() or [type(err).__name__])[0][:200]
        raise CheckpointError(f"checkpoint {path} does not fit this model: {first}") from err
