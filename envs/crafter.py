"""Crafter adapter: a TorchRL :class:`~torchrl.envs.EnvBase` around ``crafter.Env`` (danijar/crafter >= 1.8).

Crafter speaks the old gym API (``reset() -> obs``; ``step(a) -> (obs, reward, done, info)``) and is not a
gymnasium env, so :class:`CrafterEnv` talks to it directly and writes these keys (unbatched shapes, ``S = size``,
64 by default):

=====================  ======================  ==================================================================
key                    dtype / shape           meaning
=====================  ======================  ==================================================================
``"pixels"``           uint8 ``[S, S, 3]``     RGB observation (local 9x7 view above a 9x2 inventory strip); the
                                               vision modality
``"inventory"``        float32 ``[16]``        inventory counts in :data:`CRAFTER_INVENTORY` order (health, food,
                                               drink, energy, then materials and tools; each in ``[0, 9]``); the
                                               agent's state, read by the ``vector`` modality
``"achievements"``     bool ``[22]``           achievements unlocked so far in this episode, in
                                               :data:`CRAFTER_ACHIEVEMENTS` order (crafter's own, alphabetical)
``"reward_history"``   float32 ``[H]``         last ``H`` rewards, most recent last, zeros after reset (left out
                                               with ``reward_history=0``)
=====================  ======================  ==================================================================

plus ``"reward"`` float32 ``[1]`` and ``"done"`` / ``"terminated"`` / ``"truncated"`` bool ``[1]``; the action is
``Categorical(17)`` (crafter's ``constants.actions``: noop, 4 moves, do, sleep, 4 place, 6 make). There is no
language modality.

A recipe maps the observations with ``model.modalities: [vision, vector, reward]`` and
``model.observation_keys: {vector: [inventory]}`` (the ``state`` modality is MiniGrid's symbolic-grid encoder and
needs ``grid`` + ``direction``).

Reward (``CrafterReward-v1``): +1 the first time each achievement is unlocked in an episode, plus the change of
health / 10 every step; ``CrafterNoReward-v1`` pays 0 (the ``"achievements"`` entry is the same).

Episode ends: crafter ends an episode at death (health 0: ``terminated``, its ``info["discount"] == 0``) or when the
step counter reaches ``length`` (``truncated``; a death on that very step counts as ``terminated`` only).

``"achievements"`` and ``"reward_history"`` at ``("next", ...)`` already include the step that produced them, so the
``("next", "achievements")`` of an episode's last step lists everything that episode unlocked: this is what
:class:`freamer_rl.run.crafter_score.CrafterScore` reads to compute the official Crafter score.

**Success**: none. Crafter has 22 achievements and no single goal; the trainer reports returns, and the Crafter score
(geometric mean of per-achievement success rates, :mod:`freamer_rl.run.crafter_score`) is the task's metric.

Seeding: crafter takes its seed only at construction and derives episode ``k``'s world from ``(seed, k)``. So
``set_seed(s)`` (or ``make_crafter_env(..., seed=s)``) builds a fresh ``crafter.Env(seed=s)`` at the next reset, and
later resets continue its episode counter: the same seed gives the same sequence of worlds. Without any seed the
adapter draws one from the OS's entropy (not from numpy's global state as crafter would: forked workers share it).
``SerialEnv`` / ``ParallelEnv`` hand every worker a different seed derived from the one given to their ``set_seed``.
Same seed and same actions replay the same steps only until crafter's first creature balancing (step 10): it then
iterates Python sets of creatures ordered by memory address, so longer trajectories can diverge between two runs --
a property of crafter itself (danijar/crafter#36), shared by the raw env, that this adapter does not patch.

Cost (one core of a busy 2-core machine): a reset generates a whole 64x64 world, about 0.5 s; a step takes about
0.75 ms in crafter plus under 0.1 ms for this adapter and TorchRL's step bookkeeping. Early in training (a random
agent dies after ~150-200 steps) resets take most of the time. ``reset_workers=k`` (``env.reset_workers`` in a
recipe; the Crafter recipes use 1) generates each env's next world in a pool of ``k`` processes while the current
episode runs (:mod:`freamer_rl_envs.crafter_worlds`): the same worlds, off the critical path. The pool is started
with ``spawn``, so a script that builds such an env needs the ``if __name__ == "__main__":`` guard.

Batched use needs picklable factories (``ParallelEnv`` spawns workers)::

    import functools
    from torchrl.envs import EnvCreator, ParallelEnv
    from freamer_rl_envs.crafter import make_crafter_env

    if __name__ == "__main__":
        env = ParallelEnv(4, EnvCreator(functools.partial(make_crafter_env, "CrafterReward-v1")))
"""

