"""MiniGrid adapter: a TorchRL :class:`~torchrl.envs.EnvBase` around ``gymnasium.make("MiniGrid-...")``.

TorchRL's ``GymEnv`` cannot convert MiniGrid's ``MissionSpace``, so :class:`MiniGridEnv` talks to the gymnasium env
directly and writes the observation keys of ``docs/CONVENTIONS.md`` (unbatched shapes, ``V = agent view size``,
7 for every registered MiniGrid/BabyAI env):

=====================  ======================  ==================================================================
key                    dtype / shape           meaning
=====================  ======================  ==================================================================
``"grid"``             int64 ``[V, V, 3]``     symbolic partial view (object, colour, state) indices -- never /255
``"direction"``        int64 ``[]``            agent direction 0..3 (right, down, left, up)
``"mission_tokens"``   int64 ``[L]``           mission word ids from :data:`MINIGRID_VOCAB` (0 pad, 1 unknown)
``"mission"``          NonTensor ``str``       raw mission string (left out with ``include_mission=False``)
``"reward_history"``   float32 ``[H]``         last ``H`` rewards, most recent last, zeros after reset
``"pixels"``           uint8 ``[8V, 8V, 3]``   RGB agent view, tile size 8 (only with ``pixels=True``)
``"lang_reward"``      float32 ``[1]``         R_lang of Eq. A10 (only with ``language_reward={...}``, see below)
=====================  ======================  ==================================================================

``grid`` is indexed ``[x, y]`` (MiniGrid's convention; the agent sits at ``x = V // 2, y = V - 1`` facing up) while
``pixels`` is an ordinary ``[row, column]`` image of the same view. Grid values are bounded by
``minigrid.core.constants`` (object <= 10, colour <= 5, state <= 2); the agent's own cell shows what it carries.

plus ``"reward"`` float32 ``[1]`` and ``"done"`` / ``"terminated"`` / ``"truncated"`` bool ``[1]``; the action is
``Categorical(n=env.action_space.n)`` (7 for MiniGrid).

``lang_reward`` (:mod:`freamer_rl_envs.minigrid_language`) is 0 after a reset; at ``("next", "lang_reward")`` it is
the language-grounded reward of the step that produced it. It is an observation, not part of ``"reward"``: the
trainer's shaping adds ``weight * lang_reward``.

``reward_history`` at ``("next", ...)`` already contains the reward of the step that produced it: after step ``t``,
``td["next", "reward_history"][-1] == td["next", "reward"]``. The history of the root is therefore the history of
*previous* rewards, which is what a policy may condition on.

**Success** of an episode: it ended with ``terminated == True`` and ``reward > 0`` (MiniGrid pays
``1 - 0.9 * step_count / max_steps`` on reaching the goal and 0 otherwise; running out of steps sets ``truncated``).
Failures terminate with reward <= 0 (lava: 0; Dynamic-Obstacles collisions: -1).

Seeding: ``set_seed(s)`` (or ``make_minigrid_env(..., seed=s)``) seeds the gymnasium env at the next reset; later
resets continue its random stream, so the same seed and the same actions give the same episodes. ``SerialEnv`` /
``ParallelEnv`` hand every worker a different seed derived from the one given to their ``set_seed``.

Batched use needs picklable factories (``ParallelEnv`` spawns workers)::

    import functools
    from torchrl.envs import EnvCreator, ParallelEnv
    from freamer_rl_envs.minigrid import make_minigrid_env

    if __name__ == "__main__":
        env = ParallelEnv(2, EnvCreator(functools.partial(make_minigrid_env, "MiniGrid-DoorKey-5x5-v0")))
"""

from __future__ import annotations

import difflib
import logging
import re
from typing import Any

import gymnasium
import minigrid  # noqa: F401  (registers the MiniGrid-* and BabyAI-* ids with gymnasium)
import numpy as np
import torch
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX
from minigrid.core.grid import Grid
from tensordict import NonTensorData, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, NonTensor, Unbounded
from torchrl.envs import EnvBase

