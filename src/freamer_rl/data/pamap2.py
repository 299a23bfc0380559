"""PAMAP2 wearable-sensor data: loader, observation features and a format-faithful synthetic generator.

Paper: Section 5 and Appendix C (observation = IMU 36 dims + heart-rate features 16 dims), Appendix J.

File format (``Protocol/subjectNNN.dat``, subjects 101-109)
------------------------------------------------------------
Space-separated text, one row per 10 ms (IMUs at 100 Hz), 54 columns, missing values written ``NaN``:

=========  ==========================================================================================
column     content
=========  ==========================================================================================
1          timestamp (s)
2          activity id (0 = transient, see :data:`ACTIVITY_NAMES`)
3          heart rate (bpm), ~9 Hz: a value on about 9 rows in 100, ``NaN`` elsewhere
4-20       IMU hand  (17 channels, :data:`IMU_CHANNELS`)
21-37      IMU chest
38-54      IMU ankle
=========  ==========================================================================================

Each IMU block: temperature (C), acc +-16 g x/y/z (m/s^2), acc +-6 g x/y/z (m/s^2), gyro x/y/z (rad/s),
magnetometer x/y/z (uT), orientation w/x/y/z (documented as invalid in this collection).

Public API
----------
- :func:`load_pamap2_subject` / :func:`load_pamap2_protocol`: parse files into :class:`Pamap2Recording`
  (numpy's C text reader over the whole file, a row-count check and vectorised value checks; only when that fails
  does a slower pass locate the problem: a per-line token count on the raw bytes, then a block-wise search for the
  first unparseable field). A malformed file raises :class:`Pamap2FormatError` with one line naming the file, the
  1-based line and, where relevant, the 1-based column.
- :func:`pamap2_features`: the paper's observation at a chosen step rate (default 1 Hz) ->
  :class:`Pamap2Features` with ``imu`` ``[N, 36]`` and ``hr_features`` ``[N, 16]``.
- :func:`synthetic_recording` / :func:`write_synthetic_pamap2`: synthetic subjects with plausible statistics,
  written in exactly the file format above (the dataset cannot be downloaded here; the synthetic data is the
  embedded default and the test data; the real dataset is read when a folder is given).

IMU features (36 = 3 sites x 12), order ``hand, chest, ankle``; inside a site the file order without temperature
and orientation: ``acc16 x,y,z | acc6 x,y,z | gyro x,y,z | mag x,y,z``. Scaling: accelerations in g
(m/s^2 / 9.80665; typically [-3, 3], saturating at +-16 / +-6), gyro in rad/s (typically [-10, 10]),
magnetometer in units of 50 uT (typically [-2, 2]). See :data:`IMU_FEATURE_NAMES`.

Heart-rate features (16), see :data:`HR_FEATURE_NAMES` and :func:`pamap2_features` for the table.
"""

from __future__ import annotations

import dataclasses
import io
import logging
import math
import re
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Literal

import numpy as np

from freamer_rl.errors import FreamerError

logger = logging.getLogger(__name__)

__all__ = [
    "ACTIVITY_GROUP_NAMES",
    "ACTIVITY_GROUP_OF",
    "ACTIVITY_MET",
    "ACTIVITY_NAMES",
    "HR_FEATURE_NAMES",
    "IMU_CHANNELS",
    "IMU_FEATURE_NAMES",
    "IMU_SITES",
    "N_COLUMNS",
    "PROTOCOL_SUBJECTS",
    "HRFeatureParams",
    "Pamap2Features",
    "Pamap2FormatError",
    "Pamap2Recording",
    "hr_feature_sequence",
    "hr_zone",
    "load_pamap2_protocol",
    "load_pamap2_subject",
    "pamap2_features",
    "synthetic_recording",
    "write_synthetic_pamap2",
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
    "acc16_x", "acc16_y", "acc16_z",
    "acc6_x", "acc6_y", "acc6_z",
    "gyro_x", "gyro_y", "gyro_z",
    "mag_x", "mag_y", "mag_z",
    "ori_w", "ori_x", "ori_y", "ori_z",
)  # fmt: skip
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
    1: 0, 2: 0, 3: 0, 9: 0, 10: 0, 11: 0,
    16: 1, 17: 1, 18: 1, 19: 1,
    4: 2, 7: 2,
    12: 3, 13: 3,
    5: 4,
    6: 5,
    20: 6, 24: 6,
    0: 7,
}  # fmt: skip

