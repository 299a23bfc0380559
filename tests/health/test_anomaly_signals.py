"""The per-channel anomaly signals (freamer_rl.health.anomaly_signals): closed-form checks."""

import numpy as np
import pytest

from freamer_rl.health.anomaly_signals import channel_zscore, heart_rate_zscore, stale_mask, with_stale


@pytest.mark.parametrize("n, d", [(40, 1), (64, 5)])
def test_channel_zscore_is_the_largest_residual_in_its_own_running_rms(n, d):
    rng = np.random.default_rng(0)
    scale = np.geomspace(0.01, 10.0, d)  # channels of very different noise levels
    r = rng.normal(size=(n, d)) * scale
    include = np.ones(n, dtype=bool)
    include[[3, 17]] = False
    got = channel_zscore(r, include, warmup=5)
    for t in range(n):
        before = include[:t]
        if not include[t] or before.sum() < 5:
            assert np.isnan(got[t])
            continue
        rms = np.sqrt((r[:t][before] ** 2).mean(axis=0))
        assert got[t] == pytest.approx((np.abs(r[t]) / rms).max())


def test_channel_zscore_finds_a_jump_in_the_quiet_channel_the_mean_hides():
    """A 10x-its-noise jump in a quiet channel beside a loud one: the channel score sees it, the mean square does
    not rank it first."""
    rng = np.random.default_rng(1)
    r = np.stack([rng.normal(size=500) * 5.0, rng.normal(size=500) * 0.1], axis=1)
    r[400, 1] += 1.0
    score = channel_zscore(r, np.ones(500, dtype=bool))
    assert np.nanargmax(score) == 400 and score[400] > 8
    assert np.argmax((r**2).mean(axis=1)) != 400


def test_channel_zscore_checks_shapes():
    with pytest.raises(ValueError, match=r"residual \[N, D\] and include \[N\]"):
        channel_zscore(np.zeros((4, 2)), np.ones(3, dtype=bool))


def test_stale_mask_counts_repeats_in_a_row():
    x = np.array([[0, 1], [0, 1], [0, 1], [0, 2], [0, 2], [0, 2], [0, 2], [5, 5]], dtype=np.float32)
    np.testing.assert_array_equal(stale_mask(x, 1), [0, 1, 1, 0, 1, 1, 1, 0])
    np.testing.assert_array_equal(stale_mask(x, 2), [0, 0, 1, 0, 0, 1, 1, 0])
    np.testing.assert_array_equal(stale_mask(x, 3), [0, 0, 0, 0, 0, 0, 1, 0])
    assert not stale_mask(x, 0).any() and not stale_mask(x[:1], 1).any()


def test_with_stale_ranks_stale_steps_first_and_flags_them():
    score = np.array([0.5, np.nan, 3.0, 1.0])
    flags = np.array([False, False, True, False])
    stale = np.array([True, True, False, False])
    s, f = with_stale(score, flags, stale)
    np.testing.assert_array_equal(s, [4.0, 4.0, 3.0, 1.0])
    np.testing.assert_array_equal(f, [True, True, True, False])


def lag_heart_rate(n, rng, jump_at=None):
    """A first-order lag towards 60 + 10 (MET - 1) bpm with 1 bpm noise, the MET switching every 50 steps."""
    met = np.repeat(rng.choice([1.0, 1.3, 3.5, 8.0], size=n // 50 + 1), 50)[:n]
    hr = np.empty(n)
    hr[0] = 60.0
    for t in range(1, n):
        hr[t] = hr[t - 1] + 0.3 * (60.0 + 10.0 * (met[t] - 1.0) - hr[t - 1]) + rng.normal()
    if jump_at is not None:
        hr[jump_at:] += 20.0  # a heart-rate jump the activity does not explain
    return hr, met


def test_heart_rate_zscore_is_the_causal_least_squares_residual():
    rng = np.random.default_rng(2)
    hr, met = lag_heart_rate(120, rng)
    include = np.ones(120, dtype=bool)
    include[[40, 41]] = False
    got = heart_rate_zscore(hr, met, include, warmup=10, ridge=0.5)
    inc = include.copy()
    inc[0] = False
    x = np.stack([np.ones(120), np.concatenate([[hr[0]], hr[:-1]]), met], axis=1)
    r = np.full(120, np.nan)
    for t in range(120):
        past = np.flatnonzero(inc[:t])
        w = np.linalg.solve(x[past].T @ x[past] + 0.5 * np.eye(3), x[past].T @ hr[past])
        r[t] = hr[t] - x[t] @ w
    for t in range(120):
        past = np.flatnonzero(inc[:t])
        if not inc[t] or past.size < 10:
            assert np.isnan(got[t]), t
        else:
            assert got[t] == pytest.approx(abs(r[t]) / np.sqrt((r[past] ** 2).mean())), t


def test_heart_rate_zscore_flags_a_jump_the_activity_does_not_explain():
    """Activity changes move the heart rate by tens of bpm and stay below the score's normal range; a 20 bpm jump
    at rest (20 sigmas of the 1 bpm noise; the running RMS also holds the first fits' residuals) is the largest
    score of the stream by a margin."""
    rng = np.random.default_rng(3)
    hr, met = lag_heart_rate(2000, rng, jump_at=1500)
    score = heart_rate_zscore(hr, met, np.ones(2000, dtype=bool))
    assert np.nanargmax(score) == 1500 and score[1500] > 8
    assert np.nanmax(np.delete(score[100:], 1400)) < 5.5
    with pytest.raises(ValueError, match="must all be"):
        heart_rate_zscore(hr, met[:-1], np.ones(2000, dtype=bool))