from __future__ import annotations

import difflib
import logging
import secrets
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from freamer_rl.errors import EnvSetupError
from freamer_rl.run.env_registry import EnvAdapter
from freamer_rl_envs.crafter_worlds import WorldPrefetcher, check_crafter_internals, install_world
from freamer_rl_envs.single_env import finish_td, unchanged_reset

try:
    import crafter
except ImportError as _err:  # reported (one line) when an env is built: the module stays importable for its constants
    crafter = None
    _CRAFTER_IMPORT_ERROR: str | None = f"{type(_err).__name__}: {_err}"
else:
    _CRAFTER_IMPORT_ERROR = None

logger = logging.getLogger(__name__)

__all__ = [
    "ADAPTER",
    "CRAFTER_ACHIEVEMENTS",
    "CRAFTER_ENV_IDS",
    "CRAFTER_INVENTORY",
    "CrafterEnv",
    "CrafterNotInstalledError",
    "make_crafter_env",
]

#: Ids accepted by the adapter (crafter's own gym registrations) -> crafter's ``reward`` flag.
CRAFTER_ENV_IDS: dict[str, bool] = {"CrafterReward-v1": True, "CrafterNoReward-v1": False}
DEFAULT_ENV_ID = "CrafterReward-v1"
N_ACTIONS = 17
_MAX_SEED = 2**31 - 1

#: Order of the ``"inventory"`` entries (crafter's ``constants.items``; every count is clamped to ``[0, 9]``).
CRAFTER_INVENTORY: tuple[str, ...] = (
    "health",
    "food",
    "drink",
    "energy",
    "sapling",
    "wood",
    "stone",
    "coal",
    "iron",
    "diamond",
    "wood_pickaxe",
    "stone_pickaxe",
    "iron_pickaxe",
    "wood_sword",
    "stone_sword",
    "iron_sword",
)
INVENTORY_MAX = 9.0

#: Order of the ``"achievements"`` entries (crafter's ``constants.achievements``, alphabetical).
CRAFTER_ACHIEVEMENTS: tuple[str, ...] = (
    "collect_coal",
    "collect_diamond",
    "collect_drink",
    "collect_iron",
    "collect_sapling",
    "collect_stone",
    "collect_wood",
    "defeat_skeleton",
    "defeat_zombie",
    "eat_cow",
    "eat_plant",
    "make_iron_pickaxe",
    "make_iron_sword",
    "make_stone_pickaxe",
    "make_stone_sword",
    "make_wood_pickaxe",
    "make_wood_sword",
    "place_furnace",
    "place_plant",
    "place_stone",
    "place_table",
    "wake_up",
)


class CrafterNotInstalledError(EnvSetupError, ImportError):
    """The ``crafter`` package is missing (an :class:`ImportError`; the CLI prints it as one ``error:`` line)."""


def _require_crafter() -> Any:
    """The ``crafter`` module, checked against the key orders this adapter documents."""
    if crafter is None:
        raise CrafterNotInstalledError(
            f'the crafter adapter needs the crafter package: pip install -e ".[crafter]" ({_CRAFTER_IMPORT_ERROR})'
        )
    consts = crafter.constants
    if tuple(consts.items) != CRAFTER_INVENTORY or tuple(consts.achievements) != CRAFTER_ACHIEVEMENTS:
        raise EnvSetupError(
            f"crafter {getattr(crafter, '__version__', '?')} has inventory {list(consts.items)} and achievements "
            f"{list(consts.achievements)}; this adapter expects {list(CRAFTER_INVENTORY)} and "
            f"{list(CRAFTER_ACHIEVEMENTS)} (install crafter 1.8.x)"
        )
    if len(consts.actions) != N_ACTIONS:
        raise EnvSetupError(f"crafter has {len(consts.actions)} actions, this adapter expects {N_ACTIONS}")
    return crafter


