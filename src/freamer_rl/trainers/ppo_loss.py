"""TorchRL's ClipPPOLoss from a recipe's ``ppo`` section: the one place both PPO trainers (FreamerV1's and the PPO
baseline) turn the section into a loss."""

from __future__ import annotations

from typing import Any

from torchrl.objectives import ClipPPOLoss

__all__ = ["clip_ppo_loss"]


def clip_ppo_loss(actor: Any, critic: Any, ppo: Any, *, reduction: str | None = None) -> ClipPPOLoss:
    """ClipPPOLoss on the two heads (TorchRL's shared-trunk option: the trainer runs the trunk on each minibatch),
    with the section's clip, entropy and critic weights, an L2 value loss and its advantage normalisation;
    ``reduction="none"`` gives per-step losses (FreamerV1's success buffer weights them)."""
    return ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=ppo.clip_epsilon,
        entropy_coeff=ppo.entropy_coeff,
        critic_coeff=ppo.critic_coeff,
        loss_critic_type="l2",
        normalize_advantage=ppo.normalize_advantage,
        functional=False,
        reduction=reduction,
    )
