"""Prediction heads and return scaling of the world model and imagination (DreamerV3 options, issue 22 part 2).

Plain ``nn.Module`` s / functions; every one accepts arbitrary leading batch dims ``[*B, ...]``.

* Symlog two-hot (DreamerV3): a scalar ``x`` is represented on ``n`` fixed bins ``b_0 < ... < b_{n-1}`` in symlog
  space (default 255 bins over ``[-20, 20]``). With ``y = clip(symlog(x), b_0, b_{n-1})`` and ``b_k <= y < b_{k+1}``
  the target puts ``w_{k+1} = (y - b_k) / (b_{k+1} - b_k)`` on ``b_{k+1}`` and ``w_k = 1 - w_{k+1}`` on ``b_k``
  (:func:`twohot_encode`); a head predicts logits over the bins and is trained by cross-entropy against that target;
  its value is ``symexp(sum_k softmax(logits)_k b_k)`` (:func:`twohot_decode`). Encoding then decoding the target
  returns ``x`` exactly (inside the bin range).
* :class:`TwoHotHead`: an MLP to ``n`` logits with that decode and a ``loss(feat, target)``.
* :class:`HeadEnsemble`: ``K`` independently initialised heads; ``forward`` is the member mean, :meth:`HeadEnsemble.std`
  the spread over members (the imagined reward minus ``uncertainty_penalty * std`` penalises actions whose outcome the
  members disagree on -- typically the rarely seen ones).
* :func:`head_loss`: a head's own ``loss`` if it has one, else the MSE of its ``[*B, 1]`` output.
* :class:`PercentileReturnScale`: DreamerV3's return normaliser ``S = max(1, EMA(P95) - EMA(P5))`` of the
  lambda-returns (decay 0.99); advantages are divided by ``S``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from freamer_rl.world_model.functional import mlp, symexp, symlog

__all__ = [
    "twohot_bins",
    "twohot_encode",
    "twohot_decode",
    "TwoHotHead",
    "HeadEnsemble",
    "head_loss",
    "PercentileReturnScale",
    "REWARD_HEADS",
]

#: ``world_model.reward_head`` / ``imagination.value_head`` choices
REWARD_HEADS = ("mse", "twohot")


def twohot_bins(num_bins: int = 255, low: float = -20.0, high: float = 20.0) -> torch.Tensor:
    """``[num_bins]`` equally spaced bin centres in symlog space."""
    if num_bins < 2 or not low < high:
        raise ValueError(f"twohot_bins: need num_bins >= 2 and low < high, got {num_bins}, {low}, {high}")
    return torch.linspace(low, high, num_bins)


def twohot_encode(x: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
    """Two-hot target of ``x [*B]`` on ``bins [n]`` (symlog space): ``[*B, n]``, two non-zero weights on the
    neighbouring bins of ``symlog(x)`` (clipped to the bin range), summing to 1."""
    y = symlog(x).clamp(float(bins[0]), float(bins[-1]))
    n = bins.shape[0]
    lo = (torch.searchsorted(bins, y.contiguous(), right=True) - 1).clamp(0, n - 2)
    b_lo, b_hi = bins[lo], bins[lo + 1]
    w_hi = ((y - b_lo) / (b_hi - b_lo)).clamp(0.0, 1.0)
    target = torch.zeros(*x.shape, n, dtype=x.dtype, device=x.device)
    target.scatter_(-1, lo.unsqueeze(-1), (1.0 - w_hi).unsqueeze(-1))
    target.scatter_add_(-1, (lo + 1).unsqueeze(-1), w_hi.unsqueeze(-1))
    return target


def twohot_decode(probs: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
    """``symexp(sum_k p_k b_k)``: bin probabilities ``[*B, n]`` -> value ``[*B]`` (raw units)."""
    return symexp((probs * bins).sum(-1))


class TwoHotHead(nn.Module):
    """Latent ``[*B, in_dim]`` -> ``[*B, 1]`` scalar through symlog two-hot logits (module docstring).

    The last layer starts at zero (DreamerV3): uniform logits, an initial prediction of ``symexp(mean(bins))`` = 0 for
    a symmetric range, so an untrained head predicts no reward instead of a random one.
    """

    def __init__(
        self, in_dim: int, hidden: int, num_bins: int = 255, low: float = -20.0, high: float = 20.0, layers: int = 2
    ) -> None:
        super().__init__()
        self.net = mlp(in_dim, hidden, num_bins, layers=layers)
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)
        self.register_buffer("bins", twohot_bins(num_bins, low, high))

    def logits(self, feat: torch.Tensor) -> torch.Tensor:
        return self.net(feat)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return twohot_decode(torch.softmax(self.net(feat), dim=-1), self.bins).unsqueeze(-1)

    def loss(self, feat: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Mean cross-entropy ``-sum_k twohot(target)_k log softmax(logits)_k``; ``feat [*B, in]``, ``target [*B]``."""
        logp = F.log_softmax(self.net(feat), dim=-1)
        return -(twohot_encode(target.to(logp.dtype), self.bins) * logp).sum(-1).mean()


