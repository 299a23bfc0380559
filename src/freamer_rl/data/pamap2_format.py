"""PAMAP2 file-format constants, activity tables, the error type and the data containers.

Split out of :mod:`freamer_rl.data` (which re-exports every public name here) so that the parser, the
feature code and the synthetic generator share one column layout. Paper: Section 5, Appendix C.

Column layout (1-based, 54 columns): 1 timestamp (s), 2 activity id, 3 heart rate (bpm, ~9 Hz, ``NaN`` elsewhere),
4-20 IMU hand, 21-37 IMU chest, 38-54 IMU ankle; each IMU block is :data:`IMU_CHANNELS` (17 channels).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from freamer_rl.errors import FreamerError

#: every public name of the module (re-exported as a whole by :mod:`freamer_rl.data`)
__all__ = [
    "N_COLUMNS",
    "SAMPLE_RATE_HZ",
    "PROTOCOL_SUBJECTS",
    "IMU_SITES",
    "IMU_CHANNELS",
    "COLUMN_NAMES",
    "G",
    "IMU_FEATURE_NAMES",
    "ACTIVITY_NAMES",
    "MAX_ACTIVITY_ID",
    "ACTIVITY_GROUP_NAMES",
    "ACTIVITY_GROUP_OF",
    "ACTIVITY_MET",
    "HR_FEATURE_NAMES",
    "HR_ZONE_NAMES",
    "Pamap2FormatError",
    "Pamap2Recording",
    "HRFeatureParams",
    "Pamap2Features",
    "hr_zone",
    "activity_name",
    "group_table",
    "met_table",
    "valid_activity_ids",
]

# ----------------------------------------------------------------------------------------------------------------------
# format constants
# ----------------------------------------------------------------------------------------------------------------------
N_COLUMNS = 54
SAMPLE_RATE_HZ = 100.0
PROTOCOL_SUBJECTS: tuple[int, ...] = tuple(range(101, 110))
IMU_SITES: tuple[str, ...] = ("hand", "chest", "ankle")
IMU_CHANNELS: tuple[str, ...] = (
    "temperature",
    "acc16_x",
    "acc16_y",
    "acc16_z",
    "acc6_x",
    "acc6_y",
    "acc6_z",
    "gyro_x",
    "gyro_y",
    "gyro_z",
    "mag_x",
    "mag_y",
    "mag_z",
    "ori_w",
    "ori_x",
    "ori_y",
    "ori_z",
)
_SITE_FIRST_COLUMN = {"hand": 3, "chest": 20, "ankle": 37}  # 0-based column of each site's temperature
COLUMN_NAMES: tuple[str, ...] = ("timestamp", "activity_id", "heart_rate") + tuple(
    f"{site}_{ch}" for site in IMU_SITES for ch in IMU_CHANNELS
)
assert len(COLUMN_NAMES) == N_COLUMNS

#: Inside one site's 17 channels, the 12 used as features (file order, temperature and orientation dropped).
_IMU_FEATURE_CHANNELS = slice(1, 13)
G = 9.80665
_MAG_UNIT = 50.0
_IMU_SCALE = np.array([1 / G] * 6 + [1.0] * 3 + [1 / _MAG_UNIT] * 3, dtype=np.float64)
IMU_FEATURE_NAMES: tuple[str, ...] = tuple(f"{site}_{ch}" for site in IMU_SITES for ch in IMU_CHANNELS[1:13])

ACTIVITY_NAMES: dict[int, str] = {
    0: "transient",
    1: "lying",
    2: "sitting",
    3: "standing",
    4: "walking",
    5: "running",
    6: "cycling",
    7: "Nordic walking",
    9: "watching TV",
    10: "computer work",
    11: "car driving",
    12: "ascending stairs",
    13: "descending stairs",
    16: "vacuum cleaning",
    17: "ironing",
    18: "folding laundry",
    19: "house cleaning",
    20: "playing soccer",
    24: "rope jumping",
}
MAX_ACTIVITY_ID = 24

#: The 8 activity groups of the one-hot (paper Appendix C: "activity one-hot encoding (8 categories)").
ACTIVITY_GROUP_NAMES: tuple[str, ...] = (
    "rest",  # 0: lying, sitting, standing, watching TV, computer work, car driving
    "light_household",  # 1: vacuum cleaning, ironing, folding laundry, house cleaning
    "walking",  # 2: walking, Nordic walking
    "stairs",  # 3: ascending / descending stairs
    "running",  # 4: running
    "cycling",  # 5: cycling
    "sport",  # 6: playing soccer, rope jumping
    "transient_other",  # 7: activity 0 (transient periods between activities)
)
ACTIVITY_GROUP_OF: dict[int, int] = {
    1: 0,
    2: 0,
    3: 0,
    9: 0,
    10: 0,
    11: 0,
    16: 1,
    17: 1,
    18: 1,
    19: 1,
    4: 2,
    7: 2,
    12: 3,
    13: 3,
    5: 4,
    6: 5,
    20: 6,
    24: 6,
    0: 7,
}

#: Nominal metabolic equivalents (MET) per activity (rounded values in the range of the Compendium of Physical
#: Activities). Used for the intensity feature, the synthetic generator and the health env's heart-rate model.
ACTIVITY_MET: dict[int, float] = {
    0: 2.0,
    1: 1.0,
    2: 1.3,
    3: 1.8,
    4: 3.5,
    5: 8.0,
    6: 5.5,
    7: 5.0,
    9: 1.3,
    10: 1.5,
    11: 2.0,
    12: 8.0,
    13: 3.0,
    16: 3.5,
    17: 2.3,
    18: 2.0,
    19: 3.3,
    20: 7.0,
    24: 10.0,
}

# lookup tables indexed by activity id (0..24); invalid ids map to the transient group / MET
_VALID_ID = np.zeros(MAX_ACTIVITY_ID + 1, dtype=bool)
_GROUP_TABLE = np.full(MAX_ACTIVITY_ID + 1, 7, dtype=np.int64)
_MET_TABLE = np.full(MAX_ACTIVITY_ID + 1, ACTIVITY_MET[0], dtype=np.float64)
for _a, _g in ACTIVITY_GROUP_OF.items():
    _VALID_ID[_a] = True
    _GROUP_TABLE[_a] = _g
    _MET_TABLE[_a] = ACTIVITY_MET[_a]

HR_FEATURE_NAMES: tuple[str, ...] = (
    "hr",
    *(f"group_{name}" for name in ACTIVITY_GROUP_NAMES),
    "hr_zone",
    "exertion",
    "fatigue",
    "hrv",
    "hr_rate_of_change",
    "cumulative_exertion",
    "intensity",
)
assert len(HR_FEATURE_NAMES) == 16
HR_ZONE_NAMES: tuple[str, ...] = ("light", "moderate", "vigorous", "danger")


# ----------------------------------------------------------------------------------------------------------------------
# errors and containers
# ----------------------------------------------------------------------------------------------------------------------
class Pamap2FormatError(FreamerError, ValueError):
    """A PAMAP2 file or folder is missing or malformed.

    The message is one line: ``"<file>: line <n>[: column <c>]: <what is wrong>"`` (1-based line and column).
    ``path``, ``line`` and ``column`` are also available as attributes (``None`` when not applicable).
    """

    def __init__(
        self, message: str, *, path: str | Path | None = None, line: int | None = None, column: int | None = None
    ) -> None:
        super().__init__(message)
        self.path = None if path is None else str(path)
        self.line = line
        self.column = column


@dataclasses.dataclass
class Pamap2Recording:
    """One PAMAP2 session at the raw 100 Hz rate (``T`` rows).

    Attributes:
        timestamp: float64 ``[T]`` seconds.
        activity: int64 ``[T]`` activity ids (0 = transient).
        heart_rate: float64 ``[T]`` bpm, ``NaN`` where the ~9 Hz monitor has no sample.
        imu: ``{"hand", "chest", "ankle"}`` -> float64 ``[T, 17]`` in :data:`IMU_CHANNELS` order.
        subject: subject number (101-109) when known.
        source: file the recording was read from (``None`` for in-memory synthetic data).
        info: extra metadata; synthetic recordings store their ground-truth physiology here
            (``hr_rest``, ``hr_gain``, ``tau_hr``, ...).
    """

    timestamp: np.ndarray
    activity: np.ndarray
    heart_rate: np.ndarray
    imu: dict[str, np.ndarray]
    subject: int | None = None
    source: str | None = None
    info: dict = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.timestamp.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.timestamp[-1] - self.timestamp[0]) if len(self) else 0.0

    def to_array(self) -> np.ndarray:
        """The 54-column float64 ``[T, 54]`` matrix in file order."""
        out = np.empty((len(self), N_COLUMNS), dtype=np.float64)
        out[:, 0] = self.timestamp
        out[:, 1] = self.activity
        out[:, 2] = self.heart_rate
        for site in IMU_SITES:
            c = _SITE_FIRST_COLUMN[site]
            out[:, c : c + 17] = self.imu[site]
        return out


@dataclasses.dataclass(frozen=True)
class HRFeatureParams:
    """Constants of the 16 heart-rate features (shared with the health env, ``envs/health.py``).

    ``hr_rest=None``: use the recording's ground truth (synthetic ``info["hr_rest"]``) or else the 5th percentile
    of its measured heart rate, clipped to [40, 100] bpm.
    """

    hr_rest: float | None = None
    hr_max: float = 190.0
    zone_edges: tuple[float, float, float] = (110.0, 135.0, 160.0)  # light | moderate | vigorous | danger (> 160)
    tau_fatigue_up_s: float = 120.0
    tau_fatigue_down_s: float = 240.0
    tau_hrv_s: float = 30.0
    hr_scale: float = 200.0
    hrv_scale: float = 10.0
    hrv_max: float = 5.0
    roc_scale: float = 5.0
    roc_max: float = 3.0
    exertion_max: float = 1.5
    cum_scale_s: float = 600.0
    met_scale: float = 12.0


@dataclasses.dataclass
class Pamap2Features:
    """Per-step observation features of one recording at ``rate_hz`` (``N`` steps).

    Attributes:
        timestamp: float64 ``[N]`` time of the last sample of each window (s).
        activity: int64 ``[N]`` majority activity id of each window.
        group: int64 ``[N]`` activity group 0..7 (:data:`ACTIVITY_GROUP_NAMES`).
        heart_rate: float32 ``[N]`` forward-filled heart rate (bpm) at the end of each window.
        imu: float32 ``[N, 36]`` (:data:`IMU_FEATURE_NAMES`).
        hr_features: float32 ``[N, 16]`` (:data:`HR_FEATURE_NAMES`).
        met: float32 ``[N]`` nominal MET of each window's activity.
        rate_hz: effective step rate (100 / window length).
        hr_rest: resting heart rate used by the exertion feature (bpm).
        params: the :class:`HRFeatureParams` used.
        subject: subject number, when known.
    """

    timestamp: np.ndarray
    activity: np.ndarray
    group: np.ndarray
    heart_rate: np.ndarray
    imu: np.ndarray
    hr_features: np.ndarray
    met: np.ndarray
    rate_hz: float
    hr_rest: float
    params: HRFeatureParams
    subject: int | None = None

    def __len__(self) -> int:
        return int(self.timestamp.shape[0])


def hr_zone(hr: np.ndarray | float, edges: tuple[float, float, float] = (110.0, 135.0, 160.0)) -> np.ndarray:
    """Heart-rate zone 0 light (< 110), 1 moderate (< 135), 2 vigorous (<= 160), 3 danger (> 160 bpm)."""
    hr = np.asarray(hr, dtype=np.float64)
    return (hr >= edges[0]).astype(np.int64) + (hr >= edges[1]) + (hr > edges[2])


# ----------------------------------------------------------------------------------------------------------------------
# parsing


def activity_name(activity_id: int) -> str:
    """Human-readable name of a PAMAP2 activity id (``"unknown(<id>)"`` if not in :data:`ACTIVITY_NAMES`)."""
    return ACTIVITY_NAMES.get(int(activity_id), f"unknown({int(activity_id)})")


def group_table() -> np.ndarray:
    """int64 ``[25]``: activity id -> group index (invalid ids -> 7, ``transient_other``)."""
    return _GROUP_TABLE.copy()


def met_table() -> np.ndarray:
    """float64 ``[25]``: activity id -> nominal MET (invalid ids -> the transient MET 2.0)."""
    return _MET_TABLE.copy()


def valid_activity_ids() -> tuple[int, ...]:
    """The activity ids of :data:`ACTIVITY_NAMES`, ascending (0 = transient included)."""
    return tuple(sorted(ACTIVITY_NAMES))