from freamer_rl.data.text import WordTokenizer
from freamer_rl.run.env_registry import EnvAdapter
from freamer_rl_envs.minigrid_language import LanguageReward, language_reward_option
from freamer_rl_envs.single_env import EMPTY_SIZE, finish_td, unchanged_reset

logger = logging.getLogger(__name__)

__all__ = [
    "ADAPTER",
    "MINIGRID_VOCAB",
    "MiniGridEnv",
    "make_minigrid_env",
    "minigrid_env_ids",
    "render_pov",
    "PIXEL_TILE_SIZE",
]

DEFAULT_ENV_ID = "MiniGrid-MultiRoom-N2-S4-v0"
PIXEL_TILE_SIZE = 8
_TOKEN_CACHE_SIZE = 4096

# Every word used by the mission strings of minigrid 3.x (minigrid/envs/*.py, the BabyAI verifier's instruction
# surfaces and the WFC envs). Order fixes the ids: append new words at the end only, never reorder.
MINIGRID_VOCAB: tuple[str, ...] = (
    # colours (minigrid.core.constants.COLOR_TO_IDX)
    "red",
    "green",
    "blue",
    "purple",
    "yellow",
    "grey",
    # objects and places
    "key",
    "ball",
    "box",
    "door",
    "goal",
    "square",
    "wall",
    "floor",
    "lava",
    "object",
    "room",
    "rooms",
    "maze",
    "opening",
    "hallway",
    "end",
    # verbs
    "go",
    "get",
    "fetch",
    "pick",
    "up",
    "put",
    "open",
    "unlock",
    "use",
    "traverse",
    "reach",
    "avoid",
    "find",
    "must",
    "matching",
    # function words and locations
    "the",
    "a",
    "to",
    "and",
    "then",
    "after",
    "you",
    "your",
    "near",
    "next",
    "from",
    "of",
    "at",
    "in",
    "on",
    "front",
    "behind",
    "left",
    "right",
)

_GRID_HIGH = (max(OBJECT_TO_IDX.values()), max(COLOR_TO_IDX.values()), max(STATE_TO_IDX.values()))


def minigrid_env_ids() -> list[str]:
    """Registered gymnasium ids of MiniGrid (and BabyAI) environments, sorted."""
    return sorted(k for k in gymnasium.envs.registry if k.startswith(("MiniGrid-", "BabyAI-")))


#: MultiRoom sizes minigrid does not register, built on demand for curricula: ``MiniGrid-MultiRoom-N<rooms>-S<size>-v0``
#: means exactly ``rooms`` rooms of side at most ``size`` (minigrid's own ``N4-S5-v0`` has 6 rooms; its ids win).
_MULTIROOM_ID = re.compile(r"MiniGrid-MultiRoom-N(\d+)-S(\d+)-v0")
_MAX_MULTIROOM = (8, 10)  # rooms, room size: beyond this the 25x25 MultiRoom grid cannot place the rooms


def register_multiroom(env_id: str) -> bool:
    """Register ``MiniGrid-MultiRoom-N<n>-S<s>-v0`` with gymnasium if minigrid does not (True when it did).

    Raises ``ValueError`` for sizes MultiRoom cannot build (``1 <= n <= 8``, ``4 <= s <= 10``).
    """
    match = _MULTIROOM_ID.fullmatch(env_id)
    if match is None or env_id in gymnasium.envs.registry:
        return False
    rooms, size = int(match[1]), int(match[2])
    if not (1 <= rooms <= _MAX_MULTIROOM[0] and 4 <= size <= _MAX_MULTIROOM[1]):
        raise ValueError(
            f"{env_id}: MultiRoom sizes need 1 <= N <= {_MAX_MULTIROOM[0]} rooms and 4 <= S <= {_MAX_MULTIROOM[1]}"
        )
    gymnasium.register(
        env_id,
        entry_point="minigrid.envs:MultiRoomEnv",
        kwargs={"minNumRooms": rooms, "maxNumRooms": rooms, "maxRoomSize": size},
    )
    return True


