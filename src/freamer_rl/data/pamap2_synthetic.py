"""Format-faithful synthetic PAMAP2 subjects (the dataset cannot be downloaded here; paper Section 5).

:func:`synthetic_recording` builds one 100 Hz protocol session in memory; :func:`write_synthetic_pamap2` writes
``Protocol/subjectNNN.dat`` files in exactly the PAMAP2 text format. Re-exported by :mod:`freamer_rl.data`.

The generator is seeded: the helpers below draw from one ``numpy.random.Generator`` in a fixed order, so the
same ``(seed, subject)`` always gives the same recording (``tests/test_pamap2_synthetic.py`` pins the values).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from freamer_rl.data.pamap2_format import (
    _MET_TABLE,
    ACTIVITY_NAMES,
    IMU_SITES,
    MAX_ACTIVITY_ID,
    N_COLUMNS,
    PROTOCOL_SUBJECTS,
    SAMPLE_RATE_HZ,
    G,
    HRFeatureParams,
    Pamap2Recording,
)

__all__ = ["synthetic_recording", "write_recording", "write_synthetic_pamap2"]

_PROTOCOL_TIMELINE: tuple[tuple[int, float], ...] = (
    (1, 180),
    (2, 180),
    (3, 180),
    (17, 180),
    (16, 180),
    (12, 60),
    (13, 60),
    (12, 60),
    (13, 60),
    (4, 180),
    (7, 180),
    (6, 180),
    (5, 180),
    (24, 120),
)
_TRANSIENT_S = 40.0
_MIN_SEGMENT_S = 15.0
_MIN_TRANSIENT_S = 4.0

# movement model per activity: step frequency (Hz), acceleration amplitude (m/s^2) and gyro amplitude (rad/s)
# for (hand, chest, ankle), heading change rate (rad/sqrt(s)), posture
_MOVE: dict[int, tuple[float, tuple[float, float, float], tuple[float, float, float], float, str]] = {
    0: (1.5, (2.0, 1.0, 3.0), (0.6, 0.2, 1.0), 0.40, "upright"),
    1: (0.25, (0.05, 0.03, 0.03), (0.02, 0.01, 0.01), 0.01, "lying"),
    2: (0.3, (0.15, 0.05, 0.05), (0.05, 0.02, 0.02), 0.02, "sitting"),
    3: (0.3, (0.2, 0.08, 0.05), (0.08, 0.03, 0.02), 0.03, "upright"),
    4: (1.8, (3.5, 2.0, 6.0), (1.0, 0.3, 2.5), 0.25, "upright"),
    5: (2.7, (9.0, 8.0, 18.0), (3.0, 0.8, 5.0), 0.30, "upright"),
    6: (1.2, (1.0, 1.5, 4.0), (0.2, 0.3, 2.5), 0.15, "cycling"),
    7: (1.7, (6.0, 2.5, 6.5), (2.0, 0.4, 2.8), 0.25, "upright"),
    9: (0.3, (0.15, 0.05, 0.05), (0.05, 0.02, 0.02), 0.01, "sitting"),
    10: (0.5, (0.3, 0.05, 0.05), (0.1, 0.02, 0.02), 0.01, "sitting"),
    11: (0.5, (0.3, 0.3, 0.2), (0.1, 0.05, 0.05), 0.10, "sitting"),
    12: (1.6, (3.5, 2.5, 6.5), (1.0, 0.4, 2.5), 0.30, "upright"),
    13: (1.9, (4.0, 3.0, 8.0), (1.1, 0.4, 2.8), 0.30, "upright"),
    16: (0.7, (2.0, 0.8, 0.8), (0.8, 0.3, 0.4), 0.30, "upright"),
    17: (0.8, (1.5, 0.3, 0.1), (0.6, 0.1, 0.05), 0.05, "upright"),
    18: (0.6, (1.2, 0.3, 0.1), (0.5, 0.1, 0.05), 0.05, "upright"),
    19: (0.8, (2.5, 0.8, 0.8), (1.0, 0.3, 0.4), 0.30, "upright"),
    20: (2.4, (8.0, 7.0, 15.0), (2.5, 0.8, 4.5), 0.60, "upright"),
    24: (2.2, (12.0, 12.0, 22.0), (3.5, 1.0, 5.0), 0.10, "upright"),
}
# gravity direction per posture and site (hand, chest, ankle), roughly as seen in PAMAP2 sensor frames
_POSTURE: dict[str, tuple[tuple[float, float, float], ...]] = {
    "upright": ((0.25, 0.90, 0.35), (0.02, 0.99, -0.17), (0.98, -0.17, -0.01)),
    "sitting": ((0.60, 0.20, 0.77), (0.05, 0.97, -0.25), (0.70, -0.20, 0.68)),
    "lying": ((0.10, 0.10, 0.99), (0.05, -0.10, 0.99), (0.10, 0.05, 0.99)),
    "cycling": ((0.90, 0.10, 0.40), (0.30, 0.90, -0.30), (0.85, -0.30, 0.40)),
}
_SITE_TEMP_C = (32.0, 34.0, 31.0)
_EARTH_FIELD_UT = (22.0, -42.0)  # horizontal magnitude, vertical component
_FORMAT = "%.2f " + " ".join(["%.6g"] * (N_COLUMNS - 1))


def _synthetic_timeline(duration_s: float, rng: np.random.Generator) -> list[tuple[int, float]]:
    nominal = sum(d for _, d in _PROTOCOL_TIMELINE) + _TRANSIENT_S * (len(_PROTOCOL_TIMELINE) + 1)
    scale = min(1.0, duration_s / nominal)
    segs: list[tuple[int, float]] = []
    total = 0.0
    i = 0
    while total < duration_s:
        gap = max(_MIN_TRANSIENT_S, _TRANSIENT_S * scale * rng.uniform(0.5, 1.5))
        a, d = _PROTOCOL_TIMELINE[i % len(_PROTOCOL_TIMELINE)]
        seg = max(_MIN_SEGMENT_S, d * scale * rng.uniform(0.85, 1.15))
        segs += [(0, gap), (a, seg)]
        total += gap + seg
        i += 1
    return segs


def synthetic_recording(
    subject: int = 101,
    *,
    duration_s: float = 600.0,
    seed: int = 0,
    activities: Iterable[tuple[int, float]] | None = None,
    row_rate_hz: float = SAMPLE_RATE_HZ,
) -> Pamap2Recording:
    """A synthetic PAMAP2 protocol session at 100 Hz, in memory (what :func:`write_synthetic_pamap2` writes).

    ``row_rate_hz`` (default 100 Hz, the pinned numbers) gives fewer rows per second for long scenarios (48 h: 17.3 M
    rows, ~8 GB of text at 100 Hz; 172,800 at 1 Hz); it must divide 100. The same models are sampled at the row
    times (heart rate on every row below ~9 Hz, lag integrated at ~10 Hz or the row rate); the feature code reads
    the row period from the timestamps, so any step rate up to ``row_rate_hz`` works.

    Statistics:

    - activity timeline: the protocol order (lying, sitting, standing, ironing, vacuum cleaning, stairs up/down x2,
      walking, Nordic walking, cycling, running, rope jumping), durations scaled to ``duration_s`` (>= 15 s per
      activity), separated by transient (id 0) gaps, repeated if ``duration_s`` exceeds one protocol
      (``activities`` = explicit ``[(id, seconds), ...]`` overrides it);
    - per subject (drawn from ``seed`` and ``subject``): resting HR 58-78 bpm, gain 9.5-13 bpm per MET, heart-rate
      time constant ``tau_hr`` 12-25 s, fatigue drift 12 bpm per unit of fatigue;
    - heart rate: first-order lag ``dHR/dt = (HR_ss - HR) / tau_hr`` towards
      ``HR_ss = HR_rest + gain (MET - 1) + drift * fatigue`` (fatigue as the ``fatigue`` feature), plus respiratory
      sinus arrhythmia and noise, rounded to integer bpm, present on ~9 of 100 rows (gaps of 10-12 rows);
    - IMUs: gravity (9.81 m/s^2) in a posture-dependent direction per site, periodic movement at the activity's step
      frequency with per-site amplitudes (largest at the ankle, for running / rope jumping / soccer), noise; acc
      +-16 g and +-6 g copies (the latter saturating); gyro in rad/s; magnetometer = Earth field (~47 uT) rotated by
      the heading; temperature 30-35 C in 1/16 C steps, warming with fatigue; orientation columns ``1 0 0 0``.

    The ground truth physiology is stored in ``info`` (``hr_rest``, ``hr_gain``, ``tau_hr``, ``fatigue_drift``).
    """
    if not duration_s > 1.0:
        raise ValueError(f"duration_s: expected more than 1 s, got {duration_s!r}")
    rate = _check_row_rate(row_rate_hz)
    # every random draw below comes from this one generator, in a fixed order (the output is pinned by tests)
    rng = np.random.default_rng([int(seed), int(subject)])
    hr_rest = float(rng.uniform(58.0, 78.0))
    gain = float(rng.uniform(9.5, 13.0))
    tau_hr = float(rng.uniform(12.0, 25.0))
    drift = 12.0
    amp_scale = rng.uniform(0.85, 1.15, size=3)

    if activities is None:
        segs = _synthetic_timeline(float(duration_s), rng)
    else:
        segs = [(int(a), float(d)) for a, d in activities]
        bad = [a for a, _ in segs if a not in ACTIVITY_NAMES]
        if bad:
            raise ValueError(f"activities: unknown activity ids {bad} (valid: {sorted(ACTIVITY_NAMES)})")
    t_rows = int(round(duration_s * rate))
    activity, seg_jitter = _activity_rows(segs, t_rows, rng, rate)
    heart_rate, fatigue = _synthetic_heart_rate(activity, seg_jitter, (hr_rest, gain, tau_hr, drift), rng, rate)
    imu = _synthetic_imus(activity, seg_jitter, amp_scale, fatigue, rng, rate)

    dt = 1.0 / rate
    t_start = float(np.round(rng.uniform(5.0, 10.0), 2))
    timestamp = np.round(t_start + np.arange(t_rows) * dt, 2)
    info = {
        "synthetic": True,
        "seed": int(seed),
        "hr_rest": hr_rest,
        "hr_gain": gain,
        "tau_hr": tau_hr,
        "fatigue_drift": drift,
        "segments": segs,
        "row_rate_hz": rate,
    }
    return Pamap2Recording(
        timestamp=timestamp,
        activity=activity,
        heart_rate=heart_rate,
        imu=imu,
        subject=int(subject),
        source=None,
        info=info,
    )


def _check_row_rate(row_rate_hz: float) -> float:
    """``row_rate_hz`` as a float, checked: in (0, 100] Hz and dividing 100 (rows on the 10 ms grid)."""
    rate = float(row_rate_hz)
    per = SAMPLE_RATE_HZ / rate if rate > 0 else math.inf
    if not (0 < rate <= SAMPLE_RATE_HZ) or abs(per - round(per)) > 1e-9:
        raise ValueError(f"row_rate_hz: expected a rate in (0, 100] Hz that divides 100, got {row_rate_hz!r}")
    return rate


def _activity_rows(
    segs: list[tuple[int, float]], t_rows: int, rng: np.random.Generator, rate: float = SAMPLE_RATE_HZ
) -> tuple[np.ndarray, np.ndarray]:
    """Per-row activity id int64 ``[T]`` and per-segment effort jitter float64 ``[T]`` (one draw per segment)."""
    bounds = np.round(np.cumsum([d for _, d in segs]) * rate).astype(np.int64)
    # rows past the last segment's end (rounding) stay in the last segment
    seg_of_row = np.minimum(np.searchsorted(bounds, np.arange(t_rows), side="right"), len(segs) - 1)
    activity = np.array([a for a, _ in segs], dtype=np.int64)[seg_of_row]
    n_seg = len(segs)
    seg_jitter = rng.uniform(0.85, 1.15, size=n_seg)[seg_of_row]  # per-segment effort
    return activity, seg_jitter


def _synthetic_heart_rate(
    activity: np.ndarray,
    seg_jitter: np.ndarray,
    physiology: tuple[float, float, float, float],
    rng: np.random.Generator,
    rate: float = SAMPLE_RATE_HZ,
) -> tuple[np.ndarray, np.ndarray]:
    """Measured heart rate ``[T]`` (integer bpm on ~9 rows in 100, NaN elsewhere) and the true fatigue ``[T]``.

    ``physiology`` = ``(hr_rest, gain, tau_hr, drift)``. The lag model is integrated at ~10 Hz (a Python loop: 10x
    fewer steps than at 100 Hz; at the row rate below 10 Hz) and interpolated to the row rate.
    """
    hr_rest, gain, tau_hr, drift = physiology
    t_rows = activity.shape[0]
    dt = 1.0 / rate
    sub = max(1, int(round(rate / 10.0)))
    met = _MET_TABLE[activity] * np.where(activity == 0, 1.0, seg_jitter)
    hr10, fat10 = _integrate_hr(met[::sub], dt * sub, physiology, rng)
    hr_max = HRFeatureParams().hr_max
    t = np.arange(t_rows) * dt
    hr_true = np.interp(t, t[::sub], hr10)
    fatigue = np.interp(t, t[::sub], fat10)
    exert = np.clip((hr_true - hr_rest) / (hr_max - hr_rest), 0.0, 1.0)
    # respiratory sinus arrhythmia: strongest at rest, fading with exertion
    rsa = 2.5 * (1.0 - exert) * np.sin(2 * np.pi * 0.25 * t + rng.uniform(0, 2 * np.pi))
    hr_meas = np.round(hr_true + rsa + rng.normal(0.0, 1.0, size=t_rows))
    # ~9 Hz monitor: gaps of 10-12 rows at 100 Hz, scaled to the row rate (every row below ~9 Hz)
    gap_choices = np.maximum(1, np.round(np.array([10, 11, 11, 11, 12]) * rate / SAMPLE_RATE_HZ)).astype(np.int64)
    gaps = rng.choice(gap_choices, size=t_rows // int(gap_choices.min()) + 2)
    hr_rows = np.cumsum(gaps) - gaps[0]
    hr_rows = hr_rows[hr_rows < t_rows]
    heart_rate = np.full(t_rows, np.nan)
    heart_rate[hr_rows] = np.clip(hr_meas[hr_rows], 35.0, 230.0)
    return heart_rate, fatigue


def _integrate_hr(
    met10: np.ndarray, dt10: float, physiology: tuple[float, float, float, float], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """True heart rate and fatigue at 10 Hz: ``dHR/dt = (HR_ss - HR) / tau_hr``, fatigue as the ``fatigue`` feature."""
    hr_rest, gain, tau_hr, drift = physiology
    hr_max = HRFeatureParams().hr_max
    a_hr = 1.0 - math.exp(-dt10 / tau_hr)
    a_up = 1.0 - math.exp(-dt10 / HRFeatureParams().tau_fatigue_up_s)
    a_down = 1.0 - math.exp(-dt10 / HRFeatureParams().tau_fatigue_down_s)
    eps = rng.normal(0.0, 1.0, size=met10.shape[0]).tolist()
    hr_true = np.empty(met10.shape[0])
    fat = np.empty(met10.shape[0])
    h = hr_rest + gain * (met10[0] - 1.0)
    f = 0.0
    for k, (m, z) in enumerate(zip(met10.tolist(), eps)):
        h_ss = hr_rest + gain * (m - 1.0) + drift * f
        h += a_hr * (h_ss - h) + 0.3 * z
        e = min(max((h - hr_rest) / (hr_max - hr_rest), 0.0), 1.5)
        f += (a_up if e > f else a_down) * (e - f)
        hr_true[k] = h
        fat[k] = f
    return hr_true, fat


def _movement_rows(activity: np.ndarray, seg_jitter: np.ndarray, amp_scale: np.ndarray) -> dict[str, np.ndarray]:
    """Per-row movement parameters from :data:`_MOVE` / :data:`_POSTURE` (no random draws).

    Returns ``freq`` ``[T]``, ``acc_amp`` / ``gyro_amp`` ``[T, 3]`` (per site), ``turn`` ``[T]``, ``post_k`` ``[T]``
    (posture index) and ``gdir`` ``[P, 3, 3]`` (unit gravity direction per posture and site).
    """
    ids = sorted(_MOVE)
    lut = np.zeros(MAX_ACTIVITY_ID + 1, dtype=np.int64)
    lut[ids] = np.arange(len(ids))
    k_of_row = lut[activity]
    postures = sorted(_POSTURE)
    return {
        "freq": np.array([_MOVE[a][0] for a in ids])[k_of_row],
        "acc_amp": np.array([_MOVE[a][1] for a in ids])[k_of_row] * amp_scale * seg_jitter[:, None],
        "gyro_amp": np.array([_MOVE[a][2] for a in ids])[k_of_row] * amp_scale * seg_jitter[:, None],
        "turn": np.array([_MOVE[a][3] for a in ids])[k_of_row],
        "post_k": np.array([postures.index(_MOVE[a][4]) for a in ids])[k_of_row],
        "gdir": np.array([[np.asarray(v) / np.linalg.norm(v) for v in _POSTURE[name]] for name in postures]),
    }


def _synthetic_imus(
    activity: np.ndarray,
    seg_jitter: np.ndarray,
    amp_scale: np.ndarray,
    fatigue: np.ndarray,
    rng: np.random.Generator,
    rate: float = SAMPLE_RATE_HZ,
) -> dict[str, np.ndarray]:
    """``{"hand", "chest", "ankle"}`` -> float64 ``[T, 17]`` in :data:`IMU_CHANNELS` order."""
    t_rows = activity.shape[0]
    dt = 1.0 / rate
    mv = _movement_rows(activity, seg_jitter, amp_scale)
    phase = 2 * np.pi * np.cumsum(mv["freq"]) * dt + rng.uniform(0, 2 * np.pi)
    heading = np.cumsum(mv["turn"] * math.sqrt(dt) * rng.normal(size=t_rows)) + rng.uniform(0, 2 * np.pi)
    per_s = max(1, int(round(rate)))  # the temperature drifts once a second
    temp_drift = np.cumsum(rng.normal(0, 0.002, size=t_rows // per_s + 1)).repeat(per_s)[:t_rows]
    imu: dict[str, np.ndarray] = {}
    for s, site in enumerate(IMU_SITES):
        g = mv["gdir"][mv["post_k"], s] * G  # [T, 3]
        imu[site] = _site_channels(
            s, g, mv["acc_amp"][:, s : s + 1], mv["gyro_amp"][:, s : s + 1], phase, heading, fatigue, temp_drift, rng
        )
    return imu


def _site_channels(
    s: int,
    g: np.ndarray,
    acc_amp: np.ndarray,
    gyro_amp: np.ndarray,
    phase: np.ndarray,
    heading: np.ndarray,
    fatigue: np.ndarray,
    temp_drift: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """One site's 17 channels ``[T, 17]``: temperature, acc16, acc6, gyro, magnetometer, orientation ``1 0 0 0``."""
    t_rows = phase.shape[0]
    c1, c2, c3, c4 = rng.uniform(0, 2 * np.pi, size=4)
    wave = np.stack([np.sin(phase + s), 0.6 * np.sin(2 * phase + c1), 0.4 * np.sin(phase + c2)], axis=1)  # [T, 3]
    move = acc_amp * wave + 0.25 * acc_amp * rng.normal(size=(t_rows, 3))
    acc_true = g + move
    acc16 = np.clip(acc_true + rng.normal(0.0, 0.05, size=(t_rows, 3)), -16 * G, 16 * G)
    # the +-6 g sensor: slight gain / offset error and saturation
    acc6 = np.clip(acc_true * 1.01 + 0.05 + rng.normal(0.0, 0.03, size=(t_rows, 3)), -6 * G, 6 * G)
    gwave = np.stack([np.sin(phase + c3), np.cos(phase + c3), 0.5 * np.sin(2 * phase + c4)], axis=1)
    gyro = gyro_amp * gwave + rng.normal(0.0, 0.015, size=(t_rows, 3))
    hdg = heading + 0.15 * np.sin(phase + s)
    mag = np.stack(
        [_EARTH_FIELD_UT[0] * np.cos(hdg), _EARTH_FIELD_UT[0] * np.sin(hdg), np.full(t_rows, _EARTH_FIELD_UT[1])],
        axis=1,
    ) + rng.normal(0.0, 0.6, size=(t_rows, 3))
    temp = _SITE_TEMP_C[s] + rng.uniform(-1.0, 1.0) + 1.0 * fatigue + temp_drift
    temp = np.round(np.clip(temp, 28.0, 37.0) * 16.0) / 16.0  # the sensors report 1/16 C steps
    ori = np.zeros((t_rows, 4))
    ori[:, 0] = 1.0
    return np.concatenate([temp[:, None], acc16, acc6, gyro, mag, ori], axis=1)


