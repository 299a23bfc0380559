"""Gymnasium adapter: any registered gymnasium id through TorchRL's own ``GymWrapper``.

``make_gym_env("CartPole-v1")`` is ``GymWrapper(gymnasium.make("CartPole-v1"), categorical_action_encoding=True)``
(what ``GymEnv("CartPole-v1", ...)`` builds) plus, when needed,
``DoubleToFloat`` (float64 observations become float32, the model's dtype) and an optional reward history (the last
``H`` rewards under ``"reward_history"``, most recent last, zeros after reset) for FreamerV1's reward modality.
Keys are TorchRL's: a Box observation arrives as ``"observation"``, a Dict observation as its own keys; map them to
modalities with the recipe's ``model.observation_keys`` (e.g. ``{vector: [observation]}``).

Any id gymnasium can make works: a registered one, gymnasium's ``module:EnvId`` form (``module`` is imported first,
so an env registered in the user's own module is found), or an id the recipe's ``env.imports`` modules register
(``env.imports: [minigrid]`` then ``MiniGrid-Empty-5x5-v0``). Observation entries TorchRL has no spec for (gymnasium
``Text``, MiniGrid's ``MissionSpace``) are left out of a Dict observation with one log line; the env adapter that
knows them (``minigrid``) turns the mission into tokens instead.

Discrete actions are integer indices (``Categorical``), so the policy's ``"action"`` matches what a TorchRL user's
own ``GymEnv(..., categorical_action_encoding=True)`` expects; Box actions stay a ``Bounded`` float spec.
"""

from __future__ import annotations

import difflib
import importlib
import logging
from typing import Any

import gymnasium
import torch
from gymnasium import spaces
from gymnasium.wrappers import FilterObservation
from tensordict import TensorDictBase
from torchrl.data import Unbounded
from torchrl.envs import Compose, DoubleToFloat, EnvBase, Transform, TransformedEnv
from torchrl.envs.libs.gym import GymWrapper

from freamer_rl.run.env_registry import EnvAdapter

__all__ = ["ADAPTER", "RewardHistory", "make_gym_env"]

logger = logging.getLogger(__name__)

#: gymnasium spaces TorchRL converts to specs (Dict and Tuple of these too)
_TORCHRL_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)
_reported_drops: set[str] = set()  # env ids whose left-out entries were logged (once, not once per sub-env)


class RewardHistory(Transform):
    """Writes the last ``history`` rewards as ``"reward_history"`` ``[*B, H]`` (most recent last, zeros at reset)."""

    def __init__(self, history: int, out_key: str = "reward_history") -> None:
        if history < 1:
            raise ValueError(f"reward_history: expected an integer >= 1, got {history!r}")
        super().__init__(in_keys=[], out_keys=[out_key])
        self.history = int(history)
        self.out_key = out_key

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        shape = (*tensordict_reset.batch_size, self.history)
        zeros = torch.zeros(shape, dtype=torch.float32, device=tensordict_reset.device)
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        old = tensordict.get(self.out_key, None) if tensordict is not None else None
        if reset is not None and old is not None:
            # partial reset in a batched env: keep the histories of the envs that go on
            zeros = torch.where(reset.reshape(*reset.shape[: len(shape) - 1], 1), zeros, old)
        tensordict_reset.set(self.out_key, zeros)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        old = tensordict.get(self.out_key)
        reward = next_tensordict.get("reward").to(torch.float32).reshape(*old.shape[:-1], 1)
        next_tensordict.set(self.out_key, torch.cat([old[..., 1:], reward], dim=-1))
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        observation_spec[self.out_key] = Unbounded(
            shape=(*observation_spec.shape, self.history), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec


def _check_env_id(env_id: str) -> None:
    """``env_id`` or, in gymnasium's ``module:EnvId`` form, ``EnvId`` after importing ``module`` is registered."""
    module, _, name = env_id.rpartition(":")
    if module:
        try:
            importlib.import_module(module)
        except ImportError as err:
            raise ValueError(
                f"the module {module!r} it names cannot be imported ({err}); is it installed or on PYTHONPATH?"
            ) from None
    if name in gymnasium.envs.registry:
        return
    close = difflib.get_close_matches(name, list(gymnasium.envs.registry), n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(repr(c) for c in close)}? " if close else ""
    where = f"module {module!r} registers no such id; " if module else ""
    raise ValueError(
        f"unknown gymnasium env id '{env_id}': {where}{hint}(any id in gymnasium.envs.registry, e.g. "
        "'CartPole-v1', 'my_module:MyEnv-v0', or list the registering module in env.imports)"
    )


def _torchrl_holds(space: spaces.Space) -> bool:
    if isinstance(space, spaces.Dict):
        return all(_torchrl_holds(s) for s in space.spaces.values())
    if isinstance(space, spaces.Tuple):
        return all(_torchrl_holds(s) for s in space.spaces)
    return isinstance(space, _TORCHRL_SPACES)


def _without_unheld_entries(env: gymnasium.Env, env_id: str) -> gymnasium.Env:
    """``env`` with the Dict-observation entries TorchRL cannot hold filtered out (one log line per env id)."""
    space = env.observation_space
    if _torchrl_holds(space):
        return env
    entries = space.spaces if isinstance(space, spaces.Dict) else {}
    kept = [k for k, s in entries.items() if _torchrl_holds(s)]
    if not kept:
        raise ValueError(
            f"its observation space {space} has no TorchRL spec (supported: Box, Discrete, "
            "MultiDiscrete, MultiBinary and Dicts of them)"
        )
    if env_id not in _reported_drops:
        _reported_drops.add(env_id)
        dropped = ", ".join(f"{k} ({type(s).__name__})" for k, s in entries.items() if k not in kept)
        logger.info("gym adapter: %s: observation entries without a TorchRL spec are left out: %s", env_id, dropped)
    return FilterObservation(env, kept)


def make_gym_env(
    env_id: str, *, seed: int | None = None, reward_history: int = 0, device: torch.device | str = "cpu"
) -> EnvBase:
    """One unbatched gymnasium env as a TorchRL env (the ``gym`` entry point of the ``freamer_rl.envs`` group).

    Raises:
        ValueError: unknown env id (one line, with close matches), a ``module:`` that cannot be imported, an
            observation space without a TorchRL spec, or a negative ``reward_history``.
    """
    if int(reward_history) != reward_history or reward_history < 0:
        raise ValueError(f"reward_history: expected an integer >= 0, got {reward_history!r}")
    _check_env_id(env_id)
    base = GymWrapper(
        _without_unheld_entries(gymnasium.make(env_id), env_id), categorical_action_encoding=True, device=device
    )
    transforms: list[Transform] = []
    doubles = [k for k, s in base.observation_spec.items(True, True) if s.dtype == torch.float64]
    if doubles:
        transforms.append(DoubleToFloat(in_keys=doubles))
    if reward_history:
        transforms.append(RewardHistory(int(reward_history)))
    env = TransformedEnv(base, Compose(*transforms)) if transforms else base
    if seed is not None:
        env.set_seed(seed)
    return env


def _gym_options(cfg: Any) -> dict[str, Any]:
    """The reward history is built only when the reward modality reads it."""
    return {"reward_history": cfg.env.reward_history if cfg.reads_observation("reward_history") else 0}


#: The ``gym`` entry point: no notion of success (the trainer reports returns).
ADAPTER = EnvAdapter(make_env=make_gym_env, options=_gym_options)
