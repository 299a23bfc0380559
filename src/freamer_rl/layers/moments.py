"""Running mean and variance merged one batch at a time (Chan, Golub & LeVeque's parallel update).

    total = count + n
    mean' = mean + delta * n / total,                                   delta = batch_mean - mean
    var'  = (var * count + batch_var * n + delta^2 * count * n / total) / total

``var`` is the population variance (``unbiased=False``) of everything merged so far. Used by every running statistic
that sees its data in batches: the return normaliser (``machinery.return_norm``), the curiosity reward's error scale
(``machinery.exploration``) and the world model's reconstruction targets (``world_model.rssm``).
"""

from __future__ import annotations

import torch

__all__ = ["merge_moments"]


def merge_moments(
    count: torch.Tensor,
    mean: torch.Tensor,
    var: torch.Tensor,
    n: torch.Tensor | float,
    batch_mean: torch.Tensor,
    batch_var: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(count', mean', var')`` after merging a batch of ``n`` values with moments ``batch_mean``, ``batch_var``
    (population variance) into ``(count, mean, var)``; shapes broadcast (scalars or per-feature ``[D]``). ``count +
    n`` must be > 0. No host sync."""
    total = count + n
    delta = batch_mean - mean
    new_var = (var * count + batch_var * n + delta.square() * count * n / total) / total
    return total, mean + delta * n / total, new_var