def _check_env_id(env_id: str) -> None:
    if env_id in CRAFTER_ENV_IDS:
        return
    close = difflib.get_close_matches(env_id, list(CRAFTER_ENV_IDS), n=2, cutoff=0.5)
    hint = f"did you mean {', '.join(repr(c) for c in close)}? " if close else ""
    raise ValueError(f"unknown Crafter env id '{env_id}': {hint}valid ids are {', '.join(CRAFTER_ENV_IDS)}")


def _pair(name: str, value: int | tuple[int, int] | list[int], minimum: int) -> tuple[int, int]:
    pair = tuple(value) if isinstance(value, (tuple, list)) else (value, value)
    if len(pair) != 2 or any(int(v) != v or v < minimum for v in pair):
        raise ValueError(f"{name}: expected an integer >= {minimum} or a pair of them, got {value!r}")
    return int(pair[0]), int(pair[1])


class CrafterEnv(EnvBase):
    """Unbatched TorchRL env around one ``crafter.Env`` (see the module docstring for the keys).

    Args:
        env_id: ``"CrafterReward-v1"`` (the benchmark's reward) or ``"CrafterNoReward-v1"`` (reward 0).
        seed: if given, seeds the first reset (same as calling :meth:`set_seed`).
        reward_history: length ``H`` of ``"reward_history"`` (0 leaves the key out).
        length: episode step limit (crafter's ``length``; 10,000 in the benchmark); reaching it sets ``truncated``.
        size: frame size ``S`` of ``"pixels"``, an int or crafter's ``(width, height)`` (frames are
            ``[height, width, 3]``); 64 in the benchmark.
        area: world size in cells, an int or ``(x, y)`` (64 in the benchmark).
        view: cells shown, an int or ``(x, y)`` (9 in the benchmark: 9 x 7 of world above 9 x 2 of inventory).
        reset_workers: > 0: the next episode's world is generated ahead in a pool of this many processes (shared by
            every Crafter env of the process; :mod:`freamer_rl_envs.crafter_worlds`), so a reset does not wait for
            world generation; the worlds are the same. 0: crafter's own reset, inline.
        device: device of the output tensors.

    Raises:
        CrafterNotInstalledError: crafter is not installed.
        ValueError: unknown env id or invalid option.
    """

    batch_locked = True

    def __init__(
        self,
        env_id: str = DEFAULT_ENV_ID,
        *,
        seed: int | None = None,
        reward_history: int = 8,
        length: int = 10000,
        size: int | tuple[int, int] = 64,
        area: int | tuple[int, int] = 64,
        view: int | tuple[int, int] = 9,
        reset_workers: int = 0,
        device: torch.device | str = "cpu",
    ) -> None:
        self._crafter = _require_crafter()
        _check_env_id(env_id)
        if int(reward_history) != reward_history or reward_history < 0:
            raise ValueError(f"reward_history: expected an integer >= 0, got {reward_history!r}")
        if int(length) != length or length < 1:
            raise ValueError(f"length: expected an integer >= 1, got {length!r}")
        if int(reset_workers) != reset_workers or reset_workers < 0:
            raise ValueError(f"reset_workers: expected an integer >= 0, got {reset_workers!r}")
        super().__init__(device=device, batch_size=torch.Size([]))
        self.env_id = env_id
        self.reward_history = int(reward_history)
        self.length = int(length)
        self._env_kwargs = {
            "area": _pair("area", area, 9),
            "view": _pair("view", view, 3),
            "size": _pair("size", size, 9),
            "reward": CRAFTER_ENV_IDS[env_id],
            "length": self.length,
        }
        self._out_device = torch.device(self.device) if self.device is not None else torch.device("cpu")
        self._make_specs()
        self._worlds = WorldPrefetcher(reset_workers, self._env_kwargs) if reset_workers else None

        # mutable state: the crafter env is built at the first reset (and again at the reset after a set_seed)
        self._env: Any = None
        self._pending_seed: int | None = None
        self._history: list[float] = [0.0] * self.reward_history
        self._last_obs: TensorDictBase | None = None
        self._initial_inventory = torch.tensor(
            [self._crafter.constants.items[k]["initial"] for k in CRAFTER_INVENTORY], dtype=torch.float32
        )
        self._no_achievements = torch.zeros(len(CRAFTER_ACHIEVEMENTS), dtype=torch.bool)
        self._false = torch.zeros(1, dtype=torch.bool)
        self._true = torch.ones(1, dtype=torch.bool)
        if seed is not None:
            self.set_seed(seed)

    def _make_specs(self) -> None:
        width, height = self._env_kwargs["size"]  # crafter's order; its frames are [height, width, 3]
        obs = {
            "pixels": Bounded(low=0, high=255, shape=(height, width, 3), dtype=torch.uint8, device=self.device),
            "inventory": Bounded(
                low=0.0, high=INVENTORY_MAX, shape=(len(CRAFTER_INVENTORY),), dtype=torch.float32, device=self.device
            ),
            "achievements": Categorical(2, shape=(len(CRAFTER_ACHIEVEMENTS),), dtype=torch.bool, device=self.device),
        }
        if self.reward_history:
            obs["reward_history"] = Unbounded(shape=(self.reward_history,), dtype=torch.float32, device=self.device)
        self.observation_spec = Composite(obs, shape=())
        self.action_spec = Categorical(N_ACTIONS, shape=(), dtype=torch.int64, device=self.device)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(1,), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, shape=(1,), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, shape=(1,), dtype=torch.bool, device=self.device),
            shape=(),
        )

    # --------------------------------------------------------------------------------------------------------------
    # helpers
    # --------------------------------------------------------------------------------------------------------------
    def _observation(self, pixels: np.ndarray, inventory: torch.Tensor, achievements: torch.Tensor) -> dict:
        # crafter renders a fresh canvas every step and hands out a transposed view of it: wrapped without a copy
        # (a strided tensor; stacking, collectors and ParallelEnv's shared buffers copy it anyway, and a contiguous
        # copy here would cost ~10 us, over 1% of a step)
        out = {"pixels": torch.from_numpy(pixels), "inventory": inventory, "achievements": achievements}
        if self.reward_history:
            out["reward_history"] = torch.tensor(self._history, dtype=torch.float32)
        return out

    def _finish(self, out: dict[str, Any]) -> TensorDictBase:
        return finish_td(out, self._out_device)

    # --------------------------------------------------------------------------------------------------------------
    # EnvBase API
    # --------------------------------------------------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        same = unchanged_reset(self, tensordict, self._last_obs)
        if same is not None:  # a "_reset" mask that resets nothing
            return same
        if self._env is None or self._pending_seed is not None:
            seed, self._pending_seed = self._pending_seed, None
            if seed is None:
                # crafter would draw from numpy's global state, which forked workers share (identical worlds)
                seed = secrets.randbelow(_MAX_SEED)
                logger.debug("%s: unseeded, drew crafter seed %d", self.env_id, seed)
            self._env = self._crafter.Env(seed=seed, **self._env_kwargs)
            if self._worlds is not None:
                check_crafter_internals(self._env)
        pixels = self._reset_world()
        if self.reward_history:
            self._history = [0.0] * self.reward_history
        # crafter's reset returns no info: a new player holds the initial inventory and no achievements
        out = self._observation(pixels, self._initial_inventory.clone(), self._no_achievements.clone())
        out["done"] = self._false.clone()
        out["terminated"] = self._false.clone()
        out["truncated"] = self._false.clone()
        td = self._finish(out)
        self._last_obs = td
        return td

    def _reset_world(self) -> np.ndarray:
        """Crafter's reset, or with ``reset_workers`` the prefetched world of the next episode (then the one after
        it is requested); returns the first frame."""
        env = self._env
        if self._worlds is None:
            return env.reset()
        episode = env._episode + 1
        payload = self._worlds.take(env._seed, episode)
        pixels = env.reset() if payload is None else install_world(env, payload, episode)
        self._worlds.request(env._seed, episode + 1)
        return pixels

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        pixels, reward, done, info = self._env.step(int(tensordict.get("action")))
        reward = float(reward)
        if self.reward_history:
            history = self._history
            del history[0]
            history.append(reward)
        inventory, counts = info["inventory"], info["achievements"]
        out = self._observation(
            pixels,
            torch.tensor([inventory[k] for k in CRAFTER_INVENTORY], dtype=torch.float32),
            torch.tensor([counts[k] > 0 for k in CRAFTER_ACHIEVEMENTS], dtype=torch.bool),
        )
        terminated = info["discount"] == 0.0  # death
        out["reward"] = torch.tensor((reward,), dtype=torch.float32)
        out["terminated"] = self._true.clone() if terminated else self._false.clone()
        out["truncated"] = self._true.clone() if (done and not terminated) else self._false.clone()
        out["done"] = self._true.clone() if done else self._false.clone()
        td = self._finish(out)
        self._last_obs = td
        return td

    def _set_seed(self, seed: int | None) -> None:
        """Build a fresh ``crafter.Env(seed=seed)`` at the next reset (``None`` keeps the current one going)."""
        self._pending_seed = None if seed is None else int(seed)
        if self._worlds is not None and seed is not None:
            self._worlds.request(self._pending_seed, 1)  # the first world of the new seed, ahead of the reset

    def close(self, *, raise_if_closed: bool = True) -> None:
        self.__dict__["_env"] = None  # crafter.Env holds no OS resources
        if self.__dict__.get("_worlds") is not None:
            self._worlds.cancel()
        super().close(raise_if_closed=raise_if_closed)

    def __repr__(self) -> str:
        kw = self._env_kwargs
        return (
            f"{type(self).__name__}(env_id={self.env_id!r}, reward_history={self.reward_history}, "
            f"length={self.length}, size={kw['size']}, area={kw['area']}, view={kw['view']}, "
            f"reset_workers={self._worlds.workers if self._worlds else 0}, device={self.device})"
        )


