"""Training the world model from a TorchRL replay buffer: :func:`as_sequences` and :func:`train_world_model`."""

from __future__ import annotations

import logging

import torch
from tensordict import TensorDictBase

from freamer_rl.run.optim import StepStats, optimizer_step
from freamer_rl.world_model.rssm import WorldModel

logger = logging.getLogger(__name__)

__all__ = ["as_sequences", "train_world_model"]


def as_sequences(batch: TensorDictBase, seq_len: int | None = None, replay_buffer=None) -> TensorDictBase:
    """Reshape a flat ``[num_slices * T]`` sample of a ``SliceSampler`` to ``[num_slices, T]``.

    ``seq_len`` defaults to the sampler's ``slice_len`` (or ``batch_size // num_slices``). A batch that already
    has two or more batch dims is returned unchanged.
    """
    if batch.batch_dims >= 2:
        return batch
    if seq_len is None:
        sampler = getattr(replay_buffer, "sampler", None) if replay_buffer is not None else None
        if sampler is None:
            raise ValueError("as_sequences: pass seq_len or the replay_buffer whose SliceSampler produced the batch")
        seq_len = getattr(sampler, "slice_len", None)
        if seq_len is None:
            num_slices = getattr(sampler, "num_slices", None)
            if num_slices is None:
                raise ValueError("as_sequences: the replay buffer's sampler has neither slice_len nor num_slices")
            seq_len = batch.shape[0] // num_slices
    if batch.shape[0] % seq_len:
        raise ValueError(f"as_sequences: batch of {batch.shape[0]} steps is not divisible by seq_len={seq_len}")
    return batch.reshape(-1, seq_len)


def train_world_model(
    world_model: WorldModel,
    replay_buffer,
    optimizer: torch.optim.Optimizer,
    steps: int,
    *,
    seq_len: int | None = None,
    grad_clip: float | None = 1.0,
    log_every: int = 0,
    stats: StepStats | None = None,
) -> list[dict[str, float]]:
    """``steps`` gradient steps of Eq. A27 on ``[num_slices, T]`` slices sampled from ``replay_buffer``
    (a TorchRL ``ReplayBuffer`` with a ``SliceSampler``). Gradient-norm clipping at ``grad_clip`` (1.0, Table A20); a non-finite gradient skips the step and is counted in
    ``stats`` (:func:`~freamer_rl.run.optim.optimizer_step`).

    Returns one dict of float metrics per step (keys of :meth:`WorldModel.loss` plus ``grad_norm``).
    """
    history: list[dict[str, float]] = []
    params = [p for p in world_model.parameters() if p.requires_grad]
    stats = stats if stats is not None else StepStats("world model")
    world_model.train()
    for i in range(steps):
        batch = as_sequences(replay_buffer.sample(), seq_len, replay_buffer)
        losses = world_model.loss(batch)
        gn = optimizer_step(losses["total"], optimizer, params, grad_clip, stats)  # non-finite: skipped, counted
        rec = {k: float(v.detach()) for k, v in losses.items()}
        rec["grad_norm"] = float(gn)
        history.append(rec)
        if log_every and (i + 1) % log_every == 0:
            logger.info("world model step %d: %s", i + 1, {k: round(v, 4) for k, v in rec.items()})
    return history
