"""Crafter worlds generated ahead of time in worker processes, so a reset does not wait for world generation.

A Crafter reset builds a whole world (``crafter.worldgen.generate_world``: ~4,000 cells, each a handful of simplex
noise calls in Python): 0.5-2 s on one core of a 2-core machine, against ~1 ms for a step. A random agent dies after
~170 steps, so resets take most of an env's time early in training (measured: 82% of the raw env's time, 56-59% of a
FreamerV1 collection batch). Crafter derives episode ``k``'s world from ``hash((seed, k))`` alone, so the next
episode's world is known before the current one ends: :class:`WorldPrefetcher` generates it in a process pool while
the agent plays and the learner trains, and :func:`install_world` finishes the reset with it. The world is the one
crafter's own ``reset()`` would build (the same material map, objects, random state and first frame; tested
against the inline reset).

:func:`install_world` sets private attributes of ``crafter.Env`` (the world its views read, the episode counter):
:func:`check_crafter_internals` checks they exist when a prefetching env is built, so a crafter release that renames
them fails there in one line rather than rendering a stale world.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.util
import os
import pickle
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

from freamer_rl.errors import EnvSetupError

__all__ = ["WorldPrefetcher", "check_crafter_internals", "generate_world", "install_world"]

#: ``crafter.Env`` attributes :func:`install_world` writes (views: the world they render / read)
_ENV_ATTRIBUTES = (
    "_seed",
    "_episode",
    "_step",
    "_world",
    "_player",
    "_last_health",
    "_unlocked",
    "_local_view",
    "_sem_view",
)

#: (process id, workers) -> the pool of this process (a forked child does not reuse its parent's pool)
_POOLS: dict[tuple[int, int], ProcessPoolExecutor] = {}


def generate_world(seed: int, episode: int, env_kwargs: dict[str, Any]) -> bytes:
    """Episode ``episode``'s world of ``crafter.Env(seed=seed, **env_kwargs)``, pickled ``(world, player)``.

    Runs in a pool worker: crafter's own ``reset()`` with the episode counter set, so the world comes from crafter's
    code and its seed rule (``hash((seed, episode))``), nothing re-implemented here.
    """
    import crafter  # in the worker process only

    env = crafter.Env(seed=seed, **env_kwargs)
    env._episode = episode - 1  # reset() increments it first
    env.reset()
    return pickle.dumps((env._world, env._player), protocol=pickle.HIGHEST_PROTOCOL)


def check_crafter_internals(env: Any) -> None:
    """Raise :class:`EnvSetupError` unless ``env`` (a ``crafter.Env``) has what :func:`install_world` sets."""
    missing = [a for a in _ENV_ATTRIBUTES if not hasattr(env, a)]
    missing += [f"{v}._world" for v in ("_local_view", "_sem_view") if not hasattr(getattr(env, v, None), "_world")]
    if missing:
        raise EnvSetupError(
            f"env.reset_workers: this crafter release lacks {', '.join(missing)} (written by a prefetched reset); "
            "set env.reset_workers=0 or install crafter 1.8"
        )


def install_world(env: Any, payload: bytes, episode: int) -> Any:
    """Finish ``env``'s reset into episode ``episode`` with a world of :func:`generate_world`; returns the first
    frame (what ``crafter.Env.reset`` returns). Mirrors the end of crafter's ``reset()``."""
    world, player = pickle.loads(payload)
    env._episode = episode
    env._step = 0
    env._world = world
    env._local_view._world = world
    env._sem_view._world = world
    env._update_time()
    env._player = player
    env._last_health = player.health
    env._unlocked = set()
    return env._obs()


def _pool(workers: int) -> ProcessPoolExecutor:
    key = (os.getpid(), workers)
    pool = _POOLS.get(key)
    if pool is None:
        if multiprocessing.current_process().daemon:
            raise EnvSetupError(
                "env.reset_workers: this env runs in a daemonic process, which cannot start the world workers; "
                "set env.reset_workers=0 there"
            )
        # spawn: the learner's process holds torch threads and locks a fork would copy
        pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        _POOLS[key] = pool
        # A multiprocessing child (a suite worker, a collector process) joins its non-daemon children when it exits,
        # before the executor's own exit hook would stop them, so it would wait forever on idle world workers. A
        # finalizer with an exit priority runs before that join (and at a plain interpreter exit too); above 10, so
        # before the call queue's own finalizer closes the feeder that must still carry the workers' stop sentinels.
        multiprocessing.util.Finalize(None, _close_pool, args=(key,), exitpriority=100)
    return pool


def _close_pool(key: tuple[int, int]) -> None:
    pool = _POOLS.pop(key, None)
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)


class WorldPrefetcher:
    """The next world of one crafter env, generated in a pool of ``workers`` processes shared by every env of this
    process (a batched env of 8 Crafter envs starts ``workers`` processes, not 8).

    ``request(seed, episode)`` starts generating; ``take(seed, episode)`` returns the pickled world if the last
    request was for exactly that world (waiting for it if it is not ready), else ``None`` (the caller resets inline).
    A failure in a worker is raised by ``take``.
    """

    def __init__(self, workers: int, env_kwargs: dict[str, Any]) -> None:
        if int(workers) != workers or workers < 1:
            raise ValueError(f"reset_workers: expected an integer >= 1, got {workers!r}")
        self.workers = int(workers)
        self.env_kwargs = dict(env_kwargs)
        self._pending: tuple[int, int, Future] | None = None

    def request(self, seed: int, episode: int) -> None:
        self.cancel()
        future = _pool(self.workers).submit(generate_world, int(seed), int(episode), self.env_kwargs)
        self._pending = (int(seed), int(episode), future)

    def take(self, seed: int, episode: int) -> bytes | None:
        pending, self._pending = self._pending, None
        if pending is None:
            return None
        if pending[:2] != (seed, episode):
            pending[2].cancel()
            return None
        return pending[2].result()

    def cancel(self) -> None:
        if self._pending is not None:
            self._pending[2].cancel()  # a world already being generated finishes in its worker, unused
            self._pending = None
