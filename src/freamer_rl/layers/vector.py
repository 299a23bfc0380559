"""Layer 1 encoder for plain vector observations (``"observation"`` of a gymnasium env, joint angles, sensor features).

``VectorEncoder``: ``x [*B, F]`` (float) -> ``[*B, d]`` as ``Linear(F, h) -> LayerNorm -> SiLU -> Linear(h, d)``
applied to ``symlog(x) = sign(x) * log(1 + |x|)``.

Why this encoder. A vector observation carries no spatial or sequential structure for an FNO, CNN or transformer to
exploit, so a small MLP is the honest choice. Its features arrive on unknown, mixed scales (CartPole's angular
velocity is unbounded, Pendulum's reaches 8, a sensor may read thousands). ``symlog`` (DreamerV3) compresses large
magnitudes while staying ~linear near 0, without running statistics: the encoder stays a pure function of its
input, so collection and the PPO update see exactly the same embedding, and vmap / compile need no state. The
LayerNorm after the first projection keeps the embedding's scale comparable with the other modalities' before the
flow-matching refiner (Layer 2) and the FNO fusion (Layer 3).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from freamer_rl.layers.checks import check_finite

__all__ = ["VectorEncoder", "symlog"]


def symlog(x: torch.Tensor) -> torch.Tensor:
    """``sign(x) * log(1 + |x|)`` elementwise (same shape)."""
    return torch.sign(x) * torch.log1p(x.abs())


class VectorEncoder(nn.Module):
    """Plain vector observations -> one modality embedding.

    Args:
        in_features: ``F``, the total size of the (flattened, concatenated) observation entries.
        out_dim: ``d``.
        hidden: width ``h`` of the hidden layer.
        in_shapes: trailing shapes of the observation entries, one per positional input (default: one entry of
            shape ``(F,)``). Each input ``[*B, *shape_i]`` is flattened to ``[*B, prod(shape_i)]`` and the pieces
            are concatenated in order.

    Shapes:
        forward: ``*xs`` with ``xs[i] [*B, *in_shapes[i]]`` -> ``[*B, out_dim]``.

    A NaN/Inf input raises ``ValueError`` in eager mode (skipped, same maths, under vmap/compile).
    """

    def __init__(
        self, in_features: int, out_dim: int, hidden: int = 128, in_shapes: list[tuple[int, ...]] | None = None
    ) -> None:
        super().__init__()
        if in_features < 1 or out_dim < 1 or hidden < 1:
            raise ValueError(
                f"in_features, out_dim and hidden must be positive; got {in_features}, {out_dim}, {hidden}"
            )
        self.in_shapes = [tuple(s) for s in (in_shapes or [(in_features,)])]
        sizes = [int(torch.Size(s).numel()) for s in self.in_shapes]
        if sum(sizes) != in_features:
            raise ValueError(f"in_shapes {self.in_shapes} hold {sum(sizes)} features, not in_features={in_features}")
        self.in_features = in_features
        self.out_dim = out_dim
        self.inp = nn.Linear(in_features, hidden)
        self.norm = nn.LayerNorm(hidden)
        self.out = nn.Linear(hidden, out_dim)

    def forward(self, *xs: torch.Tensor) -> torch.Tensor:
        if len(xs) != len(self.in_shapes):
            raise ValueError(f"VectorEncoder: expected {len(self.in_shapes)} inputs, got {len(xs)}")
        flat = []
        batch_shape = None
        for i, (x, shape) in enumerate(zip(xs, self.in_shapes)):
            n = len(shape)
            if tuple(x.shape[x.ndim - n :]) != shape or x.ndim < n:
                raise ValueError(
                    f"VectorEncoder input {i}: expected [*B, {', '.join(map(str, shape))}], got {tuple(x.shape)}"
                )
            lead = x.shape[: x.ndim - n]
            if batch_shape is None:
                batch_shape = lead
            elif lead != batch_shape:
                raise ValueError(f"VectorEncoder input {i}: batch dims {tuple(lead)} differ from {tuple(batch_shape)}")
            check_finite(x, f"VectorEncoder input {i}")
            flat.append(x.reshape(*lead, -1).to(self.inp.weight.dtype))
        h = torch.cat(flat, dim=-1) if len(flat) > 1 else flat[0]
        return self.out(F.silu(self.norm(self.inp(symlog(h)))))
