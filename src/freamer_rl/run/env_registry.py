"""Find environment adapters through the ``freamer_rl.envs`` entry-point group.

The library never imports the adapters (``envs/``, installed as ``freamer_rl_envs``): they register themselves in
``pyproject.toml`` (``minigrid = "freamer_rl_envs.minigrid:ADAPTER"``) and any third-party package can add its own.
An entry point names either an :class:`EnvAdapter` or a plain factory
``factory(env_id, *, seed=None, **options) -> torchrl.envs.EnvBase`` (treated as an adapter without options).
The adapter, not the library, decides which config values become env options and what counts as a success.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

import torch

from freamer_rl.errors import EnvSetupError


def _no_options(cfg: Any) -> dict[str, Any]:
    return {}


@dataclass(frozen=True)
class EnvAdapter:
    """What an adapter declares.

    Attributes:
        make_env: ``(env_id, *, seed=None, **options) -> EnvBase`` building one unbatched env.
        options: ``FreamerConfig -> dict`` of keyword options for ``make_env`` (e.g. render pixels only when the
            vision modality is used).
        success: ``next-tensordict entries at episode ends [N] -> bool [N]``, or ``None`` when the task has no
            notion of success (the trainer then reports returns only).
        make_batched_env: ``(env_id, num_envs, *, seed=None, **options) -> EnvBase`` of batch size ``[num_envs]``
            giving the same data as ``SerialEnv(num_envs, make_env)`` but faster (e.g. one TensorDict per batch
            instead of one per sub-env), or ``None``: the trainer then uses that SerialEnv.
        achievements: names of the entries of the env's ``"achievements"`` observation (bool ``[A]``, unlocked so
            far in the episode), e.g. Crafter's 22; the trainer then logs the Crafter score over all training
            episodes (:mod:`freamer_rl.run.crafter_score`). Empty: none.
        writes: the optional entries the env can compute when a config asks for them, e.g. ``"lang_reward"``
            (R_lang of the MiniGrid mission). A config field that asks for one the adapter does not list (see
            :data:`freamer_rl.run.envs.ENV_WRITTEN`) is refused before the env is built. Empty: none.
        option_names: the keyword options of ``make_env`` / ``make_batched_env`` a recipe may set directly through
            ``env.options`` (and ``env.eval_options`` for evaluation envs), e.g. the health env's ``subjects``;
            the factory checks their values. Empty: the adapter takes none that way.
    """

    make_env: Callable[..., Any]
    options: Callable[[Any], dict[str, Any]] = _no_options
    success: Callable[[Any], torch.Tensor] | None = None
    make_batched_env: Callable[..., Any] | None = None
    achievements: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()
    option_names: tuple[str, ...] = ()


ENTRY_POINT_GROUP = "freamer_rl.envs"


@functools.cache
def available_adapters() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def get_adapter(adapter: str) -> EnvAdapter:
    """The :class:`EnvAdapter` registered under ``adapter`` (a plain factory is wrapped)."""
    adapters = available_adapters()
    if adapter not in adapters:
        known = ", ".join(sorted(adapters)) or "none (is the project installed? pip install -e .)"
        raise EnvSetupError(f"env.adapter: unknown adapter '{adapter}' (installed adapters: {known})")
    obj = adapters[adapter].load()
    return obj if isinstance(obj, EnvAdapter) else EnvAdapter(make_env=obj)


def get_env_factory(adapter: str) -> Callable[..., Any]:
    return get_adapter(adapter).make_env


def make_env(adapter: str, env_id: str, *, seed: int | None = None, **options: Any):
    """Build one (unbatched) environment. Invalid ids become an :class:`EnvSetupError`."""
    factory = get_env_factory(adapter)
    try:
        return factory(env_id, seed=seed, **options)
    except EnvSetupError:
        raise
    except ValueError as err:
        # Adapters report unknown ids / bad options as ValueError; keep their one-line message. Other exception
        # types are bugs and keep their traceback.
        msg = err.args[0] if err.args else repr(err)
        raise EnvSetupError(f"env.id '{env_id}' ({adapter} adapter): {msg}") from err
