"""Labelled health anomalies: injection into a PAMAP2 recording, the labels CSV and its checked reader.

A scenario with ground truth is a PAMAP2-format ``subjectNNN.dat`` whose signal was changed inside labelled
intervals, plus a labels file (``start_s,end_s,kind`` header, one interval a line, times in the ``.dat``'s own
timestamp seconds, half-open ``[start_s, end_s)``). :func:`write_anomaly_scenario` writes both.

The four kinds (:data:`ANOMALY_KINDS`) and how each is made (defaults in :data:`DEFAULT_ANOMALIES`; ``size`` is
the ``AnomalySpec.size`` field):

==============  =========  ===========================================================================================
kind            default    what is changed inside ``[start, end)``
==============  =========  ===========================================================================================
``hr_spike``    120 s,     heart rate ``+ size * ramp`` (trapezoid, 10 s up and down), placed only inside a rest
                +35 bpm    segment (lying / sitting / standing, activity ids 1-3): a heart-rate rise without movement;
                           the IMU columns are untouched
``dropout``     120 s      every sensor column (heart rate and the three IMUs) ``NaN``: the wireless packets are lost;
                           the feature code forward-fills, so the observation freezes at the last sample before it
``drift``       1200 s,    heart rate ``+ size * (t - start) / (end - start)``: a slow sensor drift (a linear ramp
                +30 bpm    from 0 to +30 bpm over 20 minutes) that vanishes at ``end`` (the sensor is re-seated)
``arrhythmia``  180 s,     heart rate ``+ size * N(0, 1)``, a new draw every ``block_s = 1`` s: irregular beat-to-beat
                15 bpm     rate (a 5 s health-env step sees jumps of ~15-20 bpm between steps)
==============  =========  ===========================================================================================

Heart rates stay integer bpm clipped to [35, 230] (the generator's range). "Detected" at the env's step rate means:
at least one step whose window overlaps the interval is flagged (:mod:`freamer_rl.health.anomaly_scoring`).

Placement (:func:`inject_anomalies`): ``per_kind`` events of each kind, in a seeded random order, each at a uniform
start in ``[t0 + lead_s, t_end - duration)`` (``lead_s = 30 min``: the detector's statistics start on normal data),
at least ``min_gap_s`` (10 min) from every other event; the draw is repeated (at most 2,000 times) until it fits.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from freamer_rl.data.pamap2_format import IMU_SITES, Pamap2Recording
from freamer_rl.data.pamap2_synthetic import synthetic_recording, write_recording
from freamer_rl.errors import FreamerError

__all__ = [
    "ANOMALY_KINDS",
    "LABELS_HEADER",
    "DEFAULT_ANOMALIES",
    "AnomalySpec",
    "AnomalyInterval",
    "AnomalyLabelsError",
    "inject_anomalies",
    "write_labels",
    "read_labels",
    "write_anomaly_scenario",
    "recording_time_range",
]

ANOMALY_KINDS: tuple[str, ...] = ("hr_spike", "dropout", "drift", "arrhythmia")
LABELS_HEADER = "start_s,end_s,kind"
_REST_IDS = (1, 2, 3)  # lying, sitting, standing: where an hr_spike is "without movement"
_RAMP_S = 10.0
_BLOCK_S = 1.0
_MAX_DRAWS = 2000


@dataclasses.dataclass(frozen=True)
class AnomalySpec:
    """Duration (s) and size of one kind (bpm for the heart-rate kinds; unused for ``dropout``)."""

    duration_s: float
    size: float = 0.0


DEFAULT_ANOMALIES: dict[str, AnomalySpec] = {
    "hr_spike": AnomalySpec(120.0, 35.0),
    "dropout": AnomalySpec(120.0),
    "drift": AnomalySpec(1200.0, 30.0),
    "arrhythmia": AnomalySpec(180.0, 15.0),
}


@dataclasses.dataclass(frozen=True)
class AnomalyInterval:
    """One labelled interval ``[start_s, end_s)`` (recording timestamps) of ``kind``; ``line``: its labels-file line."""

    start_s: float
    end_s: float
    kind: str
    line: int | None = None


class AnomalyLabelsError(FreamerError, ValueError):
    """A labels file is missing or malformed: one line ``"<file>: line <n>: <what is wrong>"``."""

    def __init__(self, message: str, *, path: str | Path | None = None, line: int | None = None) -> None:
        super().__init__(message)
        self.path = None if path is None else str(path)
        self.line = line


# ----------------------------------------------------------------------------------------------------------------------
# injection
# ----------------------------------------------------------------------------------------------------------------------
def _fits(rec: Pamap2Recording, kind: str, i0: int, i1: int, taken: list[tuple[int, int]], gap: int) -> bool:
    """Whether rows ``[i0, i1)`` keep ``gap`` rows from every taken interval (and, for a spike, lie in one rest
    segment)."""
    if any(i0 < b + gap and a < i1 + gap for a, b in taken):
        return False
    if kind == "hr_spike":
        act = rec.activity[i0:i1]
        return bool(np.isin(act, _REST_IDS).all() and (act == act[0]).all())
    return True


def _place(rec: Pamap2Recording, kind: str, n: int, lo: int, taken: list, gap: int, rng) -> int:
    """First row of a random ``n``-row interval in ``[lo, T)`` that :func:`_fits`, or -1 after ``_MAX_DRAWS``."""
    hi = len(rec) - n
    for _ in range(_MAX_DRAWS if lo < hi else 0):
        i0 = int(rng.integers(lo, hi))
        if _fits(rec, kind, i0, i0 + n, taken, gap):
            return i0
    return -1


def _change_signal(rec: Pamap2Recording, kind: str, spec: AnomalySpec, i0: int, i1: int, rng) -> None:
    """Apply one anomaly of ``kind`` to rows ``[i0, i1)`` of ``rec`` in place (module docstring table)."""
    t = rec.timestamp[i0:i1] - rec.timestamp[i0]
    hr = rec.heart_rate[i0:i1]  # a view: edits land in the recording
    has = ~np.isnan(hr)
    if kind == "dropout":
        hr[:] = np.nan
        for site in IMU_SITES:
            rec.imu[site][i0:i1] = np.nan
        return
    duration = float(t[-1]) + (float(t[1]) if t.shape[0] > 1 else 0.0)
    if kind == "hr_spike":
        offset = spec.size * np.clip(np.minimum(t, duration - t) / _RAMP_S, 0.0, 1.0)
    elif kind == "drift":
        offset = spec.size * t / max(duration, 1e-9)
    else:  # arrhythmia: one N(0, size) draw per block of _BLOCK_S seconds
        block = (t // _BLOCK_S).astype(np.int64)
        offset = spec.size * rng.normal(size=int(block[-1]) + 1)[block]
    hr[has] = np.clip(np.round(hr[has] + offset[has]), 35.0, 230.0)


def inject_anomalies(
    recording: Pamap2Recording,
    *,
    seed: int = 0,
    per_kind: int = 6,
    kinds: Iterable[str] = ANOMALY_KINDS,
    specs: Mapping[str, AnomalySpec] | None = None,
    lead_s: float = 1800.0,
    min_gap_s: float = 600.0,
) -> tuple[Pamap2Recording, list[AnomalyInterval]]:
    """A copy of ``recording`` with ``per_kind`` labelled anomalies of each kind (module docstring), and the labels.

    Returns:
        ``(changed recording, intervals sorted by start)``; ``info["anomalies"]`` of the copy holds the intervals
        as ``(start_s, end_s, kind)`` tuples.

    Raises:
        ValueError: an unknown kind, ``per_kind < 0``, or events that do not fit (recording too short; names the
            kind).
    """
    kinds = tuple(kinds)
    bad = [k for k in kinds if k not in ANOMALY_KINDS]
    if bad:
        raise ValueError(f"kinds: unknown anomaly kinds {bad} (expected some of {', '.join(ANOMALY_KINDS)})")
    if int(per_kind) != per_kind or per_kind < 0:
        raise ValueError(f"per_kind: expected an integer >= 0, got {per_kind!r}")
    specs = {**DEFAULT_ANOMALIES, **dict(specs or {})}
    rec = dataclasses.replace(
        recording,
        heart_rate=recording.heart_rate.copy(),
        imu={s: v.copy() for s, v in recording.imu.items()},
        info=dict(recording.info),
    )
    rng = np.random.default_rng([int(seed), 0xA40])
    ts = rec.timestamp
    period = float(np.median(np.diff(ts[: min(len(ts), 10001)]))) if len(ts) > 1 else 0.01
    order = list(rng.permutation(np.repeat(np.arange(len(kinds)), int(per_kind))))
    taken: list[tuple[int, int]] = []
    labels: list[AnomalyInterval] = []
    gap = int(round(min_gap_s / period))
    lo = int(np.searchsorted(ts, ts[0] + lead_s))
    for k in order:
        kind, spec = kinds[k], specs[kinds[k]]
        n = max(2, int(round(spec.duration_s / period)))
        i0 = _place(rec, kind, n, lo, taken, gap, rng)
        if i0 < 0:
            raise ValueError(
                f"per_kind: no room for another {kind!r} event of {spec.duration_s:g} s in a "
                f"{rec.duration_s:g} s recording ({len(taken)} placed; lower per_kind or lengthen the recording)"
            )
        _change_signal(rec, kind, spec, i0, i0 + n, rng)
        taken.append((i0, i0 + n))
        labels.append(AnomalyInterval(round(float(ts[i0]), 2), round(float(ts[i0]) + n * period, 2), kind))
    labels.sort(key=lambda a: a.start_s)
    rec.info["anomalies"] = [(a.start_s, a.end_s, a.kind) for a in labels]
    return rec, labels


# ----------------------------------------------------------------------------------------------------------------------
# the labels file
# ----------------------------------------------------------------------------------------------------------------------
def write_labels(intervals: Iterable[AnomalyInterval], path: str | Path) -> Path:
    """Write ``start_s,end_s,kind`` (header line, then one interval a line, seconds with 2 decimals)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = [LABELS_HEADER] + [f"{a.start_s:.2f},{a.end_s:.2f},{a.kind}" for a in intervals]
    path.write_text("\n".join(rows) + "\n", encoding="ascii")
    return path