def make_crafter_env(env_id: str = DEFAULT_ENV_ID, **options: Any) -> EnvBase:
    """Build one unbatched :class:`CrafterEnv` (the ``crafter`` entry point of the ``freamer_rl.envs`` group);
    ``options`` are its keyword arguments (``seed``, ``reward_history``, ``length``, ``size``, ``area``, ``view``,
    ``reset_workers``, ``device``).

    Picklable through ``functools.partial(make_crafter_env, env_id, ...)``, so it can feed ``SerialEnv``,
    ``ParallelEnv`` (wrap it in ``EnvCreator``) and TorchRL collectors.

    Raises:
        CrafterNotInstalledError: crafter is not installed (one line: ``pip install -e ".[crafter]"``).
        ValueError: unknown env id (with close matches) or invalid option.
    """
    return CrafterEnv(env_id, **options)


def _crafter_options(cfg: Any) -> dict[str, Any]:
    """Adapter options implied by a trainer's config (the benchmark's world otherwise)."""
    return {"reward_history": cfg.env.reward_history, "reset_workers": cfg.env.reset_workers}


#: The ``crafter`` entry point of the ``freamer_rl.envs`` group. No success rule: Crafter has no single goal (see
#: the module docstring); its metric is the Crafter score of :mod:`freamer_rl.run.crafter_score`.
ADAPTER = EnvAdapter(
    make_env=make_crafter_env, options=_crafter_options, success=None, achievements=CRAFTER_ACHIEVEMENTS
)
