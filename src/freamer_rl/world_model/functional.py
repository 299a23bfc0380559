"""Tensor helpers of the world model: symlog/symexp, MLPs, Gaussian KL (Eq. A27), free nats, one-hot actions.

Every function accepts arbitrary leading batch dims ``[*B, ...]``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["symlog", "symexp", "mlp", "gaussian_kl", "free_nats_kl", "action_to_onehot"]


def symlog(x: torch.Tensor) -> torch.Tensor:
    """``sign(x) * log(1 + |x|)`` (DreamerV3): squashes raw sensor scales (m/s^2, bpm) for the MLPs."""
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`symlog`."""
    return torch.sign(x) * torch.expm1(x.abs())


def mlp(in_dim: int, hidden: int, out_dim: int, layers: int = 2) -> nn.Sequential:
    """``layers`` x (Linear -> LayerNorm -> SiLU) then a Linear to ``out_dim``. ``[*B, in_dim] -> [*B, out_dim]``."""
    mods: list[nn.Module] = []
    d = in_dim
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.LayerNorm(hidden), nn.SiLU()]
        d = hidden
    mods.append(nn.Linear(d, out_dim))
    return nn.Sequential(*mods)


def _check_last_dim(name: str, x: torch.Tensor, expected: int) -> None:
    if x.shape[-1] != expected:
        raise ValueError(f"{name}: expected last dim {expected}, got shape {tuple(x.shape)}")


def gaussian_kl(mean_q: torch.Tensor, std_q: torch.Tensor, mean_p: torch.Tensor, std_p: torch.Tensor) -> torch.Tensor:
    """Closed-form ``KL(N(mean_q, std_q) || N(mean_p, std_p))`` of diagonal Gaussians, summed over the last dim.

    Shapes ``[*B, S]`` -> ``[*B]``. Per dim: ``log(sp/sq) + (sq^2 + (mq - mp)^2) / (2 sp^2) - 1/2``.
    """
    var_ratio = (std_q / std_p).pow(2)
    mahal = ((mean_q - mean_p) / std_p).pow(2)
    return 0.5 * (var_ratio + mahal - 1.0 - torch.log(var_ratio)).sum(-1)


def free_nats_kl(kl_per_step: torch.Tensor, free_nats: float = 1.0, mask: torch.Tensor | None = None) -> torch.Tensor:
    """``mean(max(KL_t, free_nats))``: the per-step KL (already summed over latent dims) is clamped at
    ``free_nats`` *before* averaging over batch and time (Eq. A27 with Table A20's free nats 1.0).

    ``kl_per_step``: ``[*B]``; ``mask`` (optional bool ``[*B]``) selects the steps that count.
    """
    clamped = kl_per_step.clamp(min=free_nats)
    if mask is None:
        return clamped.mean()
    return clamped[mask].mean()


def _flat(x: torch.Tensor, n_trailing: int = 1) -> tuple[torch.Tensor, torch.Size]:
    lead = x.shape[: x.ndim - n_trailing]
    return x.reshape(-1, *x.shape[x.ndim - n_trailing :]), lead


def action_to_onehot(action: torch.Tensor, action_dim: int, batch_ndim: int) -> torch.Tensor:
    """Integer actions ``[*B]`` or ``[*B, 1]`` -> float one-hot ``[*B, action_dim]``; float actions ``[*B, A]``
    (one-hot or continuous vectors) pass through after a shape check."""
    if action.dtype.is_floating_point:
        if action.ndim != batch_ndim + 1 or action.shape[-1] != action_dim:
            raise ValueError(
                f"action: expected a float tensor of shape [*B, {action_dim}] with {batch_ndim} batch dims, "
                f"got {tuple(action.shape)}"
            )
        return action
    if action.ndim == batch_ndim + 1 and action.shape[-1] == 1:
        action = action.squeeze(-1)
    if action.ndim != batch_ndim:
        raise ValueError(
            f"action: expected integer indices of shape [*B] or [*B, 1] with {batch_ndim} batch dims, "
            f"got {tuple(action.shape)}"
        )
    if action.numel() and (int(action.min()) < 0 or int(action.max()) >= action_dim):
        raise ValueError(
            f"action: indices must lie in [0, {action_dim}), got range [{int(action.min())}, {int(action.max())}]"
        )
    return F.one_hot(action.long(), action_dim).float()
