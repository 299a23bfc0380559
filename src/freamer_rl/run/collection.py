"""The one place a TorchRL collector is built from the recipe's ``collector`` section, for every trainer.

``make_collector(cfg.collector, env_fns, policy, ...)``: one env factory per collector worker (its own seed); one
factory runs in this process (``Collector``), several run in worker processes, synchronously (``sync: true``, a
MultiSyncCollector: every batch from the current weights) or asynchronously (IMPALA's actors, whose lag V-trace
corrects). ``collector.backend: ray`` runs the workers as Ray actors instead (TorchRL's ``RayCollector``), on this
machine or across a Ray cluster; the trainer sees the same batches and calls the same ``update_policy_weights_()``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

from torchrl.collectors import Collector

from freamer_rl.config.checks import check_ray_backend
from freamer_rl.errors import ConfigError

__all__ = ["make_collector"]

logger = logging.getLogger(__name__)


def make_collector(
    section: Any,
    env_fns: Sequence[Callable[[], Any]],
    policy: Any,
    *,
    frames_per_batch: int,
    total_frames: int,
    devices: dict[str, Any],
    sync: bool = True,
) -> Any:
    """A TorchRL collector over ``env_fns`` (one per worker; ``len(env_fns) == section.num_collectors``).

    Args:
        section: the config's ``collector`` section (:class:`freamer_rl.config.loader.CollectorConfig`).
        env_fns: picklable zero-argument env factories, one per collector worker.
        policy: the policy module the workers run (its weights are synced by ``update_policy_weights_()``).
        frames_per_batch / total_frames: as TorchRL's ``Collector``.
        devices: ``policy_device`` / ``env_device`` / ``storing_device``.
        sync: several workers: synchronous batches (PPO) or asynchronous ones (IMPALA).
    """
    if len(env_fns) != section.num_collectors:
        raise ValueError(
            f"make_collector: {len(env_fns)} env factories for collector.num_collectors={section.num_collectors}"
        )
    if getattr(section, "backend", "local") == "ray":
        # the actors run on the CPU; check_ray_backend refuses a policy elsewhere, so `devices` is all CPU here
        return _ray_collector(
            section, env_fns, policy, frames_per_batch=frames_per_batch, total_frames=total_frames, sync=sync
        )
    common = dict(
        frames_per_batch=frames_per_batch, total_frames=total_frames, auto_register_policy_transforms=False, **devices
    )
    if section.num_collectors == 1:
        return Collector(env_fns[0], policy, **common)
    return Collector(list(env_fns), policy, num_collectors=section.num_collectors, sync=sync, **common)


def _ray_collector(
    section: Any,
    env_fns: Sequence[Callable[[], Any]],
    policy: Any,
    *,
    frames_per_batch: int,
    total_frames: int,
    sync: bool,
) -> Any:
    """TorchRL's Ray collector: one remote ``Collector`` actor per env factory, on CPU.

    Batch layout, as the local backend's: one collector gives ``[num_envs, T]``; with ``sync`` several give
    ``torch.stack`` of their ``[num_envs, T]`` batches, ``[num_collectors, num_envs, T]`` -- what the local
    MultiSyncCollector returns too (it stacks, ``cat_results="stack"``), so no reshape is needed; without ``sync``
    each batch is one actor's ``[num_envs, T]`` of ``frames_per_batch`` frames, as MultiAsyncCollector's.
    The actors run the policy and the envs on their CPU (Ray hides GPUs from actors that reserve none), so the
    policy must be on the CPU too (``run.device=cpu``, checked).
    """

    check_ray_backend(section, policy)  # ray importable, the policy on the CPU
    import ray

    _init_ray(section)
    if section.num_collectors == 1:
        # one actor: the async iterator yields its [num_envs, T] as is (the sync one stacks it to [1, num_envs, T]);
        # it asks for the next batch only after the trainer's update_policy_weights_(), so the weights are current
        sync = False
    collector = Collector(
        list(env_fns),
        policy,
        backend="ray",
        num_collectors=section.num_collectors,
        sync=sync,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        backend_options={
            "policy_device": "cpu",
            "env_device": "cpu",
            "storing_device": "cpu",
            "collector_kwargs": {"auto_register_policy_transforms": False},
            "remote_configs": {"num_cpus": section.ray_collector_cpus, "num_gpus": 0},
        },
    )
    # push the current weights now: the actors start from them and iterating does not warn about a lazy first sync
    collector.update_policy_weights_()
    logger.info(
        "Ray collection: %d actor(s) (%s) on %s",
        section.num_collectors,
        "sync" if sync else "async",
        ray.get_runtime_context().gcs_address,
    )
    return collector


def _init_ray(section: Any) -> None:
    """Start or join Ray as ``collector.ray_address`` says; ConfigError when the actors would not fit."""
    import ray

    if not ray.is_initialized():
        # a Ray instance started here lives until this process exits (later runs in the process reuse it). The
        # actors' own output (TorchRL's reprs, one per actor) stays in Ray's log folder unless we log at DEBUG.
        verbose = logger.isEnabledFor(logging.DEBUG)
        kwargs: dict[str, Any] = {"address": section.ray_address, "include_dashboard": False, "log_to_driver": verbose}
        if section.ray_address is None:
            kwargs["num_cpus"] = section.ray_num_cpus
        ray.init(**kwargs)
    need = section.num_collectors * section.ray_collector_cpus
    # the cluster's total, not what is free now: actors of a collector just shut down free their CPUs a moment later
    total = ray.cluster_resources().get("CPU", 0.0)
    if need > total:  # else the actors wait for CPUs forever
        raise ConfigError(
            f"collector.ray_collector_cpus: {section.num_collectors} collector(s) x {section.ray_collector_cpus} "
            f"CPU need {need:g} CPUs, the Ray cluster has {total:g}; lower collector.ray_collector_cpus or "
            f"collector.num_collectors, or give Ray more CPUs (collector.ray_num_cpus, more nodes)"
        )