def _check_env_id(env_id: str) -> None:
    if env_id in gymnasium.envs.registry or register_multiroom(env_id):
        return
    close = difflib.get_close_matches(env_id, minigrid_env_ids(), n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(repr(c) for c in close)}? " if close else ""
    raise ValueError(
        f"unknown MiniGrid env id '{env_id}': {hint}valid ids are the gymnasium.envs.registry keys containing "
        f"'MiniGrid' (e.g. '{DEFAULT_ENV_ID}', 'MiniGrid-DoorKey-5x5-v0', 'MiniGrid-Empty-5x5-v0')"
    )


class MiniGridEnv(EnvBase):
    """Unbatched TorchRL env around one gymnasium MiniGrid env (see the module docstring for the keys).

    Args:
        env_id: a registered MiniGrid / BabyAI gymnasium id.
        seed: if given, seeds the first reset (same as calling :meth:`set_seed`).
        pixels: also render the RGB agent view under ``"pixels"`` (about 3x slower per step).
        reward_history: length ``H`` of ``"reward_history"`` (0 leaves the key out).
        max_mission_tokens: length ``L`` of ``"mission_tokens"``.
        device: device of the output tensors.
        include_mission: write the raw ``"mission"`` string (a NonTensor entry). TorchRL's handling of NonTensor
            entries (step_mdp, stacking, batched envs) costs about a third of the per-step time, so training loops
            that only read ``"mission_tokens"`` can pass ``False``.
        vocab: mission vocabulary (defaults to :data:`MINIGRID_VOCAB`).
        language_reward: ``None`` (off, no cost) or a plain dict ``{"parser": "regex" | "llm", "llm_path",
            "r_scale", "goal_bonus", "proximity_bonus", "distance": "observed" | "oracle" | "none"}`` (missing keys
            take :data:`~freamer_rl_envs.minigrid_language.LANGUAGE_REWARD_DEFAULTS`; ``"oracle"`` reads the full
            map, privileged information): write ``"lang_reward"``.

    Raises:
        ValueError: unknown env id, an env without MiniGrid's ``image``/``direction``/``mission`` observations,
            or a negative ``reward_history`` / non-positive ``max_mission_tokens``.
    """

    batch_locked = True
    #: render ``"pixels"`` with :func:`render_pov` (False: MiniGrid's ``get_frame``; same image, for A/B timing)
    fast_render = True

    def __init__(
        self,
        env_id: str = DEFAULT_ENV_ID,
        *,
        seed: int | None = None,
        pixels: bool = False,
        reward_history: int = 8,
        max_mission_tokens: int = 16,
        device: torch.device | str = "cpu",
        include_mission: bool = True,
        vocab: tuple[str, ...] | list[str] = MINIGRID_VOCAB,
        language_reward: dict[str, Any] | None = None,
    ) -> None:
        if int(reward_history) != reward_history or reward_history < 0:
            raise ValueError(f"reward_history: expected an integer >= 0, got {reward_history!r}")
        if int(max_mission_tokens) != max_mission_tokens or max_mission_tokens < 1:
            raise ValueError(f"max_mission_tokens: expected an integer >= 1, got {max_mission_tokens!r}")
        _check_env_id(env_id)
        super().__init__(device=device, batch_size=torch.Size([]))

        self.env_id = env_id
        self.pixels = bool(pixels)
        self.reward_history = int(reward_history)
        self.include_mission = bool(include_mission)
        self.tokenizer = WordTokenizer(vocab, max_len=int(max_mission_tokens))
        self._language = None if language_reward is None else LanguageReward(language_reward)  # option checked first
        self._lang_value = 0.0
        self._env = gymnasium.make(env_id)
        self._unwrapped = self._env.unwrapped
        space = self._env.observation_space
        if not (
            isinstance(space, gymnasium.spaces.Dict)
            and {"image", "direction", "mission"} <= set(space.spaces)
            and hasattr(self._unwrapped, "get_frame")
        ):
            self._env.close()
            raise ValueError(
                f"env id '{env_id}' is not a MiniGrid env (observation space {space} lacks "
                "'image'/'direction'/'mission'); use an id containing 'MiniGrid'"
            )
        self._grid_shape = tuple(space.spaces["image"].shape)
        self._n_actions = int(self._env.action_space.n)
        self._out_device = torch.device(self.device) if self.device is not None else torch.device("cpu")

        self._make_specs()

        # mutable per-episode state
        self._pending_seed: int | None = None
        self._history: list[float] = [0.0] * self.reward_history
        self._mission: str | None = None
        self._mission_nt: NonTensorData | None = None
        self._mission_tokens: torch.Tensor | None = None
        self._token_cache: dict[str, torch.Tensor] = {}
        self._unknown_warned: set[str] = set()
        self._last_obs: TensorDictBase | None = None
        self._false = torch.zeros(1, dtype=torch.bool)
        self._true = torch.ones(1, dtype=torch.bool)
        self._directions = [torch.tensor(d, dtype=torch.int64) for d in range(4)]
        if seed is not None:
            self.set_seed(seed)

    # --------------------------------------------------------------------------------------------------------------
    # specs
    # --------------------------------------------------------------------------------------------------------------
    def _make_specs(self) -> None:
        v_h, v_w, _ = self._grid_shape
        high = torch.tensor(_GRID_HIGH, dtype=torch.int64).expand(self._grid_shape).clone()
        obs = {
            "grid": Bounded(
                low=torch.zeros(self._grid_shape, dtype=torch.int64),
                high=high,
                shape=self._grid_shape,
                dtype=torch.int64,
                device=self.device,
            ),
            "direction": Categorical(4, shape=(), dtype=torch.int64, device=self.device),
            "mission_tokens": Bounded(
                low=0,
                high=self.tokenizer.vocab_size - 1,
                shape=(self.tokenizer.max_len,),
                dtype=torch.int64,
                device=self.device,
            ),
        }
        if self.include_mission:
            obs["mission"] = NonTensor(
                shape=(), example_data="traverse the rooms to get to the goal", device=self.device
            )
        if self.reward_history:
            obs["reward_history"] = Unbounded(shape=(self.reward_history,), dtype=torch.float32, device=self.device)
        if self._language is not None:
            obs["lang_reward"] = Unbounded(shape=(1,), dtype=torch.float32, device=self.device)
        if self.pixels:
            p_shape = (v_h * PIXEL_TILE_SIZE, v_w * PIXEL_TILE_SIZE, 3)
            obs["pixels"] = Bounded(low=0, high=255, shape=p_shape, dtype=torch.uint8, device=self.device)
        self.observation_spec = Composite(obs, shape=())
        self.action_spec = Categorical(self._n_actions, shape=(), dtype=torch.int64, device=self.device)
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
    def _tokens_for(self, mission: str) -> torch.Tensor:
        tokens = self._token_cache.get(mission)
        if tokens is None:
            unknown = [w for w in self.tokenizer.unknown_words(mission) if w not in self._unknown_warned]
            if unknown:
                self._unknown_warned.update(unknown)
                logger.warning(
                    "%s: mission %r has words outside the vocabulary %s (encoded as id 1 = unknown)",
                    self.env_id,
                    mission,
                    unknown,
                )
            if len(self._token_cache) >= _TOKEN_CACHE_SIZE:
                self._token_cache.clear()
            tokens = self.tokenizer.encode(mission)
            self._token_cache[mission] = tokens
        return tokens

    def _note_mission(self, mission: str) -> None:
        """Re-tokenize only when the mission changes (it is constant within an episode)."""
        if mission != self._mission:
            self._mission = mission
            self._mission_tokens = self._tokens_for(mission)

    def _restart(self) -> dict[str, Any]:
        """Reset the gymnasium env (with a pending seed) and the reward history; returns its observation."""
        seed, self._pending_seed = self._pending_seed, None
        obs, _ = self._env.reset(seed=seed)
        if self.reward_history:
            self._history = [0.0] * self.reward_history
        self._note_mission(obs["mission"])
        if self._language is not None:
            self._lang_value = self._language.reset(self._unwrapped, self._mission, obs["image"])
        return obs

    def _advance(self, action: int) -> tuple[dict[str, Any], float, bool, bool]:
        """Step the gymnasium env and the reward history: ``(observation, reward, terminated, truncated)``.
        Shared with :class:`freamer_rl_envs.minigrid_vec.MiniGridVecEnv`, which batches these per-env steps."""
        obs, reward, terminated, truncated, _ = self._env.step(action)
        reward = float(reward)
        if self.reward_history:
            history = self._history
            del history[0]
            history.append(reward)
        self._note_mission(obs["mission"])
        if self._language is not None:
            self._lang_value = self._language.step(self._unwrapped, obs["image"])
        return obs, reward, bool(terminated), bool(truncated)

    def _observation(self, obs: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = {
            "grid": torch.from_numpy(obs["image"].astype(np.int64)),
            "direction": self._directions[obs["direction"]].clone(),
            "mission_tokens": self._mission_tokens.clone(),
        }
        if self.include_mission:
            out["mission"] = NonTensorData(self._mission, batch_size=EMPTY_SIZE, device=self._out_device)
        if self.reward_history:
            out["reward_history"] = torch.tensor(self._history, dtype=torch.float32)
        if self._language is not None:
            out["lang_reward"] = torch.tensor((self._lang_value,), dtype=torch.float32)
        if self.pixels:
            out["pixels"] = torch.from_numpy(self.frame())
        return out

    def frame(self) -> np.ndarray:
        """The RGB agent view ``uint8 [8V, 8V, 3]`` of the current state (the ``"pixels"`` entry).

        :func:`render_pov` by default (the same image as MiniGrid's ``get_frame(tile_size=8, agent_pov=True)``,
        tested pixel for pixel); ``fast_render = False`` (class or instance attribute) calls MiniGrid's own.
        """
        if self.fast_render:
            return render_pov(self._unwrapped, PIXEL_TILE_SIZE)
        return self._unwrapped.get_frame(tile_size=PIXEL_TILE_SIZE, agent_pov=True)

    def _finish(self, out: dict[str, Any]) -> TensorDictBase:
        return finish_td(out, self._out_device)

    # --------------------------------------------------------------------------------------------------------------
    # EnvBase API
    # --------------------------------------------------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        same = unchanged_reset(self, tensordict, self._last_obs)
        if same is not None:  # a "_reset" mask that resets nothing
            return same
        out = self._observation(self._restart())
        out["done"] = self._false.clone()
        out["terminated"] = self._false.clone()
        out["truncated"] = self._false.clone()
        td = self._finish(out)
        self._last_obs = td
        return td

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, reward, terminated, truncated = self._advance(int(tensordict.get("action")))
        out = self._observation(obs)
        out["reward"] = torch.tensor((reward,), dtype=torch.float32)
        out["terminated"] = self._true.clone() if terminated else self._false.clone()
        out["truncated"] = self._true.clone() if truncated else self._false.clone()
        out["done"] = self._true.clone() if (terminated or truncated) else self._false.clone()
        td = self._finish(out)
        self._last_obs = td
        return td

    def _set_seed(self, seed: int | None) -> None:
        """Seed the gymnasium env at the next reset (``None`` leaves its random stream as it is)."""
        self._pending_seed = None if seed is None else int(seed)

    def close(self, *, raise_if_closed: bool = True) -> None:
        env = self.__dict__.get("_env")
        if env is not None:
            env.close()
        super().close(raise_if_closed=raise_if_closed)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(env_id={self.env_id!r}, pixels={self.pixels}, "
            f"reward_history={self.reward_history}, max_mission_tokens={self.tokenizer.max_len}, "
            f"include_mission={self.include_mission}, device={self.device})"
        )


def render_pov(env: Any, tile_size: int = PIXEL_TILE_SIZE) -> np.ndarray:
    """MiniGrid's agent-view image ``uint8 [V * tile_size, V * tile_size, 3]`` of the unwrapped env ``env``.

    The same pixels as ``env.get_frame(tile_size=tile_size, agent_pov=True)`` (``get_pov_render`` -> ``Grid.render``),
    from the same per-cell tiles (MiniGrid's class-level ``Grid.tile_cache``, filled by ``Grid.render_tile``), but
    ~3x cheaper: ``Grid.render`` spends most of its time in a per-cell ``np.array_equal(agent_pos, (i, j))`` and
    49 slice assignments; here the agent's cell is compared as a tuple and the tiles are stacked and laid out with
    one reshape/transpose. The agent is drawn facing up (direction 3) at ``(V // 2, V - 1)``, as in MiniGrid.
    """
    grid, vis_mask = env.gen_obs_grid()  # grid [V, V] of cells (carried object at the agent), vis_mask [x, y]
    width, height = grid.width, grid.height
    agent_index = (env.agent_view_size - 1) * width + env.agent_view_size // 2  # row-major index j * width + i
    highlight = vis_mask.T.ravel().tolist()  # row-major, like grid.grid
    render_tile = Grid.render_tile
    tiles = [
        render_tile(cell, agent_dir=3 if idx == agent_index else None, highlight=highlight[idx], tile_size=tile_size)
        for idx, cell in enumerate(grid.grid)
    ]
    # the cached tiles are float64 (MiniGrid's supersampling mean); Grid.render's assignment into its uint8 image
    # truncates them, and so does this cast
    img = np.stack(tiles).astype(np.uint8).reshape(height, width, tile_size, tile_size, 3).transpose(0, 2, 1, 3, 4)
    return np.ascontiguousarray(img).reshape(height * tile_size, width * tile_size, 3)


def make_minigrid_env(
    env_id: str = DEFAULT_ENV_ID,
    *,
    seed: int | None = None,
    pixels: bool = False,
    reward_history: int = 8,
    max_mission_tokens: int = 16,
    device: torch.device | str = "cpu",
    include_mission: bool = True,
    language_reward: dict[str, Any] | None = None,
) -> EnvBase:
    """Build one unbatched :class:`MiniGridEnv` (the ``minigrid`` entry point of the ``freamer_rl.envs`` group).

    Picklable through ``functools.partial(make_minigrid_env, env_id, ...)``, so it can feed ``SerialEnv``,
    ``ParallelEnv`` (wrap it in ``EnvCreator``) and TorchRL collectors.

    Raises:
        ValueError: unknown env id (one line, with close matches) or invalid option.
    """
    return MiniGridEnv(
        env_id,
        seed=seed,
        pixels=pixels,
        reward_history=reward_history,
        max_mission_tokens=max_mission_tokens,
        device=device,
        include_mission=include_mission,
        language_reward=language_reward,
    )


def _minigrid_options(cfg) -> dict[str, Any]:
    """Adapter options implied by a trainer's config (any schema of the trainer registry)."""
    return {
        # rendering costs ~3x per step: only when the model reads the pixels
        "pixels": cfg.reads_observation("pixels"),
        "reward_history": cfg.env.reward_history,
        "max_mission_tokens": cfg.env.max_mission_tokens,
        # the raw mission string costs ~40% of a step in TorchRL's non-tensor handling; training reads tokens
        "include_mission": False,
        # R_lang of the parsed mission (shaping.language; None when its weight is 0)
        "language_reward": language_reward_option(cfg),
    }


def _minigrid_success(ends: TensorDictBase) -> torch.Tensor:
    """MiniGrid success: the episode terminated with a positive reward (reaching the goal)."""
    return ends["terminated"].reshape(-1) & (ends["reward"].reshape(-1) > 0)


def make_minigrid_vec_env(env_id: str, num_envs: int, *, seed: int | None = None, **options: Any) -> EnvBase:
    """``num_envs`` envs stepped as one env of batch size ``[num_envs]``
    (:class:`freamer_rl_envs.minigrid_vec.MiniGridVecEnv`; same data as a SerialEnv of :func:`make_minigrid_env`)."""
    from freamer_rl_envs.minigrid_vec import MiniGridVecEnv  # noqa: PLC0415 (it imports this module)

    return MiniGridVecEnv(env_id, num_envs, seed=seed, **options)


#: The ``minigrid`` entry point of the ``freamer_rl.envs`` group.
ADAPTER = EnvAdapter(
    make_env=make_minigrid_env,
    options=_minigrid_options,
    success=_minigrid_success,
    make_batched_env=make_minigrid_vec_env,
    writes=("lang_reward",),  # R_lang of the parsed mission (option language_reward)
)