_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")


def _number(path: Path, line: int, name: str, text: str) -> float:
    if not _NUMBER.match(text):
        raise AnomalyLabelsError(f"{path}: line {line}: {name}: not a finite number: {text!r}", path=path, line=line)
    return float(text)


def _parse_row(path: Path, line: int, raw: str) -> AnomalyInterval:
    fields = [f.strip() for f in raw.split(",")]
    if len(fields) != 3:
        raise AnomalyLabelsError(
            f"{path}: line {line}: expected 3 comma-separated fields ({LABELS_HEADER}), found {len(fields)}",
            path=path,
            line=line,
        )
    start, end = _number(path, line, "start_s", fields[0]), _number(path, line, "end_s", fields[1])
    kind = fields[2]
    if not end > start:
        raise AnomalyLabelsError(
            f"{path}: line {line}: end_s {end:g} must be greater than start_s {start:g}", path=path, line=line
        )
    if kind not in ANOMALY_KINDS:
        raise AnomalyLabelsError(
            f"{path}: line {line}: unknown kind {kind!r} (expected one of {', '.join(ANOMALY_KINDS)})",
            path=path,
            line=line,
        )
    return AnomalyInterval(start, end, kind, line)


def read_labels(path: str | Path, *, time_range: tuple[float, float] | None = None) -> list[AnomalyInterval]:
    """Read and check a labels file; returns the intervals sorted by start (``line`` = their line in the file).

    Args:
        path: the CSV (header ``start_s,end_s,kind``; blank lines are skipped; zero intervals are allowed: a
            normal scenario).
        time_range: ``(first, last)`` time of the recording (s); every interval must lie inside it.

    Raises:
        AnomalyLabelsError: one line naming the file and the 1-based line: missing file, wrong header, a row
            without 3 fields, a non-numeric or non-finite time, ``end_s <= start_s``, an unknown kind, an interval
            outside ``time_range``, or two intervals that overlap (the later line, naming the earlier one).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise AnomalyLabelsError(f"{path}: labels file not found", path=path) from None
    except (OSError, UnicodeDecodeError) as err:
        raise AnomalyLabelsError(f"{path}: cannot read the labels file ({err})", path=path) from None
    lines = text.splitlines()
    if not lines or lines[0].strip().replace(" ", "") != LABELS_HEADER:
        got = lines[0][:60] if lines else ""
        raise AnomalyLabelsError(
            f"{path}: line 1: expected the header {LABELS_HEADER!r}, got {got!r}", path=path, line=1
        )
    out = [_parse_row(path, i, raw) for i, raw in enumerate(lines[1:], start=2) if raw.strip()]
    if time_range is not None:
        t0, t1 = time_range
        for a in out:
            if a.start_s < t0 - 1e-6 or a.end_s > t1 + 1e-6:
                raise AnomalyLabelsError(
                    f"{path}: line {a.line}: interval [{a.start_s:g}, {a.end_s:g}) s is outside the recording "
                    f"({t0:g} .. {t1:g} s)",
                    path=path,
                    line=a.line,
                )
    out.sort(key=lambda a: (a.start_s, a.line))
    for prev, cur in zip(out, out[1:]):
        if cur.start_s < prev.end_s:
            later, earlier = (cur, prev) if cur.line > prev.line else (prev, cur)
            raise AnomalyLabelsError(
                f"{path}: line {later.line}: interval [{later.start_s:g}, {later.end_s:g}) overlaps line "
                f"{earlier.line} [{earlier.start_s:g}, {earlier.end_s:g})",
                path=path,
                line=later.line,
            )
    return out


def recording_time_range(recording: Pamap2Recording) -> tuple[float, float]:
    """``(first timestamp, last timestamp + one row period)``: the span a label may cover (s)."""
    ts = recording.timestamp
    period = float(np.median(np.diff(ts[: min(len(ts), 10001)]))) if len(ts) > 1 else 0.0
    return float(ts[0]), float(ts[-1]) + (period if math.isfinite(period) else 0.0)


def write_anomaly_scenario(
    folder: str | Path,
    *,
    hours: float = 48.0,
    seed: int = 0,
    subject: int = 101,
    row_rate_hz: float = 1.0,
    per_kind: int | None = None,
    specs: Mapping[str, AnomalySpec] | None = None,
) -> tuple[Path, Path]:
    """Write a synthetic subject with injected anomalies: ``<folder>/Protocol/subjectNNN.dat`` and
    ``<folder>/labels.csv``.

    The recording (:func:`~freamer_rl.data.synthetic_recording`, ``duration_s = hours * 3600``, ``seed``) is
    generated for the whole scenario, so a health-env step rate of up to ``row_rate_hz`` walks through it once:
    nothing wraps around. ``row_rate_hz = 1`` (default) keeps 48 hours at 172,800 rows (~80 MB of text). ``per_kind``
    defaults to one event of each kind per 8 hours (6 each in 48 hours).

    Returns:
        ``(dat path, labels path)``.
    """
    if not hours > 0:
        raise ValueError(f"hours: expected > 0, got {hours!r}")
    n = per_kind if per_kind is not None else max(1, int(hours // 8))
    rec = synthetic_recording(subject, duration_s=hours * 3600.0, seed=seed, row_rate_hz=row_rate_hz)
    rec, labels = inject_anomalies(rec, seed=seed, per_kind=n, specs=specs)
    folder = Path(folder)
    dat = write_recording(rec, folder / "Protocol" / f"subject{int(subject)}.dat")
    return dat, write_labels(labels, folder / "labels.csv")
