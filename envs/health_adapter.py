"""The ``health`` entry point of the ``freamer_rl.envs`` group: the wearable-health env (:mod:`freamer_rl_envs.health`)
for the health trainer (batched, through ``batch_size``) and for the collector-based trainers (model-free PPO on the
simulator, ``env.options`` for the subjects and the rate)."""

from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase
from torchrl.envs import BatchSizeTransform, EnvBase, TransformedEnv

from freamer_rl.run.env_registry import EnvAdapter
from freamer_rl_envs.health import HealthEnv, make_health_env

#: :func:`make_health_env`'s options that a recipe of a collector-based trainer (``minigrid_ppo``, ``ppo_baseline``)
#: sets through ``env.options`` (and ``env.eval_options``, e.g. a held-out subject); the health trainer has its own
#: ``env`` fields for them
HEALTH_OPTION_NAMES = (
    "data_dir",
    "subjects",
    "episode_length",
    "rate_hz",
    "reward_weights",
    "synthetic_duration_s",
    "data_seed",
    "gain_jitter",
)


def _squeeze_batch(td: TensorDictBase) -> TensorDictBase:
    return td.squeeze(0)


def make_health_adapter_env(
    env_id: str | None = None, *, seed: int | None = None, batch_size: int | None = None, **options: Any
) -> EnvBase:
    """The ``health`` entry point of the ``freamer_rl.envs`` group.

    ``batch_size=None``: one unbatched env (batch ``[]``; observations ``"imu"`` ``[36]``, ``"hr_features"`` ``[16]``,
    action ``[]``), what spec probes, ``SerialEnv`` and ``check_env_specs`` expect: a batch-1 :class:`HealthEnv`
    squeezed by TorchRL's ``BatchSizeTransform``. An int: the batched :class:`HealthEnv` the health trainer steps.
    ``options``: :func:`make_health_env`'s keywords.
    """
    if batch_size is None:
        env = make_health_env(env_id, seed=seed, batch_size=1, **options)
        return TransformedEnv(env, BatchSizeTransform(reshape_fn=_squeeze_batch))
    return make_health_env(env_id, seed=seed, batch_size=batch_size, **options)


def _make_batched(env_id: str, num_envs: int, *, seed: int | None = None, **options: Any) -> HealthEnv:
    return make_health_env(env_id, seed=seed, batch_size=num_envs, **options)


#: The ``health`` entry point: the same env for the health trainer (batched, through ``batch_size``) and for the
#: collector-based trainers (model-free PPO on the simulator; ``env.options`` sets the subjects and the rate). No
#: notion of success: the trainers report returns.
ADAPTER = EnvAdapter(make_env=make_health_adapter_env, make_batched_env=_make_batched, option_names=HEALTH_OPTION_NAMES)
