"""Default observation encoder and decoder of :class:`~freamer_rl.world_model.rssm.WorldModel` (MLPs on the
concatenated observation keys)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict.utils import NestedKey
from torch import nn

from freamer_rl.world_model.encoder import StatelessStepMixin
from freamer_rl.world_model.functional import _check_last_dim, mlp, symlog

__all__ = ["MLPObsEncoder", "MLPObsDecoder"]


class MLPObsEncoder(StatelessStepMixin, nn.Module):
    """Default observation encoder: concatenation of the observation keys -> MLP -> ``[*B, out_dim]``.

    Args:
        obs_dims: ``{key: feature size}``; the keys are read (in this order) from the observation mapping.
        out_dim: embedding size ``E``.
        hidden, layers: MLP width and depth.
        symlog_inputs: apply :func:`symlog` to the inputs (robust to raw m/s^2 and bpm scales).

    Forward: ``obs`` is any mapping (dict or TensorDict) ``key -> [*B, d_key]``; returns ``[*B, out_dim]``.
    A stateless :class:`~freamer_rl.world_model.encoder.StepEncoder` (``step(obs) = (forward(obs), {})``).
    """

    def __init__(
        self,
        obs_dims: Mapping[NestedKey, int],
        out_dim: int,
        hidden: int = 256,
        layers: int = 2,
        symlog_inputs: bool = True,
    ) -> None:
        super().__init__()
        if not obs_dims:
            raise ValueError("obs_dims: expected at least one observation key, got an empty mapping")
        self.obs_dims = dict(obs_dims)
        self.out_dim = out_dim
        self.symlog_inputs = symlog_inputs
        self.net = mlp(sum(self.obs_dims.values()), hidden, out_dim, layers)

    @property
    def obs_keys(self) -> tuple[NestedKey, ...]:
        return tuple(self.obs_dims)

    def forward(self, obs: Mapping[NestedKey, torch.Tensor]) -> torch.Tensor:
        parts = []
        for k, d in self.obs_dims.items():
            x = obs[k]
            _check_last_dim(f"observation {k!r}", x, d)
            parts.append(x.float())
        x = torch.cat(parts, dim=-1)
        return self.net(symlog(x) if self.symlog_inputs else x)


class MLPObsDecoder(nn.Module):
    """Default decoder: latent ``[*B, D + S]`` -> ``{key: [*B, d_key]}`` (one MLP, output split per key)."""

    def __init__(self, latent_dim: int, obs_dims: Mapping[NestedKey, int], hidden: int = 256, layers: int = 2):
        super().__init__()
        self.obs_dims = dict(obs_dims)
        self.net = mlp(latent_dim, hidden, sum(self.obs_dims.values()), layers)

    def forward(self, latent: torch.Tensor) -> dict[NestedKey, torch.Tensor]:
        out = self.net(latent).split(list(self.obs_dims.values()), dim=-1)
        return dict(zip(self.obs_dims.keys(), out))
