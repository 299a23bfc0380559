"""The one place a TorchRL collector is built from the recipe's ``collector`` section, for every trainer.

``make_collector(cfg.collector, env_fns, policy, ...)``: one env factory per collector worker (its own seed); one
factory runs in this process (``Collector``), several run in worker processes, synchronously (``sync: true``, a
MultiSyncCollector: every batch from the current weights) or asynchronously (IMPALA's actors, whose lag V-trace
corrects).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from torchrl.collectors import Collector

__all__ = ["make_collector"]


def make_collector(section: Any, env_fns: Sequence[Callable[[], Any]], policy: Any, *, frames_per_batch: int,
                   total_frames: int, devices: dict[str, Any], sync: bool = True) -> Any:
    """A TorchRL collector over ``env_fns`` (one per worker; ``len(env_fns) == section.num_collectors``).

    Args:
        section: the config's ``collector`` section (:class:`freamer_rl.config.CollectorConfig`).
        env_fns: picklable zero-argument env factories, one per collector worker.
        policy: the policy module the workers run (its weights are synced by ``update_policy_weights_()``).
        frames_per_batch / total_frames: as TorchRL's ``Collector``.
        devices: ``policy_device`` / ``env_device`` / ``storing_device``.
        sync: several workers: synchronous batches (PPO) or asynchronous ones (IMPALA).
    """
    if len(env_fns) != section.num_collectors:
        raise ValueError(f"make_collector: {len(env_fns)} env factories for collector.num_collectors="
                         f"{section.num_collectors}")  # fmt: skip
    common = dict(frames_per_batch=frames_per_batch, total_frames=total_frames,
                  auto_register_policy_transforms=False, **devices)  # fmt: skip
    if section.num_collectors == 1:
        return Collector(env_fns[0], policy, **common)
    return Collector(list(env_fns), policy, num_collectors=section.num_collectors, sync=sync, **common)
