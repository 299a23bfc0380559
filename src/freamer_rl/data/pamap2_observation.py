"""PAMAP2 observation features (paper Appendix C): IMU ``[N, 36]`` and heart-rate features ``[N, 16]``.

Re-exported by :mod:`freamer_rl.data`. (The module is not called ``pamap2_features`` so that it does not
shadow the function :func:`pamap2_features` re-exported as ``freamer_rl.data.pamap2_features``.)
"""

from __future__ import annotations

import logging
import math
from typing import Literal

import numpy as np

from freamer_rl.data.pamap2_format import (
    _GROUP_TABLE,
    _IMU_FEATURE_CHANNELS,
    _IMU_SCALE,
    _MET_TABLE,
    IMU_SITES,
    MAX_ACTIVITY_ID,
    SAMPLE_RATE_HZ,
    HRFeatureParams,
    Pamap2Features,
    Pamap2Recording,
    hr_zone,
)

logger = logging.getLogger(__name__)

__all__ = ["hr_feature_sequence", "pamap2_features"]


def _ffill_rows(x: np.ndarray, name: str) -> np.ndarray:
    """Forward-fill rows containing a NaN (back-fill before the first complete row). ``x``: ``[T]`` or ``[T, C]``."""
    valid = ~np.isnan(x) if x.ndim == 1 else ~np.isnan(x).any(axis=1)
    if valid.all():
        return x
    if not valid.any():
        logger.warning("%s: no valid sample at all, using zeros", name)
        return np.zeros_like(x)
    idx = np.where(valid, np.arange(x.shape[0]), 0)
    np.maximum.accumulate(idx, out=idx)
    idx[: int(np.argmax(valid))] = int(np.argmax(valid))
    return x[idx]


def hr_feature_sequence(
    hr: np.ndarray, group: np.ndarray, met: np.ndarray, dt: float, hr_rest: float, p: HRFeatureParams
) -> np.ndarray:
    """The 16 heart-rate features of a heart-rate series (see the table of :func:`pamap2_features`).

    Args:
        hr: ``[N]`` heart rate (bpm, no NaN) at ``1 / dt`` Hz.
        group: int ``[N]`` activity group 0..7.
        met: ``[N]`` MET of the activity.
        dt: step (s).
        hr_rest: resting heart rate (bpm).
        p: the constants.

    Returns:
        float32 ``[N, 16]``. The recursive features (fatigue, HRV) start from ``F = 0`` and the first heart rate;
        the health env (``envs/health.py``) uses the same recursions in torch.
    """
    n = hr.shape[0]
    out = np.zeros((n, 16), dtype=np.float64)
    out[:, 0] = hr / p.hr_scale
    out[np.arange(n), 1 + group] = 1.0
    out[:, 9] = hr_zone(hr, p.zone_edges) / 3.0
    exertion = np.clip((hr - hr_rest) / (p.hr_max - hr_rest), 0.0, p.exertion_max)
    out[:, 10] = exertion
    a_up = 1.0 - math.exp(-dt / p.tau_fatigue_up_s)
    a_down = 1.0 - math.exp(-dt / p.tau_fatigue_down_s)
    b = 1.0 - math.exp(-dt / p.tau_hrv_s)
    fatigue = np.empty(n)
    hrv_std = np.empty(n)
    f = 0.0
    mean = float(hr[0]) if n else 0.0
    var = 0.0
    for t, (e, h) in enumerate(zip(exertion.tolist(), hr.tolist())):
        f += (a_up if e > f else a_down) * (e - f)
        fatigue[t] = f
        d = h - mean
        mean += b * d
        var = (1.0 - b) * (var + b * d * d)
        hrv_std[t] = math.sqrt(var)
    out[:, 11] = fatigue
    out[:, 12] = np.minimum(hrv_std / p.hrv_scale, p.hrv_max)
    roc = np.zeros(n)
    roc[1:] = np.diff(hr) / dt
    out[:, 13] = np.clip(roc / p.roc_scale, -p.roc_max, p.roc_max)
    out[:, 14] = np.cumsum(exertion) * dt / p.cum_scale_s
    out[:, 15] = met / p.met_scale
    return out.astype(np.float32)