#: Nominal metabolic equivalents (MET) per activity (rounded values in the range of the Compendium of Physical
#: Activities). Used for the intensity feature, the synthetic generator and the health env's heart-rate model.
ACTIVITY_MET: dict[int, float] = {
    0: 2.0, 1: 1.0, 2: 1.3, 3: 1.8, 4: 3.5, 5: 8.0, 6: 5.5, 7: 5.0, 9: 1.3, 10: 1.5, 11: 2.0,
    12: 8.0, 13: 3.0, 16: 3.5, 17: 2.3, 18: 2.0, 19: 3.3, 20: 7.0, 24: 10.0,
}  # fmt: skip

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

    def __init__(self, message: str, *, path: str | Path | None = None, line: int | None = None,
                 column: int | None = None) -> None:  # fmt: skip
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
# ----------------------------------------------------------------------------------------------------------------------
_EXPECTED = f"{N_COLUMNS} space-separated numeric columns"


def _tokens_per_line(body: bytes) -> np.ndarray:
    """Number of whitespace-separated tokens on each line of ``body`` (no trailing newline), int64 ``[lines]``."""
    buf = np.frombuffer(body, dtype=np.uint8)
    ws = buf == 32
    ws |= (buf >= 9) & (buf <= 13)
    start = np.empty(buf.shape[0], dtype=bool)
    start[0] = not ws[0]
    np.greater(ws[:-1], ws[1:], out=start[1:])  # whitespace followed by non-whitespace
    del ws
    line_starts = np.concatenate(([0], np.flatnonzero(buf == 10) + 1))
    return np.add.reduceat(start, line_starts, dtype=np.int64)


def _parses(chunk: bytes, n_values: int) -> bool:
    """Whether the fast reader accepts ``chunk`` as exactly ``n_values`` numbers (same reader as the fast path)."""
    try:
        arr = np.loadtxt(io.StringIO(chunk.decode("latin-1")), dtype=np.float64, comments=None, ndmin=2)
    except ValueError:
        return False
    return arr.size == n_values


_LOADTXT_POS = re.compile(r"at row (\d+), column (\d+)")


def _raise_unparseable(path: Path, body: bytes, reason: str = "") -> None:
    """Find the first token the reader rejects and raise with its line and column.

    numpy's reader stops at the first bad field and names its 0-based row (= line here: blank lines were rejected
    before); the scan starts there and falls back to the whole file if that hint finds nothing.
    """
    lines = body.split(b"\n")
    m = _LOADTXT_POS.search(reason)
    starts = [0]
    if m is not None and 0 < int(m.group(1)) < len(lines):
        starts.insert(0, int(m.group(1)))
    for start in starts:
        _scan_unparseable(path, lines, start)


def _scan_unparseable(path: Path, lines: list[bytes], start: int) -> None:
    block = 2048
    for b0 in range(start, len(lines), block):
        chunk = lines[b0 : b0 + block]
        if _parses(b"\n".join(chunk), N_COLUMNS * len(chunk)):
            continue
        for i, line in enumerate(chunk, start=b0 + 1):
            if _parses(line, N_COLUMNS):
                continue
            for j, tok in enumerate(line.split(), start=1):
                if not _parses(tok, 1):
                    text = tok.decode("latin-1")
                    if len(text) > 40:
                        text = text[:37] + "..."
                    raise Pamap2FormatError(
                        f"{path}: line {i}: column {j}: non-numeric value {text!r} (expected a number or NaN)",
                        path=path, line=i, column=j,
                    )  # fmt: skip


def _first_bad_row(mask: np.ndarray) -> int | None:
    bad = np.flatnonzero(mask)
    return int(bad[0]) if bad.size else None


