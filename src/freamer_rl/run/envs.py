"""Envs from a config's ``env`` section, through the adapter registry (:mod:`freamer_rl.run.env_registry`).

One env (:func:`make_single_env`), the batched env a collector steps (:func:`make_batched_env`: ``env.num_envs``
copies in one process plus InitTracker, StepCounter, RewardSum and the transforms a trainer hands in: its model's
state primers, a reward-shaping transform), and the env's unbatched specs (:func:`probe_specs`) that factories build
policies from. ``env.imports`` are imported first, so a user's own package can register its gymnasium ids. A config
asking for an entry the adapter cannot compute (:data:`ENV_WRITTEN`, ``EnvAdapter.writes``) is refused when it is
loaded (:func:`check_env_writes`, called by the trainer's validator).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
from collections.abc import Sequence
from typing import Any

from torchrl.envs import Compose, EnvBase, InitTracker, RewardSum, SerialEnv, StepCounter, TransformedEnv

from freamer_rl.errors import ConfigError
from freamer_rl.run import env_registry
from freamer_rl.run.corruption import copy_transforms, presence_transforms

__all__ = [
    "ENV_WRITTEN",
    "check_env_writes",
    "check_env_options",
    "eval_config",
    "import_env_modules",
    "env_options",
    "make_single_env",
    "make_batched_env",
    "probe_specs",
]

#: Config fields whose non-zero value asks the env for an entry that only some adapters compute (those listing it
#: in ``EnvAdapter.writes``): dotted field -> (entry, what it is). A field a trainer's schema lacks asks for nothing.
ENV_WRITTEN: dict[str, tuple[str, str]] = {
    "shaping.language.weight": ("lang_reward", "R_lang, which parses a MiniGrid mission and reads MiniGrid's grid"),
}


def _dotted(cfg: Any, dotted: str) -> Any:
    node = cfg
    for part in dotted.split("."):
        node = getattr(node, part, None)
    return node


def check_env_writes(cfg: Any) -> None:
    """One ConfigError line for a field of :data:`ENV_WRITTEN` that is on while ``env.adapter`` cannot compute its
    entry (e.g. ``shaping.language.weight`` on Crafter, which has no mission)."""
    adapter = env_registry.get_adapter(cfg.env.adapter)
    for dotted, (entry, what) in ENV_WRITTEN.items():
        value = _dotted(cfg, dotted)
        if value and entry not in adapter.writes:
            able = [n for n in sorted(env_registry.available_adapters()) if entry in env_registry.get_adapter(n).writes]
            raise ConfigError(
                f"{dotted}: got {value}, but env.adapter '{cfg.env.adapter}' cannot provide {what} ('{entry}'); set "
                f"{dotted}=0" + (f" or use env.adapter {' / '.join(able)}" if able else "")
            )


def import_env_modules(env: Any) -> None:
    """Import every module of ``env.imports`` (a module that registers gymnasium ids on import); one ConfigError
    line naming the module when it cannot be imported."""
    _import_modules(env.imports)


def _import_modules(names: Sequence[str]) -> None:
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError as err:
            raise ConfigError(
                f"env.imports: cannot import {name!r} ({err}); is it installed or on PYTHONPATH?"
            ) from None


def check_env_options(cfg: Any) -> None:
    """One ConfigError line for a key of ``env.options`` / ``env.eval_options`` that the adapter does not declare
    (``EnvAdapter.option_names``): it would be ignored or fail deep inside the env factory."""
    adapter = env_registry.get_adapter(cfg.env.adapter)
    for section in ("options", "eval_options"):
        for name in getattr(cfg.env, section, {}) or {}:
            if name not in adapter.option_names:
                takes = ", ".join(adapter.option_names) or "none"
                raise ConfigError(
                    f"env.{section}.{name}: the {cfg.env.adapter!r} adapter takes no option {name!r} "
                    f"(options it takes: {takes})"
                )


def env_options(cfg: Any) -> dict[str, Any]:
    """Adapter keyword options: those the adapter derives from the config (``EnvAdapter.options``), then the
    recipe's own ``env.options`` (checked by :func:`check_env_options`).

    Raises:
        ConfigError: ``env.reset_workers`` > 0 for an adapter that does not take it (it would be ignored); an
            ``env.options`` key the adapter does not declare.
    """
    options = env_registry.get_adapter(cfg.env.adapter).options(cfg)
    workers = getattr(cfg.env, "reset_workers", 0)
    if workers and "reset_workers" not in options:
        raise ConfigError(
            f"env.reset_workers={workers}: the {cfg.env.adapter!r} adapter prepares no resets in workers (Crafter "
            "does); set env.reset_workers=0"
        )
    check_env_options(cfg)
    return {**options, **(getattr(cfg.env, "options", {}) or {})}


def eval_config(cfg: Any) -> Any:
    """``cfg`` with ``env.eval_options`` laid over ``env.options``: the config of every evaluation env (e.g. a
    subject left out of training). The same object when there are none."""
    extra = getattr(cfg.env, "eval_options", {}) or {}
    if not extra:
        return cfg
    env = dataclasses.replace(cfg.env, options={**cfg.env.options, **extra}, eval_options={})
    return dataclasses.replace(cfg, env=env)


def make_single_env(cfg: Any, seed: int | None = None) -> EnvBase:
    """One env of the config (with its ``env.copies`` sensors)."""
    import_env_modules(cfg.env)
    env = env_registry.make_env(cfg.env.adapter, cfg.env.id, seed=seed, **env_options(cfg))
    copies = copy_transforms(getattr(cfg.env, "copies", {}), getattr(cfg.env, "clean_copies", ()))
    copies += presence_transforms(getattr(cfg.env, "presence", ()))
    return TransformedEnv(env, Compose(*copies)) if copies else env


def _single_env_fn(adapter: str, env_id: str, options: dict, imports: tuple[str, ...]) -> EnvBase:
    _import_modules(imports)  # in a worker process the user's registering modules are not imported yet
    return env_registry.make_env(adapter, env_id, **options)


def make_batched_env(cfg: Any, transforms: list, seed: int, num_envs: int | None = None) -> EnvBase:
    """``num_envs`` (default ``env.num_envs``) copies in one process (2 cores do not profit from ParallelEnv): the
    adapter's own batched env when it has one (``EnvAdapter.make_batched_env``), else a SerialEnv of single envs;
    then the ``env.copies`` sensors, InitTracker, StepCounter, RewardSum, copies of ``transforms`` (after
    RewardSum, so episode returns stay the env's own) and the ``env.presence`` flags (after any corruption)."""
    import_env_modules(cfg.env)
    n = num_envs or cfg.env.num_envs
    adapter = env_registry.get_adapter(cfg.env.adapter)
    if adapter.make_batched_env is not None:
        base = adapter.make_batched_env(cfg.env.id, n, **env_options(cfg))
    else:
        make = functools.partial(_single_env_fn, cfg.env.adapter, cfg.env.id, env_options(cfg), tuple(cfg.env.imports))
        base = SerialEnv(n, make)
    copies = copy_transforms(getattr(cfg.env, "copies", {}), getattr(cfg.env, "clean_copies", ()))
    env = TransformedEnv(
        base,
        Compose(
            *copies,
            InitTracker(),
            StepCounter(),
            RewardSum(),
            *[t.clone() for t in transforms],
            *presence_transforms(getattr(cfg.env, "presence", ())),
        ),
    )
    env.set_seed(seed)
    return env


def probe_specs(cfg: Any):
    """Unbatched observation and action specs of the configured env (also validates the env id)."""
    env = make_single_env(cfg)
    try:
        return env.observation_spec.clone(), env.action_spec.clone()
    finally:
        env.close()
