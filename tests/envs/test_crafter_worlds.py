"""Crafter worlds generated ahead in worker processes (``env.reset_workers``): the same worlds and frames as crafter's
own reset, a new seed discards the prefetched world, worker failures surface, adapters without the option refuse it.

Every test uses a 32 x 32 world (a fraction of the benchmark's generation time) and a few episodes of 6 steps
(crafter's creature balancing, which iterates sets in memory order, starts at step 10: before it, trajectories replay
exactly).
"""

from __future__ import annotations

import importlib.util
import os
import threading
import types

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from freamer_rl.errors import ConfigError, EnvSetupError
from freamer_rl.experiments.workers import worker_pool
from freamer_rl.run.envs import env_options
from freamer_rl.trainers.minigrid_ppo import FreamerConfig

HAS_CRAFTER = importlib.util.find_spec("crafter") is not None
pytestmark = pytest.mark.skipif(not HAS_CRAFTER, reason='crafter is not installed: pip install -e ".[crafter]"')

SMALL = {"area": 32, "length": 6}


def play(env, episodes: int, steps: int) -> tuple[list[torch.Tensor], list[np.ndarray]]:
    """Frames, inventories and rewards of ``episodes`` episodes of fixed actions, and each episode's material map."""
    seen, maps = [], []
    td = env.reset()
    for e in range(episodes):
        seen.append(td["pixels"].clone())
        maps.append(env._env._world._mat_map.copy())
        for t in range(steps):
            td = env.step(td.set("action", torch.tensor((7 * t + e) % 17)))
            nxt = td["next"]
            seen += [nxt["pixels"].clone(), nxt["inventory"].clone(), nxt["reward"].clone()]
            td = nxt
        td = env.reset()
    return seen, maps


def test_prefetched_worlds_are_crafters_own():
    from freamer_rl_envs.crafter import CrafterEnv

    inline, inline_maps = play(CrafterEnv(seed=5, **SMALL), episodes=3, steps=6)
    env = CrafterEnv(seed=5, reset_workers=1, **SMALL)
    ahead, ahead_maps = play(env, episodes=3, steps=6)
    assert len(ahead) == len(inline) == 3 * (1 + 3 * 6)
    for i, (a, b) in enumerate(zip(inline, ahead, strict=True)):
        assert torch.equal(a, b), f"entry {i} differs"
    for a, b in zip(inline_maps, ahead_maps, strict=True):
        np.testing.assert_array_equal(a, b)
    assert len({m.tobytes() for m in ahead_maps}) == 3  # three different worlds, not one installed thrice
    assert env._env._episode == 4  # the episode counter continues as crafter's would (reset after the 3rd)
    check_env_specs(env)
    env.close()


def test_a_new_seed_discards_the_prefetched_world():
    from freamer_rl_envs.crafter import CrafterEnv

    env = CrafterEnv(seed=5, reset_workers=1, **SMALL)
    env.reset()  # episode 1 of seed 5; episode 2 is being generated
    env.set_seed(9)
    first = env.reset()["pixels"]
    fresh = CrafterEnv(seed=9, **SMALL).reset()["pixels"]
    assert torch.equal(first, fresh)
    assert env._env._seed == 9 and env._env._episode == 1


def test_a_failing_worker_is_raised_at_the_reset():
    from freamer_rl_envs.crafter_worlds import WorldPrefetcher

    worlds = WorldPrefetcher(1, {"area": (32, 32), "colour": "red"})  # crafter.Env takes no such argument
    worlds.request(seed=1, episode=1)
    with pytest.raises(TypeError, match="colour"):
        worlds.take(seed=1, episode=1)
    assert worlds.take(seed=1, episode=1) is None  # the failed request is gone: the next reset is inline


def test_a_request_for_another_world_is_not_used():
    from freamer_rl_envs.crafter_worlds import WorldPrefetcher

    worlds = WorldPrefetcher(1, {"area": (32, 32)})
    worlds.request(seed=1, episode=2)
    assert worlds.take(seed=1, episode=3) is None
    assert worlds.take(seed=1, episode=2) is None  # taken (and dropped) by the mismatched take


def test_checks():
    from freamer_rl_envs.crafter import CrafterEnv
    from freamer_rl_envs.crafter_worlds import WorldPrefetcher, check_crafter_internals

    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="reset_workers"):
            CrafterEnv(reset_workers=bad)
    with pytest.raises(ValueError, match="reset_workers"):
        WorldPrefetcher(0, {})
    with pytest.raises(EnvSetupError, match="_local_view._world"):
        check_crafter_internals(types.SimpleNamespace(_seed=1, _episode=0, _local_view=None))


def test_the_option_reaches_crafter_and_other_adapters_refuse_it():
    cfg = FreamerConfig()
    cfg.env.adapter, cfg.env.id, cfg.env.reset_workers = "crafter", "CrafterReward-v1", 2
    assert env_options(cfg)["reset_workers"] == 2
    cfg.env.adapter, cfg.env.id = "minigrid", "MiniGrid-Empty-5x5-v0"
    with pytest.raises(ConfigError, match=r"env.reset_workers=2: the 'minigrid' adapter"):
        env_options(cfg)
    cfg.env.reset_workers = 0
    assert "reset_workers" not in env_options(cfg)


def _reset_in_a_worker(payload: dict) -> dict:
    """A suite job: a prefetching env resets twice, so its process holds an idle world worker when the job ends."""
    from freamer_rl_envs.crafter import CrafterEnv

    env = CrafterEnv(seed=payload["seed"], reset_workers=1, **SMALL)
    env.reset()
    env.reset()
    env.close()
    return {"ok": True, "pid": os.getpid()}


def test_a_suite_worker_with_world_workers_exits():
    """A multiprocessing child joins its children before the executor's exit hook would stop them: without the
    prefetcher's finalizer a suite that ran a Crafter job waited forever at its end (seen on robustness_crafter)."""
    done = threading.Event()
    result: dict = {}

    def run() -> None:
        with worker_pool(1) as pool:
            result.update(pool.submit(_reset_in_a_worker, {"seed": 3}).result(timeout=120))
        done.set()  # the pool's shutdown returned: its worker and the worker's world pool exited

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert done.wait(timeout=180), "the suite's worker pool did not shut down (a world worker kept its parent alive)"
    assert result["ok"] and result["pid"] != os.getpid()