def _validate(path: Path, arr: np.ndarray) -> None:
    """Cheap value checks on the parsed ``[T, 54]`` matrix (raise on the first bad row)."""
    checks = (
        (1, ~np.isfinite(arr[:, 0]), "timestamp must be a finite number"),
        (2, ~np.isfinite(arr[:, 1]), "activity id must be a finite integer"),
    )
    for col, mask, what in checks:
        row = _first_bad_row(mask)
        if row is not None:
            raise Pamap2FormatError(
                f"{path}: line {row + 1}: column {col}: {what}, got {float(arr[row, col - 1]):g}",
                path=path, line=row + 1, column=col,
            )  # fmt: skip
    act = arr[:, 1]
    ok = (act == np.round(act)) & (act >= 0) & (act <= MAX_ACTIVITY_ID)
    ok[ok] = _VALID_ID[act[ok].astype(np.int64)]
    row = _first_bad_row(~ok)
    if row is not None:
        valid = ", ".join(str(a) for a in sorted(ACTIVITY_NAMES))
        raise Pamap2FormatError(
            f"{path}: line {row + 1}: column 2: invalid activity id {act[row]:g} (valid ids: {valid})",
            path=path, line=row + 1, column=2,
        )  # fmt: skip
    hr = arr[:, 2]
    row = _first_bad_row(~np.isnan(hr) & ~((hr > 0) & (hr <= 300)))
    if row is not None:
        raise Pamap2FormatError(
            f"{path}: line {row + 1}: column 3: implausible heart rate {hr[row]:g} bpm (expected (0, 300] or NaN)",
            path=path, line=row + 1, column=3,
        )  # fmt: skip
    inf = np.isinf(arr)
    if inf.any():
        row = int(np.flatnonzero(inf.any(axis=1))[0])
        col = int(np.flatnonzero(inf[row])[0]) + 1
        raise Pamap2FormatError(
            f"{path}: line {row + 1}: column {col}: infinite value (expected a finite number or NaN)",
            path=path, line=row + 1, column=col,
        )  # fmt: skip
    back = np.flatnonzero(np.diff(arr[:, 0]) < 0)
    if back.size:
        logger.warning(
            "%s: timestamps decrease at %d places (first at line %d); the rows are kept in file order",
            path, back.size, int(back[0]) + 2,
        )  # fmt: skip


def _parse_dat(path: Path) -> np.ndarray:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise Pamap2FormatError(f"{path}: file not found", path=path) from None
    except OSError as err:
        raise Pamap2FormatError(f"{path}: cannot read file ({err.strerror or err})", path=path) from None
    body = data.rstrip()  # trailing blank lines / final newline are fine
    if not body:
        raise Pamap2FormatError(
            f"{path}: line 1: empty file (expected rows of {_EXPECTED})", path=path, line=1
        )
    n_lines = body.count(b"\n") + 1
    try:
        # numpy's C text reader (about 2x faster than np.fromstring); it skips blank lines, hence the row check
        arr = np.loadtxt(io.StringIO(body.decode("latin-1")), dtype=np.float64, comments=None, ndmin=2)
    except ValueError as err:
        _raise_located(path, body, str(err))
    if arr.shape != (n_lines, N_COLUMNS):
        _raise_located(path, body, f"parsed shape {arr.shape}, expected ({n_lines}, {N_COLUMNS})")
    _validate(path, arr)
    return arr


def _raise_located(path: Path, body: bytes, reason: str) -> None:
    """Slow path after the fast parser failed: find the first bad line / field and raise with its position."""
    counts = _tokens_per_line(body)
    bad = np.flatnonzero(counts != N_COLUMNS)
    if bad.size:
        i = int(bad[0])
        n = int(counts[i])
        if n == 0:
            what = f"blank line (expected {_EXPECTED})"
        elif i == counts.shape[0] - 1 and n < N_COLUMNS:
            what = f"truncated last row: {n} of {N_COLUMNS} columns"
        else:
            what = f"expected {N_COLUMNS} columns, found {n}"
        raise Pamap2FormatError(f"{path}: line {i + 1}: {what}", path=path, line=i + 1)
    _raise_unparseable(path, body, reason)
    raise Pamap2FormatError(f"{path}: could not parse the numeric data ({reason})", path=path)


def _recording_from_array(arr: np.ndarray, *, subject: int | None, source: str | None,
                          info: dict | None = None) -> Pamap2Recording:  # fmt: skip
    imu = {}
    for site in IMU_SITES:
        c = _SITE_FIRST_COLUMN[site]
        imu[site] = arr[:, c : c + 17]
    return Pamap2Recording(
        timestamp=arr[:, 0],
        activity=arr[:, 1].astype(np.int64),
        heart_rate=arr[:, 2],
        imu=imu,
        subject=subject,
        source=source,
        info=dict(info or {}),
    )