def _estimate_hr_rest(rec: Pamap2Recording) -> float:
    if "hr_rest" in rec.info:
        return float(rec.info["hr_rest"])
    hr = rec.heart_rate[~np.isnan(rec.heart_rate)]
    if hr.size == 0:
        return 70.0
    return float(np.clip(np.percentile(hr, 5), 40.0, 100.0))


def pamap2_features(
    recording: Pamap2Recording,
    rate_hz: float = 1.0,
    *,
    imu_reduce: Literal["last", "mean"] = "last",
    params: HRFeatureParams | None = None,
    drop_transient: bool = False,
) -> Pamap2Features:
    """The paper's observation (Appendix C) at ``rate_hz`` steps per second (RL steps are not 10 ms).

    The 100 Hz rows are cut into windows of ``w = round(100 / rate_hz)`` rows (a trailing partial window is
    dropped). IMU samples with a NaN (dropped packets) and heart-rate gaps are forward-filled first.

    IMU ``[N, 36]``: per window the last sample (``imu_reduce="last"``, decimation: keeps the raw movement noise,
    so acceleration magnitudes still reflect intensity) or the window mean (``"mean"``); order and scaling in the
    module docstring (:data:`IMU_FEATURE_NAMES`).

    Heart-rate features ``[N, 16]`` (``HR`` = forward-filled heart rate at the window end, ``dt = 1 / rate_hz``,
    ``HR_rest`` see :class:`HRFeatureParams`, ``HR_max = 190``):

    ====  ======================  ===========================================================  ==================
    idx   name                    definition                                                   range
    ====  ======================  ===========================================================  ==================
    0     hr                      HR / 200                                                     ~[0.2, 1.1]
    1-8   group_*                 one-hot of the activity group (:data:`ACTIVITY_GROUP_NAMES`)  {0, 1}
    9     hr_zone                 zone / 3; light < 110 <= moderate < 135 <= vigorous <= 160   {0, 1/3, 2/3, 1}
                                  < danger (bpm)
    10    exertion                e = clip((HR - HR_rest) / (HR_max - HR_rest), 0, 1.5)        [0, 1.5]
    11    fatigue                 F += a (e - F), a = 1 - exp(-dt/tau), tau = 120 s if e > F   [0, 1.5]
                                  (accumulate) else 240 s (recover); F = 0 at the start
    12    hrv                     exponentially weighted std of HR (tau 30 s) / 10 bpm         [0, 5]
    13    hr_rate_of_change       (HR_t - HR_{t-1}) / dt / 5 bpm/s, clipped; 0 at the start    [-3, 3]
    14    cumulative_exertion     sum of e * dt / 600 s since the start                        [0, inf)
    15    intensity               nominal MET of the activity / 12 (:data:`ACTIVITY_MET`)      [0.08, 0.84]
    ====  ======================  ===========================================================  ==================

    Activity of a window = its majority id. Activity 0 (transient) is kept by default and encoded as the
    ``transient_other`` group (MET 2.0) so that the time series stays continuous; ``drop_transient=True`` removes
    those windows *after* all features are computed (the recursive features still see them).

    Raises:
        ValueError: ``rate_hz`` not positive or above the recording rate, unknown ``imu_reduce``, or fewer rows than
            one window.
    """
    p = params or HRFeatureParams()
    if imu_reduce not in ("last", "mean"):
        raise ValueError(f"imu_reduce: expected 'last' or 'mean', got {imu_reduce!r}")
    n_rows = len(recording)
    w, n, eff_rate = _windows(n_rows, rate_hz, _row_period(recording))
    ends = np.arange(1, n + 1) * w - 1
    name = recording.source or f"subject {recording.subject}"
    imu = _imu_features(recording, ends, n, w, imu_reduce, name)
    activity = _window_activity(recording.activity, n, w)
    group = _GROUP_TABLE[activity]
    met = _MET_TABLE[activity]

    hr_rest = float(p.hr_rest) if p.hr_rest is not None else _estimate_hr_rest(recording)
    hr = _window_heart_rate(recording, ends, hr_rest, name)
    hr_feat = hr_feature_sequence(hr, group, met, 1.0 / eff_rate, hr_rest, p)

    keep = slice(None) if not drop_transient else activity != 0
    return Pamap2Features(
        timestamp=recording.timestamp[ends][keep],
        activity=activity[keep],
        group=group[keep],
        heart_rate=hr.astype(np.float32)[keep],
        imu=imu[keep],
        hr_features=hr_feat[keep],
        met=met.astype(np.float32)[keep],
        rate_hz=eff_rate,
        hr_rest=hr_rest,
        params=p,
        subject=recording.subject,
    )


