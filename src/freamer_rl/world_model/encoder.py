"""What a world-model encoder can do, as a typed ``Protocol`` (no ``hasattr`` probing in the callers).

:class:`StepEncoder` is the interface every observation encoder of :class:`~freamer_rl.world_model.rssm.WorldModel`
offers to online users -- :class:`~freamer_rl.health.agent.HealthPolicy`, the anomaly recorder and
:class:`~freamer_rl.world_model.anomaly.KLAnomalyTransform` -- and to world-model training (auxiliary losses: a
``LossModule`` run on the tensordict the encoder wrote, no hidden cache).
Stateless encoders get it from :class:`StatelessStepMixin`; the health encoders implement it
(:data:`freamer_rl.health.encoders.HealthEncoder` is this protocol), the recurrent foundation encoder with its DNC
memory as the state.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import torch
from tensordict.utils import NestedKey

if TYPE_CHECKING:
    from torchrl.objectives import LossModule

__all__ = ["StepEncoder", "StatelessStepMixin"]


@runtime_checkable
class StepEncoder(Protocol):
    """Observation encoder with an online step API, auxiliary losses and gates."""

    out_dim: int

    @property
    def obs_keys(self) -> tuple[NestedKey, ...]:
        """The observation keys read."""
        ...

    @property
    def gates(self) -> dict[str, float]:
        """Flow-matching gates ``sigmoid(alpha_m)`` per modality (Eq. 3); ``{}`` without refiners."""
        ...

    def state_shapes(self) -> dict[str, tuple[int, ...]]:
        """Recurrent state entries ``{name: per-element shape}``; ``{}`` for a stateless encoder."""
        ...

    def initial_state(self, batch_shape: Sequence[int] = (), device=None) -> dict[str, torch.Tensor]:
        """Zero state ``{name: [*batch_shape, *shape]}``."""
        ...

    def step(
        self, obs: Mapping, state: Mapping[str, torch.Tensor] | None = None, is_first: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One online step: ``obs {key: [*B, d]}``, ``state``, ``is_first [*B]`` -> ``(embed [*B, E], new_state)``."""
        ...

    def make_aux_loss(self, *, lambda_fm: float = 0.1, lambda_smooth: float = 1e-3) -> LossModule | None:
        """The encoder's auxiliary loss as a TorchRL ``LossModule`` reading the tensordict the encoder wrote (e.g.
        :class:`~freamer_rl.model.losses.FreamerAuxLoss`: weighted ``loss_fm``, ``loss_smooth``), or ``None``. Give it to
        :meth:`WorldModel.loss(batch, aux_loss=...) <freamer_rl.world_model.rssm.WorldModel.loss>`."""
        ...


class StatelessStepMixin:
    """:class:`StepEncoder` defaults for a stateless encoder whose ``forward(obs)`` maps ``{key: [*B, d]}`` to
    ``[*B, E]``: no state, no auxiliary losses, no gates."""

    def state_shapes(self) -> dict[str, tuple[int, ...]]:
        """Recurrent state entries ``{name: per-element shape}``; empty for a stateless encoder."""
        return {}

    def initial_state(self, batch_shape: Sequence[int] = (), device=None) -> dict[str, torch.Tensor]:
        """Zero state ``{name: [*batch_shape, *shape]}`` (empty for a stateless encoder)."""
        return {n: torch.zeros(*batch_shape, *s, device=device) for n, s in self.state_shapes().items()}

    def step(
        self, obs: Mapping, state: Mapping[str, torch.Tensor] | None = None, is_first: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One online step: ``forward(obs)``, no state (``state`` and ``is_first`` are ignored)."""
        return self(obs), {}

    def make_aux_loss(self, *, lambda_fm: float = 0.1, lambda_smooth: float = 1e-3) -> LossModule | None:
        """No auxiliary losses: ``None``."""
        return None

    @property
    def gates(self) -> dict[str, float]:
        """No flow-matching refiners: ``{}``."""
        return {}
