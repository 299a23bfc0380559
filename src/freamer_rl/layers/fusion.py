"""Layer-3 alternatives to the FNO fuser, for ablations (``model.fusion: concat | mean``).

Both take the same input and give the same outputs as :class:`~freamer_rl.layers.fno.FNOFuser`, so the trunk and the
losses do not change with the choice:

    forward: ``E [*B, M, d] -> (fused [*B, d], rows [*B, M, d])``

``rows`` is ``E`` itself: neither mixes the modality rows, so the FNO smoothness term (Eq. A16) has nothing to act on.

:class:`PresenceMask` sits in front of any fuser: ``e [*B, d] * present [*B, 1]``, so a modality whose sensor was
dropped (``present = 0``) adds exactly nothing to the mix (``model.presence_keys``).

* :class:`ConcatFuser` -- the usual late fusion of a multimodal MLP policy: ``fused = MLP([E_1; ...; E_M])``
  (``Linear(M d, h) -> GELU -> Linear(h, d)``), so every modality's entries can be weighted against each other.
* :class:`MeanFuser` -- ``fused = mean_m E_m`` with no parameters: what the FNO fuser reduces to with ``R_k = 0``,
  ``W = 0``.
"""

from __future__ import annotations

import torch
from torch import nn

from freamer_rl.layers.checks import check_finite

__all__ = ["ConcatFuser", "MeanFuser", "PresenceMask"]


def _check_stack(e: torch.Tensor, num_modalities: int, dim: int, name: str) -> None:
    if e.ndim < 2 or tuple(e.shape[-2:]) != (num_modalities, dim):
        raise ValueError(f"{name} expects E of shape [*B, M={num_modalities}, d={dim}]; got {tuple(e.shape)}")
    check_finite(e, f"{name} modal_stack")


class ConcatFuser(nn.Module):
    """``E [*B, M, d] -> (MLP(flatten(E)) [*B, d], E)``; ``hidden`` is the MLP's width ``h`` (default ``d``)."""

    def __init__(self, num_modalities: int, dim: int, hidden: int | None = None) -> None:
        super().__init__()
        if num_modalities < 1 or dim < 1:
            raise ValueError(f"num_modalities and dim must be positive; got {num_modalities}, {dim}")
        self.num_modalities, self.dim = num_modalities, dim
        h = dim if hidden is None else hidden
        self.mlp = nn.Sequential(nn.Linear(num_modalities * dim, h), nn.GELU(), nn.Linear(h, dim))

    def forward(self, e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _check_stack(e, self.num_modalities, self.dim, "ConcatFuser")
        return self.mlp(e.flatten(-2)), e


class MeanFuser(nn.Module):
    """``E [*B, M, d] -> (mean over M [*B, d], E)``, no parameters."""

    def __init__(self, num_modalities: int, dim: int) -> None:
        super().__init__()
        self.num_modalities, self.dim = num_modalities, dim

    def forward(self, e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _check_stack(e, self.num_modalities, self.dim, "MeanFuser")
        return e.mean(dim=-2), e


class PresenceMask(nn.Module):
    """``(e [*B, d], present [*B, 1]) -> e * present``: a dropped modality's row of the fuser's input is zero."""

    def forward(self, e: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        if present.shape != (*e.shape[:-1], 1):
            raise ValueError(
                f"PresenceMask: the flag must be [*B, 1] for an embedding {tuple(e.shape)}; got {tuple(present.shape)}"
            )
        return e * present.to(e.dtype)
