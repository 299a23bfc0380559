"""Return-based reward normalisation: the reward PPO trains on, divided by a running std of its discounted return.

A critic that shares the policy's trunk regresses on returns whose size is the task's: ~100 on CartPole (the value
loss's gradient crowds the policy's out after clipping), ~0.05-0.3 on DoorKey-8x8 with a small novelty bonus (where
FreamerV1 learned on 2 of 5 seeds, and on 5 of 5 with the reward normalised: recipes/suites/scratch_doorkey8x8.yaml).
``shaping.return_norm`` sets the scale from the data, as SB3's ``VecNormalize(norm_reward=True)`` and
openai/baselines do (our own code; TorchRL's ``VecNorm`` transform scales by the per-step reward's own statistics,
and any env transform acts before the trainer mixes its bonus terms in)::

    G_t     = gamma * G_{t-1} * (1 - done_{t-1}) + r_t       per env row, carried from batch to batch
    sigma^2 = running variance of G over every step seen     (moments merged per batch: Chan et al. 1979)
    r'_t    = clamp(r_t / max(sigma, floor), -CLIP, CLIP)

The mean of ``G`` is not subtracted (shifting the reward would change which episodes pay). Rewards are divided by the
statistics that include the current batch. ``CLIP`` bounds the first rewards of a sparse task, seen while ``sigma``
is still near 0; every clipped step is counted (``return_norm_clipped``). ``floor`` (``shaping.return_norm_floor``,
default :data:`STD_FLOOR`) caps the factor at ``1 / floor``: with only a sparse goal reward the returns' spread stays
small, the factor large, and a small floor lets the clip flatten every goal reward to ``CLIP``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from freamer_rl.layers.moments import merge_moments

__all__ = ["ReturnNormalizer"]

#: default smallest std divided by, so the factor is at most 10: with a floor of 1e-4 (the first runs') a goal-only
#: reward's factor stayed at 11-250 and the clip flattened every goal reward (MultiRoom-N2-S4: 1.4x the frames to
#: 95%); with 0.1 N2-S4 learned as without normalisation, DoorKey-8x8 and N4-S5 as well as or better than with 1e-4
STD_FLOOR = 0.1
#: bound on a normalised reward (SB3's default ``clip_reward``)
CLIP = 10.0


class ReturnNormalizer(nn.Module):
    """Divides rewards ``[*B, T, 1]`` (time on dim -2, batches in collection order) by a running std of their
    discounted return. State (:meth:`state` / :meth:`load_state`, so a resumed run keeps its scale): ``count``,
    ``mean``, ``var`` of the returns seen, and ``carry`` ``[rows]``, each env row's return so far in its unfinished
    episode.

    Args:
        gamma: the discount of the returns whose spread is measured (PPO's ``gamma``), in ``(0, 1]``.
        floor: the smallest std divided by (finite, > 0): the factor is at most ``1 / floor``.

    Raises:
        ValueError: ``gamma`` outside ``(0, 1]``; a floor that is not finite and > 0; ``reward`` and ``done`` of
            different sizes.
    """

    def __init__(self, gamma: float, floor: float = STD_FLOOR) -> None:
        super().__init__()
        if not (math.isfinite(gamma) and 0.0 < gamma <= 1.0):
            raise ValueError(f"ReturnNormalizer: gamma must be in (0, 1], got {gamma!r}")
        if not (math.isfinite(floor) and floor > 0):
            raise ValueError(f"ReturnNormalizer: floor must be a finite number > 0, got {floor!r}")
        self.gamma = float(gamma)
        self.floor = float(floor)
        self.count = torch.zeros((), dtype=torch.float64)
        self.mean = torch.zeros((), dtype=torch.float64)
        self.var = torch.zeros((), dtype=torch.float64)
        self.carry = torch.zeros(0, dtype=torch.float64)
        self.last_scale = torch.ones(())  # 1 / max(sigma, floor) of the last call (diagnostic)
        self.last_clipped = torch.zeros(())  # steps clipped in the last call

    def returns(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """Discounted returns ``[rows, T]`` (float64) from the carried ones; updates ``carry``. ``done`` ends an
        episode after its step: the next step starts from 0."""
        steps = reward.shape[-2]
        r = reward.reshape(-1, steps).double()
        d = done.reshape(r.shape).double()
        if self.carry.shape != r.shape[:1]:  # first batch (or another number of env rows): no episode carried
            self.carry = torch.zeros(r.shape[0], dtype=torch.float64, device=r.device)
        out = torch.empty_like(r)
        g = self.carry
        for t in range(steps):  # T small ops on [rows]: a sequential scan, no host sync
            g = self.gamma * g + r[:, t]
            out[:, t] = g
            g = g * (1.0 - d[:, t])
        self.carry = g
        return out

    def forward(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """The normalised reward, same shape and dtype as ``reward [*B, T, 1]``; ``done`` ``[*B, T, 1]`` or
        ``[*B, T]``."""
        if done.numel() != reward.numel():
            raise ValueError(
                f"ReturnNormalizer: reward {tuple(reward.shape)} and done {tuple(done.shape)} must have the same size"
            )
        if self.mean.device != reward.device:  # plain tensors, not buffers: follow the batch's device
            self.count, self.mean, self.var = (t.to(reward.device) for t in (self.count, self.mean, self.var))
            self.carry = self.carry.to(reward.device)
        with torch.no_grad():
            g = self.returns(reward, done)
            self.count, self.mean, self.var = merge_moments(
                self.count, self.mean, self.var, g.numel(), g.mean(), g.var(unbiased=False)
            )
            scale = self.var.sqrt().clamp_min(self.floor).reciprocal().to(reward.dtype)
            scaled = reward * scale
            out = scaled.clamp(-CLIP, CLIP)
            self.last_scale = scale
            self.last_clipped = (scaled.abs() > CLIP).sum()
        return out

    def state(self) -> dict[str, torch.Tensor]:
        """The running statistics and the carried returns (tensors: a ``weights_only`` checkpoint holds them)."""
        return {"count": self.count, "mean": self.mean, "var": self.var, "carry": self.carry}

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore :meth:`state`'s output; a missing or malformed entry is an error naming it."""
        for name in ("count", "mean", "var", "carry"):
            value = state.get(name)
            if not isinstance(value, torch.Tensor) or (name != "carry" and value.ndim != 0):
                raise ValueError(f"ReturnNormalizer.load_state: {name!r} missing or not a tensor of the right shape")
            setattr(self, name, value.to(torch.float64))

    def diagnostics(self) -> dict[str, torch.Tensor]:
        """``return_scale`` (the factor of the last call) and ``return_norm_clipped`` (its clipped steps)."""
        return {"return_scale": self.last_scale, "return_norm_clipped": self.last_clipped}

    def extra_repr(self) -> str:
        return f"gamma={self.gamma}, floor={self.floor}"
