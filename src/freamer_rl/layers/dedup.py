"""Evaluate a row-wise function once per distinct input row (eager mode only; same maths).

Several modality branches see the same input row many times in one batch: a MiniGrid mission is constant within
an episode (and often across the whole run), and a sparse reward history is all zeros for most steps. A PPO
minibatch of 512 steps then holds one or a handful of distinct rows for those branches, and computing the flow
matching refiner (4 Euler steps of an MLP) or the reward encoder on every row wastes most of their forward and
backward time. :func:`dedup_rows` runs ``fn`` on the distinct rows and gathers the result back:

    out = fn(x[first])[inverse]        with x[first][inverse] == x (exactly)

Each output row is ``fn`` of the same input values, so the forward is the same maths (results can differ in the
last bits because a matmul over fewer rows may block differently). Gradients flow through the gather: a duplicate
row's gradient is added to its representative row, so parameter gradients inside ``fn`` are the same sums. For an
input that itself requires grad, the gradient of every duplicate reaches the upstream graph through the
representative row; that equals the reference whenever equal rows have equal upstream Jacobians, which holds for
rows computed from equal observations (how duplicates arise here; the tests check parameter gradients end to end).

Finding duplicates reads values on the host, so it is skipped under ``torch.vmap``/``torch.func``/``torch.compile``
and when :func:`~freamer_rl.layers.checks.set_value_checks` switched value checks off (e.g. on an accelerator):
``fn`` then runs on every row. It is also skipped for batches under :data:`MIN_ROWS` rows (a collection step: overhead-bound, nothing to win)
and when fewer than half the rows repeat.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from freamer_rl.layers.checks import value_checks_active

__all__ = ["dedup_rows", "distinct_rows"]

#: Batches with fewer rows are computed directly (for 16 rows the search costs about what it saves).
MIN_ROWS = 64

_PROBES: dict[tuple[int, torch.device], torch.Tensor] = {}


def _probe(width: int, device: torch.device) -> torch.Tensor:
    """A fixed random vector ``[width]`` (float64) for hashing rows; its own generator leaves torch's RNG alone."""
    key = (width, device)
    if key not in _PROBES:
        gen = torch.Generator().manual_seed(0x5EED + width)
        _PROBES[key] = torch.randn(width, generator=gen, dtype=torch.float64).to(device)
    return _PROBES[key]


def distinct_rows(x: torch.Tensor, max_fraction: float = 0.5) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Representatives of the distinct rows of ``x [B, ...]``: ``(first [U], inverse [B])`` with
    ``x[first][inverse]`` equal to ``x`` element for element, or ``None`` when ``U > max_fraction * B``, when
    ``B < MIN_ROWS``, when a row holds NaN (never equal to itself), or when values may not be read (see the module
    docstring).

    Rows are hashed by one projection on a fixed random vector (float64), then the candidate grouping is verified
    exactly, so a hash collision can only make it return ``None``, never merge two different rows.
    """
    b = x.shape[0] if x.ndim else 0
    if b < max(MIN_ROWS, 2) or not value_checks_active(x):
        return None
    rows = x.reshape(b, -1)
    if rows.shape[1] == 0:
        return None
    keys = rows.to(torch.float64) @ _probe(rows.shape[1], rows.device)
    uniq, inverse = torch.unique(keys, return_inverse=True)
    if uniq.shape[0] > max_fraction * b:
        return None
    first = torch.full((uniq.shape[0],), b, dtype=torch.long, device=x.device)
    first = first.scatter_reduce(0, inverse, torch.arange(b, device=x.device), reduce="amin")
    if not bool((rows[first][inverse] == rows).all()):  # a hash collision or NaN: no shortcut
        return None
    return first, inverse


def dedup_rows(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """``fn(x)`` for a row-wise ``fn`` (``[B, ...] -> [B, ...]``, output row ``i`` depends on input row ``i`` only),
    evaluated once per distinct row of ``x`` and gathered when at least half the rows repeat."""
    found = distinct_rows(x)
    if found is None:
        return fn(x)
    first, inverse = found
    return fn(x[first])[inverse]