_SUBJECT_RE = re.compile(r"subject(\d{3})\.dat$")


def load_pamap2_subject(path: str | Path) -> Pamap2Recording:
    """Read one ``subjectNNN.dat`` file (54 space-separated columns, ``NaN`` for missing values).

    Returns:
        :class:`Pamap2Recording` with ``T`` rows; ``imu[site]`` are views of one ``[T, 54]`` float64 matrix.

    Raises:
        Pamap2FormatError: missing/unreadable/empty file, a line without exactly 54 columns (a short last line is
            reported as a truncated row), a non-numeric field, an infinite value, a NaN timestamp or activity, an
            activity id outside :data:`ACTIVITY_NAMES`, or a heart rate outside (0, 300] bpm. One line naming the
            file, the 1-based line and (for field errors) the 1-based column.
    """
    path = Path(path)
    t0 = time.perf_counter()
    arr = _parse_dat(path)
    elapsed = time.perf_counter() - t0
    logger.debug("%s: %d rows in %.3f s (%.0f rows/s)", path, arr.shape[0], elapsed, arr.shape[0] / max(elapsed, 1e-9))
    m = _SUBJECT_RE.search(path.name)
    return _recording_from_array(arr, subject=int(m.group(1)) if m else None, source=str(path))


def _protocol_dir(folder: str | Path) -> Path:
    folder = Path(folder)
    if not folder.is_dir():
        raise Pamap2FormatError(f"{folder}: PAMAP2 folder not found", path=folder)
    if (folder / "Protocol").is_dir():
        return folder / "Protocol"
    return folder


def load_pamap2_protocol(folder: str | Path, subjects: Iterable[int] | None = None) -> dict[int, Pamap2Recording]:
    """Read ``Protocol/subjectNNN.dat`` for the given subjects (101-109).

    Args:
        folder: the dataset root (holding ``Protocol/``) or the ``Protocol`` folder itself.
        subjects: subject numbers; ``None`` = every ``subject101.dat`` .. ``subject109.dat`` present.

    Returns:
        ``{subject: Pamap2Recording}`` in ascending subject order.

    Raises:
        Pamap2FormatError: missing folder, no subject file, a requested subject's file missing, or a malformed file.
        ValueError: a subject number outside 101-109.
    """
    pdir = _protocol_dir(folder)
    if subjects is None:
        chosen = [s for s in PROTOCOL_SUBJECTS if (pdir / f"subject{s}.dat").is_file()]
        if not chosen:
            raise Pamap2FormatError(
                f"{pdir}: no subjectNNN.dat files (expected subject101.dat .. subject109.dat)", path=pdir
            )
    else:
        chosen = sorted({int(s) for s in subjects})
        wrong = [s for s in chosen if s not in PROTOCOL_SUBJECTS]
        if wrong or not chosen:
            raise ValueError(f"subjects: expected numbers in 101..109, got {list(subjects)!r}")
    return {s: load_pamap2_subject(pdir / f"subject{s}.dat") for s in chosen}


# ----------------------------------------------------------------------------------------------------------------------
# features
# ----------------------------------------------------------------------------------------------------------------------
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