def _format_rows(arr: np.ndarray) -> str:
    fmt = _FORMAT
    text = "\n".join([fmt % tuple(row) for row in arr.tolist()])
    return text.replace("nan", "NaN") + "\n"


def write_recording(recording: Pamap2Recording, path: str | Path) -> Path:
    """Write one recording as a PAMAP2 ``.dat`` file (the format of :func:`write_synthetic_pamap2`); returns the path.

    Written in blocks of 100,000 rows, so a long scenario never holds its whole text in memory.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = recording.to_array()
    with open(path, "w", encoding="ascii") as f:
        for i in range(0, arr.shape[0], 100_000):
            f.write(_format_rows(arr[i : i + 100_000]))
    return path


def write_synthetic_pamap2(
    folder: str | Path,
    subjects: Iterable[int] = (101, 102, 103),
    duration_s: float = 600.0,
    seed: int = 0,
    row_rate_hz: float = SAMPLE_RATE_HZ,
) -> Path:
    """Write ``<folder>/Protocol/subjectNNN.dat`` files of :func:`synthetic_recording` in the PAMAP2 format.

    54 space-separated columns; timestamps with 2 decimals (10 ms steps); activity and heart rate as integers,
    ``NaN`` where the heart-rate monitor has no sample (~91 % of rows); IMU values with 6 significant digits.
    ``row_rate_hz``: see :func:`synthetic_recording` (fewer rows per second for long scenarios).

    Returns:
        the ``Protocol`` folder.
    """
    subjects = [int(s) for s in subjects]
    wrong = [s for s in subjects if s not in PROTOCOL_SUBJECTS]
    if wrong or not subjects:
        raise ValueError(f"subjects: expected numbers in 101..109, got {subjects!r}")
    pdir = Path(folder) / "Protocol"
    pdir.mkdir(parents=True, exist_ok=True)
    for s in subjects:
        rec = synthetic_recording(s, duration_s=duration_s, seed=seed, row_rate_hz=row_rate_hz)
        write_recording(rec, pdir / f"subject{s}.dat")
    return pdir
