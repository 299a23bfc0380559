"""Scoring an anomaly detector against labelled intervals (plain numpy; no sklearn).

Inputs are per-step arrays of one recording (``N`` steps of ``step_s`` seconds): a score (the world model's KL, or
the detector's z-score), the detector's flags, and the labelled events as step intervals ``[E, 2]`` (``[start,
end)``, from :func:`interval_steps`).

Event level (the target's unit):

- an event is **detected** when a flagged step lies in ``[start, end + tolerance)``;
- a **false alarm** is a maximal run of flagged steps outside every event's ``[start, end + tolerance)``;
- ``recall = detected / events``, ``precision = detected / (detected + false alarms)``, ``fa_per_hour = false
  alarms / (N step_s / 3600)`` (hours of the whole recording).

Step level, threshold-free (``valid`` steps only; labels = step inside an event):

- **strict**: AUROC (Mann-Whitney, ties counted half) and AUC-PR (average precision: ``sum_k (R_k - R_{k-1}) P_k``
  over the distinct thresholds, descending) of the per-step score; precision / recall / F1 of the flags;
- **point-adjusted** beside it: every step of an event takes the event's largest score (flags: the whole event is
  flagged once any step of it is). Point adjustment credits a whole event to one lucky step, so it overstates;
  the strict numbers are the honest ones.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = [
    "interval_steps",
    "event_mask",
    "flag_runs",
    "event_metrics",
    "auroc",
    "average_precision",
    "point_adjust_scores",
    "point_adjust_flags",
    "step_metrics",
    "score_report",
]


def interval_steps(starts_s, ends_s, step_end_s, step_s: float) -> np.ndarray:
    """Step intervals int64 ``[E, 2]`` of time intervals ``[start_s, end_s)``.

    Step ``t`` covers ``(step_end_s[t] - step_s, step_end_s[t]]`` (a window ending at ``step_end_s[t]``,
    ascending); it belongs to an interval when the two overlap. An interval between two step ends still gets the
    step whose window contains it.
    """
    ends = np.asarray(step_end_s, dtype=np.float64)
    first = np.searchsorted(ends, np.asarray(starts_s, dtype=np.float64), side="right")
    last = np.searchsorted(ends - step_s, np.asarray(ends_s, dtype=np.float64), side="left")
    return np.stack([first, np.maximum(last, first + 1)], axis=-1).clip(0, ends.shape[0]).astype(np.int64)


def event_mask(events: np.ndarray, n: int, tolerance: int = 0) -> np.ndarray:
    """bool ``[n]``: steps inside some event ``[start, end + tolerance)``."""
    diff = np.zeros(n + 1, dtype=np.int64)
    ev = np.asarray(events, dtype=np.int64).reshape(-1, 2)
    np.add.at(diff, np.clip(ev[:, 0], 0, n), 1)
    np.add.at(diff, np.clip(ev[:, 1] + tolerance, 0, n), -1)
    return np.cumsum(diff[:n]) > 0


def flag_runs(flags: np.ndarray) -> np.ndarray:
    """Maximal runs of True as int64 ``[R, 2]`` ``[start, end)``."""
    f = np.concatenate([[False], np.asarray(flags, dtype=bool), [False]])
    edges = np.flatnonzero(f[1:] != f[:-1])
    return edges.reshape(-1, 2).astype(np.int64)


def event_metrics(flags: np.ndarray, events: np.ndarray, *, step_s: float, tolerance: int = 0) -> dict:
    """Event-level detection (module docstring): ``events``, ``detected``, ``recall``, ``false_alarms``,
    ``fa_per_hour``, ``precision``, ``f1``, ``hours``, ``detected_mask`` (bool ``[E]``) and ``delay_s`` (mean time
    from an event's start to its first flag, over the detected events; NaN if none)."""
    flags = np.asarray(flags, dtype=bool)
    n = flags.shape[0]
    ev = np.asarray(events, dtype=np.int64).reshape(-1, 2)
    csum = np.concatenate([[0], np.cumsum(flags)])
    hi = np.clip(ev[:, 1] + tolerance, 0, n)
    detected = csum[hi] - csum[np.clip(ev[:, 0], 0, n)] > 0
    false_alarms = flag_runs(flags & ~event_mask(ev, n, tolerance)).shape[0]
    delays = [float(np.argmax(flags[s:h])) * step_s for (s, _), h, d in zip(ev, hi, detected) if d]
    hours = n * step_s / 3600.0
    n_det = int(detected.sum())
    recall = n_det / ev.shape[0] if ev.shape[0] else math.nan
    precision = n_det / (n_det + false_alarms) if n_det + false_alarms else math.nan
    return {
        "events": int(ev.shape[0]),
        "detected": n_det,
        "recall": recall,
        "false_alarms": int(false_alarms),
        "fa_per_hour": false_alarms / hours if hours > 0 else math.nan,
        "precision": precision,
        "f1": _f1(precision, recall),
        "hours": hours,
        "delay_s": float(np.mean(delays)) if delays else math.nan,
        "detected_mask": detected,
    }


def _f1(p: float, r: float) -> float:
    return 2 * p * r / (p + r) if (p + r) > 0 else (math.nan if math.isnan(p) or math.isnan(r) else 0.0)


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """1-based ranks of ``x`` with ties given their average rank."""
    order = np.argsort(x, kind="mergesort")
    xs = x[order]
    starts = np.flatnonzero(np.concatenate([[True], xs[1:] != xs[:-1]]))
    ends = np.concatenate([starts[1:], [xs.shape[0]]])
    avg = (starts + ends + 1) / 2.0  # mean of the 1-based ranks starts+1 .. ends
    ranks = np.empty(x.shape[0])
    ranks[order] = np.repeat(avg, ends - starts)
    return ranks


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve: ``P(score_pos > score_neg) + 0.5 P(equal)``; NaN without both classes."""
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return math.nan
    r = _average_ranks(s)
    return float((r[y].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """AUC-PR as average precision ``sum_k (R_k - R_{k-1}) P_k`` over distinct thresholds; NaN without positives."""
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    n_pos = int(y.sum())
    if n_pos == 0:
        return math.nan
    order = np.argsort(-s, kind="mergesort")
    s, y = s[order], y[order]
    last = np.flatnonzero(np.concatenate([s[1:] != s[:-1], [True]]))  # end of each tie group
    tp = np.cumsum(y)[last]
    precision = tp / (last + 1)
    recall = tp / n_pos
    return float(np.sum(np.diff(np.concatenate([[0.0], recall])) * precision))


def point_adjust_scores(scores: np.ndarray, events: np.ndarray) -> np.ndarray:
    """A copy of ``scores`` in which every step of an event holds the event's largest (finite) score."""
    out = np.array(scores, dtype=np.float64, copy=True)
    for s, e in np.asarray(events, dtype=np.int64).reshape(-1, 2):
        seg = out[s:e]
        if seg.size and np.isfinite(seg).any():
            seg[:] = np.nanmax(np.where(np.isfinite(seg), seg, np.nan))
    return out


def point_adjust_flags(flags: np.ndarray, events: np.ndarray) -> np.ndarray:
    """A copy of ``flags`` in which every event with a flagged step is flagged whole."""
    out = np.array(flags, dtype=bool, copy=True)
    for s, e in np.asarray(events, dtype=np.int64).reshape(-1, 2):
        if out[s:e].any():
            out[s:e] = True
    return out


def step_metrics(flags: np.ndarray, labels: np.ndarray) -> dict:
    """Step-level ``precision``, ``recall``, ``f1`` of bool ``flags`` against bool ``labels`` (NaN when undefined)."""
    f, y = np.asarray(flags, dtype=bool), np.asarray(labels, dtype=bool)
    tp = int((f & y).sum())
    precision = tp / int(f.sum()) if f.any() else math.nan
    recall = tp / int(y.sum()) if y.any() else math.nan
    return {"precision": precision, "recall": recall, "f1": _f1(precision, recall)}


def score_report(
    scores: np.ndarray,
    flags: np.ndarray,
    events: np.ndarray,
    *,
    step_s: float,
    tolerance: int = 0,
    valid: np.ndarray | None = None,
    kinds: Sequence[str] | None = None,
) -> dict:
    """Every metric of the module docstring, as a JSON-ready dict.

    Args:
        scores: float ``[N]`` per-step score (higher = more anomalous; non-finite steps are left out of the
            threshold-free metrics).
        flags: bool ``[N]`` the detector's flags.
        events: int ``[E, 2]`` step intervals.
        step_s: seconds per step.
        tolerance: steps after an event's end in which a flag still detects it (not a false alarm).
        valid: bool ``[N]`` steps to score (default: all with a finite score).
        kinds: ``[E]`` the events' kinds, for the per-kind recall.
    Returns:
        ``{"event": {...}, "strict": {...}, "point_adjusted": {...}, "recall_by_kind": {...}}`` (NaN -> None).
    """
    scores = np.asarray(scores, dtype=np.float64)
    n = scores.shape[0]
    flags = np.asarray(flags, dtype=bool)
    ev = np.asarray(events, dtype=np.int64).reshape(-1, 2)
    ok = np.isfinite(scores) if valid is None else np.asarray(valid, dtype=bool) & np.isfinite(scores)
    labels = event_mask(ev, n)
    event = event_metrics(flags, ev, step_s=step_s, tolerance=tolerance)
    detected = event.pop("detected_mask")
    pa_scores = point_adjust_scores(np.where(ok, scores, np.nan), ev)
    strict = {
        "auroc": auroc(scores[ok], labels[ok]),
        "auc_pr": average_precision(scores[ok], labels[ok]),
        **step_metrics(flags[ok], labels[ok]),
    }
    adjusted = {
        "auroc": auroc(pa_scores[ok], labels[ok]),
        "auc_pr": average_precision(pa_scores[ok], labels[ok]),
        **step_metrics(point_adjust_flags(flags, ev)[ok], labels[ok]),
    }
    by_kind: dict[str, float] = {}
    if kinds is not None:
        k_arr = np.asarray(list(kinds))
        for k in dict.fromkeys(kinds):
            by_kind[k] = float(detected[k_arr == k].mean())
    report = {
        "event": event,
        "strict": strict,
        "point_adjusted": adjusted,
        "recall_by_kind": by_kind,
        "steps": int(n),
        "anomalous_steps": int(labels.sum()),
        "flagged_steps": int(flags.sum()),
        "tolerance_steps": int(tolerance),
    }
    return _none_for_nan(report)


def _none_for_nan(x):
    if isinstance(x, dict):
        return {k: _none_for_nan(v) for k, v in x.items()}
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
