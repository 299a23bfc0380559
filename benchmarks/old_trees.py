"""Older commits' trees as the throughput benchmark's worker imports them (``throughput_benchmark.py``).

Trees before be0f9cc have a flat top level (``freamer_rl.config``, ``freamer_rl.train``, ``freamer_rl.env_registry``);
older ones still ship the adapters as the top-level package ``envs`` and have no public trainer seams (411f9a7).
"""

from __future__ import annotations

import importlib
from pathlib import Path


def patch_legacy_adapters(tree: Path) -> bool:
    """Old trees ship the adapters as the top-level package ``envs``; the installed entry point names the current
    ``freamer_rl_envs``, which old code cannot import. Point the registry at the tree's own MiniGrid factory."""
    if not (tree / "envs" / "minigrid.py").is_file():
        return False
    import envs.minigrid  # noqa: PLC0415 (from the old tree, via PYTHONPATH)

    env_registry = from_tree("freamer_rl.run.env_registry", "freamer_rl.env_registry")
    env_registry.get_env_factory = lambda adapter: envs.minigrid.make_minigrid_env
    return True


def from_tree(module: str, flat: str, name: str | None = None):
    """``module`` (or its attribute ``name``) from the imported tree; trees before be0f9cc (the tiered
    sub-packages) have it at the flat top-level path ``flat``."""
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError:
        mod = importlib.import_module(flat)
    return mod if name is None else getattr(mod, name)


def seam(trainer, public: str, private: str):
    """``trainer``'s public seam, or the private method it wraps on an older tree (411f9a7 has no public seams)."""
    fn = getattr(trainer, public, None)
    return fn if callable(fn) else getattr(trainer, private)
