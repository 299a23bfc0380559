"""Synthetic subjects that differ in their activity mix: one session plan per PAMAP2 subject number (101-109).

The synthetic generator (:func:`freamer_rl.data.synthetic_recording`) gives every subject its own physiology, drawn
from ``(seed, subject)`` before anything else (so the same under any activity mix): resting heart rate 58-78 bpm,
gain 9.5-13 bpm per MET (the fitness of the heart: a fitter subject's heart rate rises less per MET), heart-rate time
constant 12-25 s, fatigue drift 12 bpm. Without ``activities=`` every subject follows the same protocol order. This
module adds the other half of a subject: **what it does**. :data:`SUBJECT_PROFILES` gives each subject a session plan
(activities in order, with nominal durations, like PAMAP2's subjects, who skipped some protocol activities and did
different optional ones) and an activity level, ``"low"`` / ``"moderate"`` / ``"high"``:

=======  ==========  =====================================================  ============  ==================
subject  level       plan (main activities)                                 mean MET [1]  vigorous share [2]
=======  ==========  =====================================================  ============  ==================
101      moderate    protocol-like: rest, household, stairs, walks, run     3.7           0.13
102      low         rest, computer work, household, walking, short cycle   2.5           0.03
103      low         TV, car driving, household, walking                    2.2           0.03
104      high        runner: long running, stairs, cycling, rope jumping    5.5           0.40
105      moderate    cyclist: household, walking, long cycling              4.2           0.07
106      high        sport: soccer, running, rope jumping                   5.9           0.57
107      moderate    household and long walks (Nordic walking)              3.4           0.03
108      high        Nordic walking, running, cycling, rope jumping, soccer 5.9           0.45
109      low         optional activities (TV, computer, car, laundry)       2.1           0.00
=======  ==========  =====================================================  ============  ==================

[1] time-weighted mean MET of the plan (:data:`freamer_rl.data.ACTIVITY_MET`, transients excluded); range 2.1-5.9.
[2] share of the plan's time at MET >= 6 (running, ascending stairs, soccer, rope jumping); range 0.00-0.57.
(:func:`plan_statistics` computes both; ``tests/health/test_health_loso.py`` checks this table.)

:func:`profile_timeline` turns a plan into ``[(activity id, seconds), ...]`` for ``duration_s`` the way the generator
lays out the protocol (durations scaled to fit, jittered 0.85-1.15 and >= 15 s, transient gaps of 0.5-1.5 x 40 s
scaled, the plan repeated when the session is longer) from its own generator seeded by ``(seed, subject)``;
:func:`profile_recording` passes it to :func:`~freamer_rl.data.synthetic_recording` as ``activities=``. The health env
uses these recordings for env id ``pamap2-health-varied`` (``freamer_rl_envs.health``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freamer_rl.data.pamap2_format import ACTIVITY_MET, ACTIVITY_NAMES, PROTOCOL_SUBJECTS, Pamap2Recording
from freamer_rl.data.pamap2_synthetic import synthetic_recording

__all__ = [
    "ACTIVITY_LEVELS",
    "SubjectProfile",
    "SUBJECT_PROFILES",
    "plan_statistics",
    "profile_timeline",
    "profile_recording",
]

ACTIVITY_LEVELS: tuple[str, ...] = ("low", "moderate", "high")
#: MET at and above which an activity counts as vigorous (running, ascending stairs, soccer, rope jumping)
VIGOROUS_MET = 6.0
# the timeline layout of the generator's protocol (freamer_rl.data.pamap2_synthetic), for a plan
_TRANSIENT_S = 40.0
_MIN_SEGMENT_S = 15.0
_MIN_TRANSIENT_S = 4.0
_STREAM = 7  # a third word of the timeline generator's seed: its draws never coincide with the recording's


@dataclass(frozen=True)
class SubjectProfile:
    """One subject's session: ``plan`` = ``((activity id, nominal seconds), ...)`` in order; ``level`` in
    :data:`ACTIVITY_LEVELS`."""

    subject: int
    level: str
    plan: tuple[tuple[int, float], ...]

    def __post_init__(self) -> None:
        if self.level not in ACTIVITY_LEVELS:
            raise ValueError(
                f"SubjectProfile {self.subject}: level must be one of {ACTIVITY_LEVELS}, got {self.level!r}"
            )
        bad = [a for a, d in self.plan if a not in ACTIVITY_NAMES or a == 0 or not d > 0]
        if not self.plan or bad:
            raise ValueError(
                f"SubjectProfile {self.subject}: plan needs activity ids != 0 with durations > 0, got {bad}"
            )


def _profile(subject: int, level: str, plan: str) -> SubjectProfile:
    """``plan`` written ``"<activity id>:<seconds> ..."``."""
    return SubjectProfile(subject, level, tuple((int(a), float(d)) for a, d in (x.split(":") for x in plan.split())))


#: The session plan of each subject (module docstring table), ``activity id:nominal seconds`` in order. Activity ids:
#: 1 lying, 2 sitting, 3 standing, 4 walking, 5 running, 6 cycling, 7 Nordic walking, 9 watching TV, 10 computer
#: work, 11 car driving, 12/13 stairs up/down, 16 vacuum cleaning, 17 ironing, 18 folding laundry, 19 house
#: cleaning, 20 soccer, 24 rope jumping.
SUBJECT_PROFILES: dict[int, SubjectProfile] = {
    p.subject: p
    for p in (
        _profile(101, "moderate", "1:180 2:180 3:180 17:180 16:180 12:60 13:60 4:240 7:180 6:180 5:120 24:60"),
        _profile(102, "low", "1:240 2:240 10:300 3:180 17:240 18:180 19:180 4:300 12:60 13:60 6:120"),
        _profile(103, "low", "1:180 9:300 2:240 11:240 3:120 18:180 17:180 4:360 13:60 12:60"),
        _profile(104, "high", "1:120 2:120 3:120 4:180 5:420 12:90 13:90 6:240 24:180 7:180"),
        _profile(105, "moderate", "2:180 3:120 16:180 19:180 4:240 6:480 7:240 12:60 13:60 5:60"),
        _profile(106, "high", "1:120 3:120 4:180 20:420 5:240 24:180 6:180 12:90 13:90"),
        _profile(107, "moderate", "1:180 2:180 17:180 16:240 19:240 4:300 7:300 12:60 13:60 6:120"),
        _profile(108, "high", "2:120 3:120 4:180 7:240 5:300 6:300 24:240 20:240"),
        _profile(109, "low", "2:240 9:300 10:300 11:240 18:180 19:240 3:120 4:240"),
    )
}
if tuple(SUBJECT_PROFILES) != PROTOCOL_SUBJECTS:  # one plan per PAMAP2 subject number, in order
    raise RuntimeError(f"SUBJECT_PROFILES covers {tuple(SUBJECT_PROFILES)}, expected {PROTOCOL_SUBJECTS}")


def _profile_of(subject: int) -> SubjectProfile:
    try:
        return SUBJECT_PROFILES[int(subject)]
    except KeyError:
        raise ValueError(f"subject: expected a PAMAP2 subject number in 101..109, got {subject!r}") from None


def plan_statistics(subject: int) -> dict[str, float]:
    """``{"mean_met", "vigorous_share", "seconds"}`` of a subject's plan: time-weighted mean MET, share of the time at
    MET >= :data:`VIGOROUS_MET`, nominal length in seconds (transients excluded)."""
    plan = _profile_of(subject).plan
    seconds = np.array([d for _, d in plan], dtype=np.float64)
    met = np.array([ACTIVITY_MET[a] for a, _ in plan], dtype=np.float64)
    total = float(seconds.sum())
    return {
        "mean_met": float((met * seconds).sum() / total),
        "vigorous_share": float(seconds[met >= VIGOROUS_MET].sum() / total),
        "seconds": total,
    }


def profile_timeline(subject: int, duration_s: float, seed: int = 0) -> list[tuple[int, float]]:
    """``[(activity id, seconds), ...]`` covering ``duration_s``: the subject's plan with transient (id 0) gaps,
    durations scaled to one plan per session at most (``min(1, duration_s / nominal)``), jittered 0.85-1.15 (>= 15 s),
    gaps 0.5-1.5 x 40 s scaled (>= 4 s), repeated until ``duration_s``; seeded by ``(seed, subject)``."""
    if not duration_s > 1.0:
        raise ValueError(f"duration_s: expected more than 1 s, got {duration_s!r}")
    plan = _profile_of(subject).plan
    rng = np.random.default_rng([int(seed), int(subject), _STREAM])
    nominal = sum(d for _, d in plan) + _TRANSIENT_S * (len(plan) + 1)
    scale = min(1.0, float(duration_s) / nominal)
    segs: list[tuple[int, float]] = []
    total, i = 0.0, 0
    while total < duration_s:
        gap = max(_MIN_TRANSIENT_S, _TRANSIENT_S * scale * float(rng.uniform(0.5, 1.5)))
        activity, seconds = plan[i % len(plan)]
        seg = max(_MIN_SEGMENT_S, seconds * scale * float(rng.uniform(0.85, 1.15)))
        segs += [(0, gap), (activity, seg)]
        total += gap + seg
        i += 1
    return segs


def profile_recording(subject: int, *, duration_s: float = 600.0, seed: int = 0) -> Pamap2Recording:
    """:func:`~freamer_rl.data.synthetic_recording` of ``subject`` following its plan (:func:`profile_timeline`);
    the physiology is the generator's for ``(seed, subject)``; ``info["activity_level"]`` holds the plan's level."""
    rec = synthetic_recording(
        int(subject), duration_s=duration_s, seed=seed, activities=profile_timeline(subject, duration_s, seed)
    )
    rec.info["activity_level"] = _profile_of(subject).level
    return rec