def hr_feature_sequence(hr: np.ndarray, group: np.ndarray, met: np.ndarray, dt: float, hr_rest: float,
                         p: HRFeatureParams) -> np.ndarray:  # fmt: skip
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
    if n_rows >= 2:
        dt_row = float(np.median(np.diff(recording.timestamp[: min(n_rows, 10001)])))
        if not dt_row > 0:
            dt_row = 1.0 / SAMPLE_RATE_HZ
    else:
        dt_row = 1.0 / SAMPLE_RATE_HZ
    if not (rate_hz > 0) or rate_hz > 1.0 / dt_row * 1.0001:
        raise ValueError(f"rate_hz: expected a rate in (0, {1.0 / dt_row:g}] Hz, got {rate_hz!r}")
    w = max(1, int(round(1.0 / (rate_hz * dt_row))))
    n = n_rows // w
    if n < 1:
        raise ValueError(f"recording has {n_rows} rows, fewer than one window of {w} rows at rate_hz={rate_hz}")
    eff_rate = 1.0 / (w * dt_row)
    if abs(eff_rate - rate_hz) > 1e-6 * rate_hz:
        logger.info("rate_hz=%g is not a divisor of the %g Hz row rate; using %g Hz", rate_hz, 1 / dt_row, eff_rate)
    ends = np.arange(1, n + 1) * w - 1
    name = recording.source or f"subject {recording.subject}"

    sites = []
    for site in IMU_SITES:
        x = _ffill_rows(np.asarray(recording.imu[site][:, _IMU_FEATURE_CHANNELS], dtype=np.float64), f"{name} {site}")
        x = x[ends] if imu_reduce == "last" else x[: n * w].reshape(n, w, 12).mean(axis=1)
        sites.append(x * _IMU_SCALE)
    imu = np.concatenate(sites, axis=1).astype(np.float32)

    act = recording.activity[: n * w].astype(np.int64)
    counts = np.bincount(np.repeat(np.arange(n), w) * (MAX_ACTIVITY_ID + 1) + act, minlength=n * (MAX_ACTIVITY_ID + 1))
    activity = counts.reshape(n, MAX_ACTIVITY_ID + 1).argmax(axis=1).astype(np.int64)
    group = _GROUP_TABLE[activity]
    met = _MET_TABLE[activity]

    hr_rest = float(p.hr_rest) if p.hr_rest is not None else _estimate_hr_rest(recording)
    hr_ff = recording.heart_rate
    if np.isnan(hr_ff).all():
        logger.warning("%s: no heart-rate sample at all, using a constant %.0f bpm", name, hr_rest)
        hr_ff = np.full(n_rows, hr_rest)
    else:
        hr_ff = _ffill_rows(hr_ff, f"{name} heart rate")
    hr = hr_ff[ends].astype(np.float64)
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


