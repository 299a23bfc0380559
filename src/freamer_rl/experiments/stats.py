"""Aggregate statistics for suite reports, after Agarwal et al., "Deep RL at the Edge of the Statistical Precipice"
(NeurIPS 2021; its library is ``rliable``): interquartile mean, stratified-bootstrap confidence intervals,
probability of improvement. Written on numpy (``rliable`` needs arch, pandas and seaborn besides).

Scores are given per task as 1-D arrays over seeds (``{task: [s_seed0, s_seed1, ...]}``); a single task is a
one-entry mapping. "Stratified" means each bootstrap replicate resamples the seeds of every task separately, so a task
with more seeds does not crowd out the others.

    iqm_ci({"N2-S4": [1038, 1729, 1517, 1250, 1402]})     # -> (point, low, high)
    probability_of_improvement(a_scores, b_scores)          # -> (P(A > B), low, high)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np

__all__ = [
    "is_missing",
    "iqm",
    "stratified_bootstrap_ci",
    "iqm_ci",
    "subject_bootstrap_ci",
    "mean_ratio_ci",
    "difference_ci",
    "probability_of_improvement",
]

Scores = Mapping[str, Sequence[float]]


def is_missing(value: object) -> bool:
    """A value a report leaves out: ``None`` or a float NaN (summary.json writes NaN as null)."""
    return value is None or (isinstance(value, float) and math.isnan(value))


def iqm(values: Sequence[float]) -> float:
    """Interquartile mean: the mean of the values left after cutting ``floor(n / 4)`` from each end of the sorted
    list (``scipy.stats.trim_mean(x, 0.25)``, what rliable uses). NaN for no values."""
    x = np.sort(np.asarray(values, dtype=float).reshape(-1))
    if not x.size:
        return float("nan")
    cut = x.size // 4
    return float(x[cut : x.size - cut].mean())


def _as_arrays(scores: Scores) -> dict[str, np.ndarray]:
    out = {task: np.asarray(v, dtype=float).reshape(-1) for task, v in scores.items()}
    empty = [t for t, v in out.items() if not v.size]
    if not out or empty:
        raise ValueError(f"scores: every task needs at least one seed (empty: {empty or 'no tasks'})")
    return out


def stratified_bootstrap_ci(
    scores: Scores,
    statistic: Callable[[np.ndarray], float],
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """``(statistic of all scores, low, high)``: the percentile interval of ``statistic`` over ``reps`` replicates,
    each resampling every task's seeds with replacement (stratified)."""
    arrays = _as_arrays(scores)
    rng = np.random.default_rng(seed)
    point = statistic(np.concatenate(list(arrays.values())))
    reps_values = np.empty(reps)
    for r in range(reps):
        reps_values[r] = statistic(np.concatenate([v[rng.integers(0, v.size, v.size)] for v in arrays.values()]))
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(reps_values, [tail, 100 - tail])
    return float(point), float(low), float(high)


def iqm_ci(scores: Scores, **options) -> tuple[float, float, float]:
    """IQM over every task's seeds with its stratified-bootstrap 95% interval (``options`` as
    :func:`stratified_bootstrap_ci`)."""
    return stratified_bootstrap_ci(scores, iqm, **options)


