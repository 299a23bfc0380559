"""Find environment adapters through the ``freamer_rl.envs`` entry-point group.

The library never imports the top-level ``envs`` package: adapters register themselves in ``pyproject.toml``
(``minigrid = "freamer_rl_envs.minigrid:make_minigrid_env"``) and any third-party package can add its own.
An adapter is a callable ``factory(env_id, *, seed=None, **options) -> torchrl.envs.EnvBase``.
"""

from __future__ import annotations

import functools
from importlib.metadata import entry_points
from typing import Any, Callable

from freamer_rl.errors import EnvSetupError

ENTRY_POINT_GROUP = "freamer_rl.envs"


@functools.cache
def available_adapters() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def get_env_factory(adapter: str) -> Callable[..., Any]:
    adapters = available_adapters()
    if adapter not in adapters:
        known = ", ".join(sorted(adapters)) or "none (is the project installed? pip install -e .)"
        raise EnvSetupError(f"env.adapter: unknown adapter '{adapter}' (installed adapters: {known})")
    return adapters[adapter].load()


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
