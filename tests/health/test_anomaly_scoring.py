"""Scoring anomaly flags against labelled intervals: closed-form event counts, AUROC, AUC-PR, point adjustment."""

import itertools
import math

import numpy as np
import pytest

from freamer_rl.health.anomaly_scoring import (
    auroc,
    average_precision,
    event_mask,
    event_metrics,
    flag_runs,
    interval_steps,
    point_adjust_flags,
    point_adjust_scores,
    score_report,
)

# 100 steps of 36 s = exactly one hour; three events
EVENTS = np.array([[10, 20], [40, 45], [70, 80]])


def hand_flags():
    f = np.zeros(100, dtype=bool)
    f[[12, 13]] = True  # inside event 0 (first flag 2 steps after its start)
    f[46] = True  # one step after event 1 ends (inside a tolerance of 2)
    f[50:53] = True  # one run outside every event
    f[90] = True  # another
    return f


def test_event_metrics_strict_and_with_tolerance():
    m = event_metrics(hand_flags(), EVENTS, step_s=36.0, tolerance=0)
    assert m["hours"] == pytest.approx(1.0)
    assert (m["events"], m["detected"], m["false_alarms"]) == (3, 1, 3)  # 46, 50-52, 90
    assert m["recall"] == pytest.approx(1 / 3)
    assert m["precision"] == pytest.approx(1 / 4)
    assert m["fa_per_hour"] == pytest.approx(3.0)
    assert m["f1"] == pytest.approx(2 * (1 / 4) * (1 / 3) / (1 / 4 + 1 / 3))
    assert m["delay_s"] == pytest.approx(2 * 36.0)
    assert m["detected_mask"].tolist() == [True, False, False]
    m = event_metrics(hand_flags(), EVENTS, step_s=36.0, tolerance=2)
    assert (m["detected"], m["false_alarms"]) == (2, 2)  # step 46 now detects event 1
    assert m["recall"] == pytest.approx(2 / 3) and m["precision"] == pytest.approx(0.5)
    assert m["delay_s"] == pytest.approx((2 + 6) * 36.0 / 2)  # event 1: first flag 6 steps after its start


def test_runs_masks_and_interval_steps():
    assert flag_runs(hand_flags()).tolist() == [[12, 14], [46, 47], [50, 53], [90, 91]]
    assert flag_runs(np.ones(3, bool)).tolist() == [[0, 3]] and flag_runs(np.zeros(3, bool)).shape == (0, 2)
    m = event_mask(np.array([[1, 3], [5, 6]]), 8, tolerance=1)
    assert m.tolist() == [False, True, True, True, False, True, True, False]
    # step t covers (end_t - 5, end_t]; [6, 12) touches steps 1 and 2, [10, 10.5) only step 2, [0, 1) step 0
    ends = np.array([5.0, 10.0, 15.0, 20.0])
    got = interval_steps([6.0, 10.0, 0.0, 18.0], [12.0, 10.5, 1.0, 20.0], ends, 5.0)
    assert got.tolist() == [[1, 3], [2, 3], [0, 1], [3, 4]]


def brute_auroc(s, y):
    pos, neg = s[y], s[~y]
    wins = sum(1.0 if p > n else 0.5 if p == n else 0.0 for p, n in itertools.product(pos, neg))
    return wins / (len(pos) * len(neg))


def test_auroc_and_average_precision_closed_form():
    s = np.array([0.1, 0.4, 0.35, 0.8])
    y = np.array([False, False, True, True])
    assert auroc(s, y) == pytest.approx(0.75)
    # thresholds 0.8 (P=1, R=.5), 0.4 (P=.5, R=.5), 0.35 (P=2/3, R=1): AP = .5 * 1 + .5 * 2/3
    assert average_precision(s, y) == pytest.approx(0.5 + 0.5 * 2 / 3)
    # ties: one group holding a positive and a negative counts half
    assert auroc(np.array([1.0, 1.0, 0.0, 0.0]), np.array([True, False, True, False])) == pytest.approx(0.5)
    assert average_precision(np.array([1.0, 1.0, 0.0]), np.array([True, False, False])) == pytest.approx(0.5)
    assert math.isnan(auroc(s, np.zeros(4, bool))) and math.isnan(average_precision(s, np.zeros(4, bool)))
    rng = np.random.default_rng(0)
    s = rng.integers(0, 5, size=60).astype(float)  # many ties
    y = rng.random(60) < 0.3
    assert auroc(s, y) == pytest.approx(brute_auroc(s, y))


def test_point_adjustment_credits_the_whole_event():
    s = np.array([0.5, 0.2, 0.9, 0.1, 0.1, 0.3])
    ev = np.array([[2, 5]])
    y = event_mask(ev, 6)
    assert auroc(s, y) == pytest.approx(1 / 3)  # only 0.9 beats the three normal scores
    pa = point_adjust_scores(s, ev)
    assert pa.tolist() == [0.5, 0.2, 0.9, 0.9, 0.9, 0.3]
    assert auroc(pa, y) == pytest.approx(1.0)
    f = np.array([False, False, False, True, False, True])
    assert point_adjust_flags(f, ev).tolist() == [False, False, True, True, True, True]
    assert s.tolist() == [0.5, 0.2, 0.9, 0.1, 0.1, 0.3]  # inputs untouched


def test_score_report_keys_and_nan_as_none():
    rng = np.random.default_rng(1)
    scores = rng.random(100)
    scores[EVENTS[0, 0] : EVENTS[0, 1]] += 2.0  # event 0 separable
    rep = score_report(scores, hand_flags(), EVENTS, step_s=36.0, kinds=["a", "b", "a"])
    assert rep["event"]["recall"] == pytest.approx(1 / 3) and rep["recall_by_kind"] == {"a": 0.5, "b": 0.0}
    for part in ("strict", "point_adjusted"):
        assert set(rep[part]) == {"auroc", "auc_pr", "precision", "recall", "f1"}
    assert rep["point_adjusted"]["auroc"] >= rep["strict"]["auroc"]
    assert rep["anomalous_steps"] == 25 and rep["flagged_steps"] == 7
    # step-level strict recall: 2 of the 25 event steps are flagged
    assert rep["strict"]["recall"] == pytest.approx(2 / 25)
    empty = score_report(scores, np.zeros(100, bool), np.zeros((0, 2), int), step_s=36.0)
    assert empty["event"]["recall"] is None and empty["strict"]["auroc"] is None
    assert empty["event"]["false_alarms"] == 0 and empty["event"]["fa_per_hour"] == 0.0