def _row_period(recording: Pamap2Recording) -> float:
    """Row spacing (s): the median timestamp step of the first 10,000 rows (1 / 100 Hz when undefined)."""
    n_rows = len(recording)
    if n_rows >= 2:
        dt_row = float(np.median(np.diff(recording.timestamp[: min(n_rows, 10001)])))
        if not dt_row > 0:
            dt_row = 1.0 / SAMPLE_RATE_HZ
    else:
        dt_row = 1.0 / SAMPLE_RATE_HZ
    return dt_row


def _windows(n_rows: int, rate_hz: float, dt_row: float) -> tuple[int, int, float]:
    """``(w, n, eff_rate)``: rows per window, number of whole windows and the effective step rate (Hz)."""
    if not (rate_hz > 0) or rate_hz > 1.0 / dt_row * 1.0001:
        raise ValueError(f"rate_hz: expected a rate in (0, {1.0 / dt_row:g}] Hz, got {rate_hz!r}")
    w = max(1, int(round(1.0 / (rate_hz * dt_row))))
    n = n_rows // w
    if n < 1:
        raise ValueError(f"recording has {n_rows} rows, fewer than one window of {w} rows at rate_hz={rate_hz}")
    eff_rate = 1.0 / (w * dt_row)
    if abs(eff_rate - rate_hz) > 1e-6 * rate_hz:
        logger.info("rate_hz=%g is not a divisor of the %g Hz row rate; using %g Hz", rate_hz, 1 / dt_row, eff_rate)
    return w, n, eff_rate


def _imu_features(
    recording: Pamap2Recording, ends: np.ndarray, n: int, w: int, imu_reduce: str, name: str
) -> np.ndarray:
    """float32 ``[n, 36]``: per site the 12 feature channels, forward-filled, reduced per window and scaled."""
    sites = []
    for site in IMU_SITES:
        x = _ffill_rows(np.asarray(recording.imu[site][:, _IMU_FEATURE_CHANNELS], dtype=np.float64), f"{name} {site}")
        x = x[ends] if imu_reduce == "last" else x[: n * w].reshape(n, w, 12).mean(axis=1)
        sites.append(x * _IMU_SCALE)
    return np.concatenate(sites, axis=1).astype(np.float32)


def _window_activity(activity: np.ndarray, n: int, w: int) -> np.ndarray:
    """int64 ``[n]``: the majority activity id of each window (ties -> the smaller id)."""
    act = activity[: n * w].astype(np.int64)
    # one bincount over (window, id) pairs instead of a Python loop over windows
    counts = np.bincount(np.repeat(np.arange(n), w) * (MAX_ACTIVITY_ID + 1) + act, minlength=n * (MAX_ACTIVITY_ID + 1))
    return counts.reshape(n, MAX_ACTIVITY_ID + 1).argmax(axis=1).astype(np.int64)


def _window_heart_rate(recording: Pamap2Recording, ends: np.ndarray, hr_rest: float, name: str) -> np.ndarray:
    """float64 ``[n]``: the forward-filled heart rate at each window end (``hr_rest`` if there is no sample)."""
    hr_ff = recording.heart_rate
    if np.isnan(hr_ff).all():
        logger.warning("%s: no heart-rate sample at all, using a constant %.0f bpm", name, hr_rest)
        hr_ff = np.full(len(recording), hr_rest)
    else:
        hr_ff = _ffill_rows(hr_ff, f"{name} heart rate")
    return hr_ff[ends].astype(np.float64)
