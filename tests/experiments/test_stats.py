"""Suite statistics (freamer_rl.experiments.stats) against closed forms and scipy where it has the same estimator."""

import math

import numpy as np
import pytest

from freamer_rl.experiments.stats import (
    iqm,
    iqm_ci,
    mean_ratio_ci,
    probability_of_improvement,
    stratified_bootstrap_ci,
    subject_bootstrap_ci,
)


@pytest.mark.parametrize(
    "values, expected",
    [
        ([1, 2, 3, 4, 100], 3.0),  # n=5: cut one from each end -> mean(2, 3, 4)
        ([5, 1, 3, 2], 2.5),  # n=4: cut one each -> mean(2, 3)
        ([7, 7, 7], 7.0),  # n=3: nothing cut
        ([1, 2, 3, 4, 5, 6, 7, 8], 4.5),  # n=8: cut two each -> mean(3..6)
    ],
)
def test_iqm_closed_form(values, expected):
    assert iqm(values) == pytest.approx(expected)


def test_iqm_matches_scipy_trim_mean():
    scipy_stats = pytest.importorskip("scipy.stats")
    x = np.random.default_rng(1).normal(size=37)
    assert iqm(x) == pytest.approx(scipy_stats.trim_mean(x, 0.25))


def test_bootstrap_interval_of_the_mean_matches_the_normal_approximation():
    x = np.random.default_rng(2).normal(10.0, 2.0, size=400)
    point, low, high = stratified_bootstrap_ci({"t": x}, np.mean, reps=4000)
    se = x.std() / np.sqrt(x.size)
    assert point == pytest.approx(x.mean())
    assert low == pytest.approx(x.mean() - 1.96 * se, abs=0.2 * se) and high == pytest.approx(
        x.mean() + 1.96 * se, abs=0.2 * se
    )


def test_stratified_resampling_keeps_each_task_size():
    seen = []
    stratified_bootstrap_ci({"a": [0.0] * 3, "b": [1.0] * 7}, lambda v: seen.append(v.copy()) or 0.0, reps=20)
    # every replicate draws 3 seeds of task a (all 0) and 7 of task b (all 1)
    assert all(v.size == 10 and v.sum() == 7 for v in seen)


def test_iqm_ci_brackets_the_point():
    point, low, high = iqm_ci({"t": [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]})
    assert low <= point <= high and low < high


def test_probability_of_improvement_closed_forms():
    assert probability_of_improvement({"t": [3, 4]}, {"t": [1, 2]})[0] == 1.0
    assert probability_of_improvement({"t": [1, 2]}, {"t": [3, 4]})[0] == 0.0
    assert probability_of_improvement({"t": [1, 2]}, {"t": [1, 2]})[0] == 0.5  # ties count half
    # two tasks: 1.0 on one, 0.0 on the other -> 0.5 on average
    assert probability_of_improvement({"a": [2], "b": [0]}, {"a": [1], "b": [1]})[0] == 0.5
    p, low, high = probability_of_improvement({"t": [5, 6, 7, 8, 9]}, {"t": [1, 2, 3, 4, 5]})
    assert p == pytest.approx(24.5 / 25) and low > 0.5


def test_empty_task_is_refused():
    with pytest.raises(ValueError, match="every task needs at least one seed"):
        iqm_ci({"t": []})


def test_mean_ratio_ci_is_exact_for_constant_arms_and_bounded_by_the_extremes():
    assert mean_ratio_ci([2.0, 2.0, 2.0], [4.0, 4.0]) == (0.5, 0.5, 0.5)
    point, low, high = mean_ratio_ci([48.0, 52.0, 53.0], [50.0, 60.0, 64.0])
    assert point == pytest.approx(51.0 / 58.0)
    # a replicate's means stay within each arm's extremes, so its ratio does too
    assert 48.0 / 64.0 <= low < point < high <= 53.0 / 50.0
    assert all(math.isnan(v) for v in mean_ratio_ci([1.0], [0.0])[1:])  # no finite replicate: NaN bounds


def test_subject_bootstrap_ci_weighs_every_group_alike_and_resamples_the_groups():
    # group a has one seed at 0, b three at 10: the mean of the group means is 5 (the pooled mean would be 7.5); the
    # groups are drawn with replacement, so a replicate is 0 (a, a), 5 (a, b) or 10 (b, b) with odds 1/4, 1/2, 1/4
    point, low, high = subject_bootstrap_ci({"a": [0.0], "b": [10.0, 10.0, 10.0]}, reps=4000)
    assert (point, low, high) == (5.0, 0.0, 10.0)
    # identical groups: nothing can move
    assert subject_bootstrap_ci({"a": [3.0], "b": [3.0], "c": [3.0]}) == (3.0, 3.0, 3.0)
    # one group: only its seeds are resampled, so the interval lies within their range
    point, low, high = subject_bootstrap_ci({"a": [0.0, 2.0]})
    assert point == 1.0 and 0.0 <= low < high <= 2.0
