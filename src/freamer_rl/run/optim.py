"""The one optimiser step of the project (MiniGrid PPO, health world model, imagination PPO).

Policy for a non-finite gradient (NaN/inf total norm, e.g. from an overflowing loss): the update is **skipped**
(the parameters and the optimiser state stay as they were), the skip is **counted** in :class:`StepStats`, and it
is **logged** with a rate-limited warning. One bad batch must neither poison the weights (Adam would write NaN into
every parameter) nor stop a long run; a run whose skips keep growing shows it in its logged ``skipped_steps``.

    stats = StepStats("world model")
    grad_norm = optimizer_step(loss, optimizer, params, max_grad_norm=1.0, stats=stats)
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import torch

logger = logging.getLogger(__name__)

__all__ = ["StepStats", "optimizer_step", "scheduled_lr", "set_lr", "restore_optimizer"]

_WARN_EVERY_S = 30.0  # at most one warning per StepStats in this many seconds (a diverging run would flood the log)


@dataclass
class StepStats:
    """Counts of one optimiser's steps: ``steps`` (every call) and ``skipped`` (non-finite gradients)."""

    name: str = "optimizer"
    steps: int = 0
    skipped: int = 0
    _last_warning: float = field(default=-math.inf, repr=False)
    _unreported: int = field(default=0, repr=False)

    def record_skip(self, grad_norm: float) -> None:
        self.skipped += 1
        self._unreported += 1
        now = time.monotonic()
        if now - self._last_warning >= _WARN_EVERY_S:
            logger.warning(
                "%s: non-finite gradient norm (%s); update skipped (%d skipped since the last warning, %d of %d "
                "steps in all)",
                self.name,
                grad_norm,
                self._unreported,
                self.skipped,
                self.steps,
            )
            self._last_warning = now
            self._unreported = 0

    def state_dict(self) -> dict[str, int]:
        return {"steps": self.steps, "skipped": self.skipped}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.steps = int(state["steps"])
        self.skipped = int(state["skipped"])


_UNNAMED = StepStats()  # callers that keep no stats of their own share this one (and its rate limit)


def optimizer_step(
    loss: torch.Tensor,
    optimizer: torch.optim.Optimizer,
    params: Iterable[torch.Tensor],
    max_grad_norm: float | None = None,
    stats: StepStats | None = None,
    *,
    foreach: bool | None = None,
    before_step: Callable[[], None] | None = None,
) -> torch.Tensor:
    """Zero the gradients, ``loss.backward()``, clip the total gradient norm of ``params`` at ``max_grad_norm``
    (``None``: no clipping, the norm is still measured), then ``optimizer.step()`` -- unless the norm is not finite,
    in which case the step is skipped, the gradients are dropped and ``stats`` counts it.

    Args:
        loss: scalar tensor ``[]`` to minimise.
        params: the parameters whose gradients are clipped (those of ``optimizer``).
        foreach: passed to ``clip_grad_norm_`` (True: the fused multi-tensor kernel for many small tensors).
        before_step: called after clipping and just before ``optimizer.step()``, only when the step is taken (the
            gradients are final and finite): e.g. :meth:`freamer_rl.machinery.ogm.OGMGE.modulate` sets per-group learning
            rates and adds its gradient-enhancement noise there.

    Returns the total gradient norm before clipping (a 0-dim tensor; NaN/inf when the step was skipped).
    """
    params = list(params)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    limit = max_grad_norm if max_grad_norm is not None else math.inf
    grad_norm = torch.nn.utils.clip_grad_norm_(params, limit, foreach=foreach)
    if stats is None:
        stats = _UNNAMED
    stats.steps += 1
    if torch.isfinite(grad_norm):
        if before_step is not None:
            before_step()
        optimizer.step()
    else:
        stats.record_skip(float(grad_norm))
    # dropped at once: a skipped step's NaN gradients must not leak into the next accumulation
    optimizer.zero_grad(set_to_none=True)
    return grad_norm


def scheduled_lr(optim: Any, frames: int, total_frames: int) -> float:
    """The learning rate of ``optim`` (an ``optim`` section) after ``frames`` of ``total_frames``: ``optim.lr``, or
    with ``optim.lr_schedule: linear`` decayed to 0 at ``total_frames`` (from the frames done, so resumes match)."""
    if optim.lr_schedule != "linear":
        return optim.lr
    return optim.lr * max(1.0 - frames / total_frames, 0.0)


def set_lr(optimizer: torch.optim.Optimizer, lr: float, eps: float | None = None) -> None:
    """Every parameter group's ``lr`` (times its ``lr_scale``, OGM-GE's Mode A gate groups) and, given, ``eps``."""
    for group in optimizer.param_groups:
        group["lr"] = lr * group.get("lr_scale", 1.0)
        if eps is not None:
            group["eps"] = eps


def restore_optimizer(
    optimizer: torch.optim.Optimizer, state: dict, optim: Any, frames: int, total_frames: int
) -> None:
    """Load a checkpoint's optimiser ``state`` on resume: Adam's moments are kept, the ``optim`` section of the
    current config sets lr (its schedule at ``frames``) and eps."""
    optimizer.load_state_dict(state)
    set_lr(optimizer, scheduled_lr(optim, frames, total_frames), optim.eps)
