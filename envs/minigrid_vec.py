"""``MiniGridVecEnv``: N MiniGrid envs stepped in one process as one TorchRL env of batch size ``[N]``.

``SerialEnv(N, make_minigrid_env)`` builds a TensorDict per sub-env and step and copies it into its shared buffer;
for MiniGrid's cheap steps that bookkeeping costs more than the N gymnasium steps themselves. This env steps the
same N :class:`~freamer_rl_envs.minigrid.MiniGridEnv` cores (their gymnasium env, reward history and mission
tokens, through ``MiniGridEnv._restart`` / ``_advance``) and writes every key once per batch.

Same keys, specs (with a leading ``[N]``), seeding and episodes as ``SerialEnv(N, make_minigrid_env)``: ``set_seed``
chains the seed through the sub-envs as SerialEnv does, so the same seed and actions give the same data (tested).
Partial resets follow TorchRL's ``"_reset"`` mask. The raw ``"mission"`` string is left out (as the trainer's
``include_mission=False`` does); ``include_mission=True`` is refused with a pointer to SerialEnv.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from freamer_rl_envs.minigrid import DEFAULT_ENV_ID, MiniGridEnv

__all__ = ["MiniGridVecEnv"]


class MiniGridVecEnv(EnvBase):
    """``num_envs`` MiniGrid envs as one env of batch size ``[num_envs]`` (keys: see ``freamer_rl_envs.minigrid``).

    Args:
        env_id: a registered MiniGrid / BabyAI gymnasium id.
        num_envs: ``N >= 1``.
        seed: if given, seeds the first reset of every sub-env (chained as ``SerialEnv.set_seed`` does).
        pixels, reward_history, max_mission_tokens, language_reward: as for
            :class:`~freamer_rl_envs.minigrid.MiniGridEnv`.
        device: must be the CPU (the trainer collects on the CPU and moves batches to the policy's device).
    """

    batch_locked = True

    def __init__(
        self,
        env_id: str = DEFAULT_ENV_ID,
        num_envs: int = 1,
        *,
        seed: int | None = None,
        pixels: bool = False,
        reward_history: int = 8,
        max_mission_tokens: int = 16,
        include_mission: bool = False,
        device: torch.device | str = "cpu",
        language_reward: dict[str, Any] | None = None,
    ) -> None:
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs: expected an integer >= 1, got {num_envs!r}")
        if include_mission:
            raise ValueError(
                "MiniGridVecEnv leaves the raw mission string out (it reads mission_tokens); for include_mission=True "
                "use SerialEnv(n, functools.partial(make_minigrid_env, env_id, include_mission=True))"
            )
        if torch.device(device).type != "cpu":
            raise ValueError(f"MiniGridVecEnv steps on the CPU; got device={device!r} (move batches afterwards)")
        n = int(num_envs)
        self.cores = [
            MiniGridEnv(
                env_id,
                pixels=pixels,
                reward_history=reward_history,
                max_mission_tokens=max_mission_tokens,
                include_mission=False,
                language_reward=language_reward,
            )
            for _ in range(n)
        ]
        super().__init__(device="cpu", batch_size=torch.Size([n]))
        self.env_id = env_id
        one = self.cores[0]
        self.observation_spec = one.observation_spec.expand(n, *one.observation_spec.shape)
        self.action_spec = one.action_spec.expand(n, *one.action_spec.shape)
        self.reward_spec = one.reward_spec.expand(n, *one.reward_spec.shape)
        self.done_spec = one.done_spec.expand(n, *one.done_spec.shape)
        obs = one.observation_spec
        # current observation of every sub-env, overwritten in place; each step hands out copies
        self._buffers: dict[str, np.ndarray] = {
            "grid": np.zeros((n, *obs["grid"].shape), dtype=np.int64),
            "direction": np.zeros((n,), dtype=np.int64),
            "mission_tokens": np.zeros((n, *obs["mission_tokens"].shape), dtype=np.int64),
        }
        if one.reward_history:
            self._buffers["reward_history"] = np.zeros((n, one.reward_history), dtype=np.float32)
        if one._language is not None:
            self._buffers["lang_reward"] = np.zeros((n, 1), dtype=np.float32)
        if one.pixels:
            self._buffers["pixels"] = np.zeros((n, *obs["pixels"].shape), dtype=np.uint8)
        if seed is not None:
            self.set_seed(seed)

    @property
    def num_envs(self) -> int:
        return len(self.cores)

    def _write(self, i: int, core: MiniGridEnv, obs: dict[str, Any]) -> None:
        buf = self._buffers
        buf["grid"][i] = obs["image"]
        buf["direction"][i] = obs["direction"]
        buf["mission_tokens"][i] = core._mission_tokens.numpy()
        if "reward_history" in buf:
            buf["reward_history"][i] = core._history
        if "lang_reward" in buf:
            buf["lang_reward"][i, 0] = core._lang_value
        if "pixels" in buf:
            buf["pixels"][i] = core.frame()

    def _observation(self, flags: dict[str, np.ndarray]) -> TensorDictBase:
        out = {k: torch.from_numpy(v.copy()) for k, v in self._buffers.items()}
        out.update({k: torch.from_numpy(v) for k, v in flags.items()})
        return TensorDict(out, batch_size=self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        which = range(self.num_envs) if mask is None else mask.reshape(self.num_envs).nonzero().flatten().tolist()
        for i in which:
            core = self.cores[i]
            self._write(i, core, core._restart())
        false = np.zeros((self.num_envs, 1), dtype=bool)
        return self._observation({"done": false, "terminated": false.copy(), "truncated": false.copy()})

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get("action").reshape(self.num_envs).tolist()
        n = self.num_envs
        reward = np.zeros((n, 1), dtype=np.float32)
        terminated = np.zeros((n, 1), dtype=bool)
        truncated = np.zeros((n, 1), dtype=bool)
        for i, (core, action) in enumerate(zip(self.cores, actions)):
            obs, reward[i, 0], terminated[i, 0], truncated[i, 0] = core._advance(int(action))
            self._write(i, core, obs)
        done = terminated | truncated
        return self._observation({"reward": reward, "done": done, "terminated": terminated, "truncated": truncated})

    def set_seed(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        """Seed every sub-env's next reset, chaining the seed as ``SerialEnv.set_seed`` does; returns the next seed."""
        for core in self.cores:
            seed = core.set_seed(seed, static_seed=static_seed)
        return seed

    def _set_seed(self, seed: int | None) -> None:  # EnvBase's abstract hook; set_seed above does the work
        self.set_seed(seed)

    def close(self, *, raise_if_closed: bool = True) -> None:
        for core in self.__dict__.get("cores", []):
            core.close(raise_if_closed=False)
        super().close(raise_if_closed=raise_if_closed)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(env_id={self.env_id!r}, num_envs={self.num_envs})"