def head_loss(head: nn.Module, feat: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The head's own ``loss(feat, target)`` (two-hot, ensembles) or the MSE of its ``[*B, 1]`` output vs
    ``target [*B]``."""
    if hasattr(head, "loss"):
        return head.loss(feat, target)
    return F.mse_loss(head(feat).squeeze(-1), target)


class HeadEnsemble(nn.Module):
    """``K`` heads of the same kind (independent initialisations, the same data): ``forward`` = member mean
    ``[*B, 1]``, :meth:`members` ``[K, *B, 1]``, :meth:`std` the population std over members ``[*B, 1]`` (zero when
    every member predicts the same), :meth:`loss` the mean of the members' losses."""

    def __init__(self, members: list[nn.Module]) -> None:
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"HeadEnsemble: expected >= 2 members, got {len(members)}")
        self.heads = nn.ModuleList(members)

    def members(self, feat: torch.Tensor) -> torch.Tensor:
        return torch.stack([h(feat) for h in self.heads])

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return self.members(feat).mean(0)

    def std(self, feat: torch.Tensor) -> torch.Tensor:
        return self.members(feat).std(0, unbiased=False)

    def loss(self, feat: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return torch.stack([head_loss(h, feat, target) for h in self.heads]).mean()


class PercentileReturnScale(nn.Module):
    """DreamerV3's return scale: ``S = max(1, hi - lo)`` with ``lo``/``hi`` EMAs (``decay``) of the 5th / 95th
    percentiles of the lambda-returns seen (the first batch initialises them). ``update(returns)`` takes any shape,
    returns the new ``S`` (a 0-d tensor, no host sync); divide the advantages by it."""

    def __init__(self, decay: float = 0.99, low_q: float = 0.05, high_q: float = 0.95) -> None:
        super().__init__()
        if not 0.0 <= decay < 1.0 or not 0.0 <= low_q < high_q <= 1.0:
            raise ValueError(
                f"PercentileReturnScale: decay in [0, 1) and 0 <= low_q < high_q <= 1, got {decay}, {low_q}, {high_q}"
            )
        self.decay, self.low_q, self.high_q = decay, low_q, high_q
        self.register_buffer("lo", torch.zeros(()))
        self.register_buffer("hi", torch.zeros(()))
        self.register_buffer("count", torch.zeros(()))

    @torch.no_grad()
    def update(self, returns: torch.Tensor) -> torch.Tensor:
        flat = returns.detach().float().flatten()
        q = torch.quantile(flat, torch.tensor([self.low_q, self.high_q], device=flat.device))
        d = torch.where(self.count > 0, torch.full_like(self.lo, self.decay), torch.zeros_like(self.lo))
        self.lo.copy_(d * self.lo + (1 - d) * q[0])
        self.hi.copy_(d * self.hi + (1 - d) * q[1])
        self.count.add_(1)
        return self.scale()

    def scale(self) -> torch.Tensor:
        return torch.clamp(self.hi - self.lo, min=1.0)


def make_scalar_head(kind: str, in_dim: int, hidden: int, ensemble: int = 1) -> nn.Module:
    """A scalar head ``[*B, in_dim] -> [*B, 1]``: ``"mse"`` (a plain :func:`mlp`) or ``"twohot"``
    (:class:`TwoHotHead`); ``ensemble`` K > 1 gives a :class:`HeadEnsemble` of K such heads."""
    if kind not in REWARD_HEADS:
        raise ValueError(f"head kind: expected one of {REWARD_HEADS}, got {kind!r}")
    if ensemble < 1:
        raise ValueError(f"ensemble: expected >= 1 members, got {ensemble}")

    def one() -> nn.Module:
        return mlp(in_dim, hidden, 1) if kind == "mse" else TwoHotHead(in_dim, hidden)

    return one() if ensemble == 1 else HeadEnsemble([one() for _ in range(ensemble)])