def subject_bootstrap_ci(
    scores: Scores, *, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """``(mean over groups of each group's mean, low, high)`` for scores grouped by held-out subject (leave-one-subject-
    out folds): every group weighs the same whatever its number of seeds. Two-level bootstrap: each replicate draws
    the groups with replacement, then each drawn group's seeds with replacement, so the interval covers a new subject
    as well as a new seed (with one seed per fold it is the bootstrap over subjects). One group: seeds only."""
    arrays = list(_as_arrays(scores).values())
    rng = np.random.default_rng(seed)
    point = float(np.mean([v.mean() for v in arrays]))
    values = np.empty(reps)
    for r in range(reps):
        groups = rng.integers(0, len(arrays), len(arrays)) if len(arrays) > 1 else [0]
        values[r] = np.mean([arrays[g][rng.integers(0, arrays[g].size, arrays[g].size)].mean() for g in groups])
    return (point, *_percentile_interval(values, confidence))


def _prob_greater(x: np.ndarray, y: np.ndarray) -> float:
    """P(X > Y) + P(X = Y) / 2 over all pairs (the Mann-Whitney U statistic, normalised)."""
    diff = x[:, None] - y[None, :]
    return float(((diff > 0) + 0.5 * (diff == 0)).mean())


def probability_of_improvement(
    a: Scores, b: Scores, *, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """``(P(A > B), low, high)``: the probability that a run of A scores higher than a run of B on a task, averaged
    over the tasks both have, with a stratified-bootstrap interval (both arms' seeds resampled per task). For
    "lower is better" scores (frames to 95%), pass them negated. "A ahead of B" needs ``low > 0.5``."""
    a_arr, b_arr = _as_arrays(a), _as_arrays(b)
    tasks = sorted(set(a_arr) & set(b_arr))
    if not tasks:
        raise ValueError(f"probability_of_improvement: no task in common ({sorted(a_arr)} vs {sorted(b_arr)})")
    rng = np.random.default_rng(seed)
    point = float(np.mean([_prob_greater(a_arr[t], b_arr[t]) for t in tasks]))
    values = np.empty(reps)
    for r in range(reps):
        values[r] = np.mean(
            [
                _prob_greater(
                    a_arr[t][rng.integers(0, a_arr[t].size, a_arr[t].size)],
                    b_arr[t][rng.integers(0, b_arr[t].size, b_arr[t].size)],
                )
                for t in tasks
            ]
        )
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return point, float(low), float(high)


def _two_arm_replicates(x: np.ndarray, y: np.ndarray, stat, reps: int, seed: int) -> np.ndarray:
    """``reps`` bootstrap replicates of ``stat(x*, y*)``, each arm's runs resampled with replacement on their own
    (independent arms: different seeds)."""
    rng = np.random.default_rng(seed)
    return np.array([stat(x[rng.integers(0, x.size, x.size)], y[rng.integers(0, y.size, y.size)]) for _ in range(reps)])


def _percentile_interval(values: np.ndarray, confidence: float) -> tuple[float, float]:
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def mean_ratio_ci(
    a: Sequence[float], b: Sequence[float], *, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """``(mean(a) / mean(b), low, high)``: the ratio of two arms' mean scores (e.g. Table 15's Foundation / MLP
    reward) with a percentile-bootstrap interval, each arm's seeds resampled on their own. NaN bounds where a
    replicate's ``mean(b)`` is 0."""
    x, y = np.asarray(a, dtype=float).reshape(-1), np.asarray(b, dtype=float).reshape(-1)
    if not x.size or not y.size:
        raise ValueError(f"mean_ratio_ci: both arms need a value (got {x.size} and {y.size})")
    with np.errstate(divide="ignore", invalid="ignore"):
        point = float(x.mean() / y.mean())
        values = _two_arm_replicates(x, y, lambda u, v: u.mean() / v.mean(), reps, seed)
    values = values[np.isfinite(values)]
    if not values.size:
        return point, float("nan"), float("nan")
    return (point, *_percentile_interval(values, confidence))


def difference_ci(
    a: Sequence[float], b: Sequence[float], *, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """``(IQM(a) - IQM(b), low, high)``: the percentile interval over ``reps`` replicates, each resampling the runs
    of ``a`` and of ``b`` on their own (the arms are independent runs); NaNs when an arm has no value."""
    x, y = np.asarray(a, dtype=float).reshape(-1), np.asarray(b, dtype=float).reshape(-1)
    if not x.size or not y.size:
        return math.nan, math.nan, math.nan
    values = _two_arm_replicates(x, y, lambda u, v: iqm(u) - iqm(v), reps, seed)
    return (iqm(x) - iqm(y), *_percentile_interval(values, confidence))