# ----------------------------------------------------------------------------------------------------------------------
# synthetic generator
# ----------------------------------------------------------------------------------------------------------------------
#: Protocol activity order with nominal durations (s), similar to the PAMAP2 data collection protocol.
_PROTOCOL_TIMELINE: tuple[tuple[int, float], ...] = (
    (1, 180), (2, 180), (3, 180), (17, 180), (16, 180), (12, 60), (13, 60), (12, 60), (13, 60),
    (4, 180), (7, 180), (6, 180), (5, 180), (24, 120),
)  # fmt: skip
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
) -> Pamap2Recording:
    """A synthetic PAMAP2 protocol session at 100 Hz, in memory (what :func:`write_synthetic_pamap2` writes).

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
    t_rows = int(round(duration_s * SAMPLE_RATE_HZ))
    dt = 1.0 / SAMPLE_RATE_HZ
    bounds = np.round(np.cumsum([d for _, d in segs]) * SAMPLE_RATE_HZ).astype(np.int64)
    seg_of_row = np.minimum(np.searchsorted(bounds, np.arange(t_rows), side="right"), len(segs) - 1)
    activity = np.array([a for a, _ in segs], dtype=np.int64)[seg_of_row]
    n_seg = len(segs)
    seg_jitter = rng.uniform(0.85, 1.15, size=n_seg)[seg_of_row]  # per-segment effort

    # --- heart rate: integrate at 10 Hz, interpolate to 100 Hz -------------------------------------------------------
    sub = 10
    met = _MET_TABLE[activity] * np.where(activity == 0, 1.0, seg_jitter)
    met10 = met[::sub]
    dt10 = dt * sub
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
    t = np.arange(t_rows) * dt
    hr_true = np.interp(t, t[::sub], hr_true)
    fatigue = np.interp(t, t[::sub], fat)
    exert = np.clip((hr_true - hr_rest) / (hr_max - hr_rest), 0.0, 1.0)
    rsa = 2.5 * (1.0 - exert) * np.sin(2 * np.pi * 0.25 * t + rng.uniform(0, 2 * np.pi))
    hr_meas = np.round(hr_true + rsa + rng.normal(0.0, 1.0, size=t_rows))
    gaps = rng.choice(np.array([10, 11, 11, 11, 12]), size=t_rows // 10 + 2)
    hr_rows = np.cumsum(gaps) - gaps[0]
    hr_rows = hr_rows[hr_rows < t_rows]
    heart_rate = np.full(t_rows, np.nan)
    heart_rate[hr_rows] = np.clip(hr_meas[hr_rows], 35.0, 230.0)

    # --- IMUs -----------------------------------------------------------------------------------------------------
    ids = sorted(_MOVE)
    lut = np.zeros(MAX_ACTIVITY_ID + 1, dtype=np.int64)
    lut[ids] = np.arange(len(ids))
    k_of_row = lut[activity]
    freq = np.array([_MOVE[a][0] for a in ids])[k_of_row]
    acc_amp = np.array([_MOVE[a][1] for a in ids])[k_of_row] * amp_scale * seg_jitter[:, None]  # [T, 3]
    gyro_amp = np.array([_MOVE[a][2] for a in ids])[k_of_row] * amp_scale * seg_jitter[:, None]
    turn = np.array([_MOVE[a][3] for a in ids])[k_of_row]
    postures = sorted(_POSTURE)
    post_k = np.array([postures.index(_MOVE[a][4]) for a in ids])[k_of_row]
    gdir = np.array([[np.asarray(v) / np.linalg.norm(v) for v in _POSTURE[name]] for name in postures])  # [P, 3, 3]

    phase = 2 * np.pi * np.cumsum(freq) * dt + rng.uniform(0, 2 * np.pi)
    heading = np.cumsum(turn * math.sqrt(dt) * rng.normal(size=t_rows)) + rng.uniform(0, 2 * np.pi)
    temp_drift = np.cumsum(rng.normal(0, 0.002, size=t_rows // 100 + 1)).repeat(100)[:t_rows]

    imu: dict[str, np.ndarray] = {}
    for s, site in enumerate(IMU_SITES):
        g = gdir[post_k, s] * G  # [T, 3]
        c1, c2, c3, c4 = rng.uniform(0, 2 * np.pi, size=4)
        wave = np.stack(
            [np.sin(phase + s), 0.6 * np.sin(2 * phase + c1), 0.4 * np.sin(phase + c2)], axis=1
        )  # [T, 3]
        move = acc_amp[:, s : s + 1] * wave + 0.25 * acc_amp[:, s : s + 1] * rng.normal(size=(t_rows, 3))
        acc_true = g + move
        acc16 = np.clip(acc_true + rng.normal(0.0, 0.05, size=(t_rows, 3)), -16 * G, 16 * G)
        acc6 = np.clip(acc_true * 1.01 + 0.05 + rng.normal(0.0, 0.03, size=(t_rows, 3)), -6 * G, 6 * G)
        gwave = np.stack([np.sin(phase + c3), np.cos(phase + c3), 0.5 * np.sin(2 * phase + c4)], axis=1)
        gyro = gyro_amp[:, s : s + 1] * gwave + rng.normal(0.0, 0.015, size=(t_rows, 3))
        hdg = heading + 0.15 * np.sin(phase + s)
        mag = np.stack(
            [_EARTH_FIELD_UT[0] * np.cos(hdg), _EARTH_FIELD_UT[0] * np.sin(hdg), np.full(t_rows, _EARTH_FIELD_UT[1])],
            axis=1,
        ) + rng.normal(0.0, 0.6, size=(t_rows, 3))
        temp = _SITE_TEMP_C[s] + rng.uniform(-1.0, 1.0) + 1.0 * fatigue + temp_drift
        temp = np.round(np.clip(temp, 28.0, 37.0) * 16.0) / 16.0
        ori = np.zeros((t_rows, 4))
        ori[:, 0] = 1.0
        imu[site] = np.concatenate([temp[:, None], acc16, acc6, gyro, mag, ori], axis=1)

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


def _format_rows(arr: np.ndarray) -> str:
    fmt = _FORMAT
    text = "\n".join([fmt % tuple(row) for row in arr.tolist()])
    return text.replace("nan", "NaN") + "\n"


def write_synthetic_pamap2(
    folder: str | Path,
    subjects: Iterable[int] = (101, 102, 103),
    duration_s: float = 600.0,
    seed: int = 0,
) -> Path:
    """Write ``<folder>/Protocol/subjectNNN.dat`` files of :func:`synthetic_recording` in the PAMAP2 format.

    54 space-separated columns; timestamps with 2 decimals (10 ms steps); activity and heart rate as integers,
    ``NaN`` where the heart-rate monitor has no sample (~91 % of rows); IMU values with 6 significant digits.

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
        rec = synthetic_recording(s, duration_s=duration_s, seed=seed)
        (pdir / f"subject{s}.dat").write_text(_format_rows(rec.to_array()), encoding="ascii")
    return pdir


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
    return tuple(sorted(ACTIVITY_NAMES))

