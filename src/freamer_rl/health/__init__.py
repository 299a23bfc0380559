"""Wearable health management (paper Section 5, Appendices C and J) as TorchRL parts.

* :mod:`.encoders` -- the four observation encoders of Table 15 (MLP, CNN, SlotAttn+CrossAttn, Foundation), each a
  pluggable encoder of :class:`~freamer_rl.world_model.rssm.WorldModel`.
* :mod:`.config` -- :class:`HealthConfig` (YAML recipes ``recipes/health/health_*.yaml``, ``trainer: health``).
* :mod:`.agent` -- env, world model, actor-value, :class:`HealthPolicy`, :class:`HealthAgent` and its checkpoint.
* :mod:`.trainer` -- :func:`run_health` (real-env collection -> world model -> imagination PPO -> real-env
  evaluation; resumable). :mod:`.evaluation` -- the real-env evaluation protocol.
* :mod:`.anomaly_report` -- :func:`anomaly_report` (J.5 / Fig. 4).
* :mod:`.reference` -- fixed and heuristic reference policies (always Continue / Rest / ..., uniform random, a heart-rate
  threshold) evaluated with the same real-env protocol: the yardstick of the imagination-trained policy.
* :mod:`.cli` -- ``freamer-rl health {train,anomaly} ...`` (``freamer-rl train RECIPE`` trains any domain).

The real env is built through the ``freamer_rl.envs`` entry point ``health`` (the library never imports ``envs``).
"""

from freamer_rl.health import encoders, reference
from freamer_rl.health.agent import HealthAgent, HealthPolicy, build_agent, load_agent
from freamer_rl.health.anomaly_report import anomaly_report
from freamer_rl.health.config import HealthConfig, health_config_from_dict, health_config_to_dict, load_health_config
from freamer_rl.health.encoders import *  # noqa: F403
from freamer_rl.health.reference import *  # noqa: F403
from freamer_rl.health.trainer import run_health

#: submodule constants left out of ``__all__`` (``IMU_SITES`` would clash with :data:`freamer_rl.data.IMU_SITES`)
_NOT_REEXPORTED = frozenset({"IMU_DIM", "HR_DIM", "IMU_SITES", "IMU_CHANNELS", "ACTION_NAMES"})

__all__ = [
    *(name for name in encoders.__all__ if name not in _NOT_REEXPORTED),
    "HealthConfig",
    "HealthAgent",
    "HealthPolicy",
    "load_health_config",
    "health_config_from_dict",
    "health_config_to_dict",
    "build_agent",
    "load_agent",
    "run_health",
    "anomaly_report",
    *(name for name in reference.__all__ if name not in _NOT_REEXPORTED),
]
