"""Physiology of the health env: heart-rate dynamics constants, exertion / fatigue / HRV updates, and the per-subject
tables (IMU windows, activities, heart rate, fitted physiology) built from PAMAP2 recordings or their synthetic twins.

Split from :mod:`freamer_rl_envs.health` (the TorchRL env), which re-exports the public names.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math

import numpy as np
import torch

from freamer_rl.data import (
    MAX_ACTIVITY_ID,
    HRFeatureParams,
    Pamap2Features,
    load_pamap2_protocol,
    pamap2_features,
    synthetic_recording,
)
from freamer_rl.data.subject_profiles import profile_recording

logger = logging.getLogger(__name__)

#: Subjects of the embedded synthetic data when none are named.
DEFAULT_SYNTHETIC_SUBJECTS: tuple[int, ...] = (101, 102, 103)


@dataclasses.dataclass(frozen=True)
class HealthDynamics:
    """Constants of the health env (see the module docstring for the equations)."""

    hr_danger: float = 160.0
    hr_critical: float = 200.0
    hr_min: float = 35.0
    hr_clip_max: float = 230.0
    hr_noise: float = 1.0  # bpm / sqrt(s)
    hr_target_cap: float = 150.0
    target_sigma: float = 10.0
    danger_slope: float = 20.0
    level_step: float = 0.25
    level_max: float = 2.0
    alert_hold_s: float = 30.0
    alert_level_cap: float = 0.25
    alert_cost: float = 0.2
    termination_penalty: float = 10.0
    default_tau_s: float = 20.0
    default_drift: float = 12.0


# ----------------------------------------------------------------------------------------------------------------------
# shared feature maths (the recursions of freamer_rl.data.hr_feature_sequence, in torch)
# ----------------------------------------------------------------------------------------------------------------------
def exertion(hr: torch.Tensor, hr_rest: torch.Tensor, p: HRFeatureParams) -> torch.Tensor:
    """``clip((HR - HR_rest) / (HR_max - HR_rest), 0, exertion_max)``."""
    return ((hr - hr_rest) / (p.hr_max - hr_rest)).clamp(0.0, p.exertion_max)


def fatigue_update(fatigue: torch.Tensor, e: torch.Tensor, dt: float, p: HRFeatureParams) -> torch.Tensor:
    """Asymmetric EMA of exertion: accumulates with ``tau_fatigue_up_s``, recovers with ``tau_fatigue_down_s``."""
    a_up = 1.0 - math.exp(-dt / p.tau_fatigue_up_s)
    a_down = 1.0 - math.exp(-dt / p.tau_fatigue_down_s)
    return fatigue + torch.where(e > fatigue, a_up, a_down) * (e - fatigue)


def hrv_update(
    mean: torch.Tensor, var: torch.Tensor, hr: torch.Tensor, dt: float, p: HRFeatureParams
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exponentially weighted mean / variance of the heart rate (time constant ``tau_hrv_s``)."""
    b = 1.0 - math.exp(-dt / p.tau_hrv_s)
    d = hr - mean
    return mean + b * d, (1.0 - b) * (var + b * d * d)


# ----------------------------------------------------------------------------------------------------------------------
# data tables
# ----------------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class _SubjectTables:
    subjects: tuple[int, ...]
    rate_hz: float
    imu: np.ndarray  # [S, N, 36]
    activity: np.ndarray  # [S, N]
    hr: np.ndarray  # [S, N]
    fatigue: np.ndarray  # [S, N]
    hrv_std: np.ndarray  # [S, N] bpm
    length: np.ndarray  # [S]
    hr_rest: np.ndarray  # [S]
    gain: np.ndarray  # [S]
    tau: np.ndarray  # [S]
    drift: np.ndarray  # [S]
    posture: np.ndarray  # [S, 25, 36]
    pool: np.ndarray  # [S, 25, P] window indices per activity
    pool_n: np.ndarray  # [S, 25]


def _subject_physiology(feat: Pamap2Features, info: dict, dyn: HealthDynamics) -> tuple[float, float, float, float]:
    if info.get("synthetic"):
        return float(info["hr_rest"]), float(info["hr_gain"]), float(info["tau_hr"]), float(info["fatigue_drift"])
    hr_rest = feat.hr_rest
    sel = (feat.met >= 3.0) & (feat.activity != 0)
    if sel.any():
        gain = float(np.clip(np.median((feat.heart_rate[sel] - hr_rest) / (feat.met[sel] - 1.0)), 6.0, 18.0))
    else:
        gain = 11.0
        logger.warning(
            "subject %s: no activity with MET >= 3, using a default gain of %.0f bpm/MET", feat.subject, gain
        )
    return hr_rest, gain, dyn.default_tau_s, dyn.default_drift


@functools.lru_cache(maxsize=8)
def _load_tables(
    data_dir: str | None,
    subjects: tuple[int, ...] | None,
    rate_hz: float,
    synthetic_duration_s: float,
    data_seed: int,
    dyn: HealthDynamics,
    varied: bool = False,
) -> _SubjectTables:
    if data_dir is None:
        chosen = subjects or DEFAULT_SYNTHETIC_SUBJECTS
        # varied: each subject follows its own activity plan (freamer_rl.data.subject_profiles), else the protocol
        make = profile_recording if varied else synthetic_recording
        recordings = {s: make(s, duration_s=synthetic_duration_s, seed=data_seed) for s in chosen}
    else:
        recordings = load_pamap2_protocol(data_dir, subjects)
    feats = {s: pamap2_features(r, rate_hz=rate_hz) for s, r in recordings.items()}
    subj = tuple(feats)
    n_max = max(len(f) for f in feats.values())
    S, A = len(subj), MAX_ACTIVITY_ID + 1
    imu = np.zeros((S, n_max, 36), np.float32)
    act = np.zeros((S, n_max), np.int64)
    hr = np.zeros((S, n_max), np.float32)
    fat = np.zeros((S, n_max), np.float32)
    hrv = np.zeros((S, n_max), np.float32)
    length = np.zeros(S, np.int64)
    phys = np.zeros((S, 4), np.float64)
    posture = np.zeros((S, A, 36), np.float32)
    pools: list[list[np.ndarray]] = []
    p = HRFeatureParams()
    for i, s in enumerate(subj):
        f = feats[s]
        n = len(f)
        imu[i, :n], act[i, :n], hr[i, :n] = f.imu, f.activity, f.heart_rate
        fat[i, :n] = f.hr_features[:, 11]
        hrv[i, :n] = f.hr_features[:, 12] * p.hrv_scale
        length[i] = n
        phys[i] = _subject_physiology(f, recordings[s].info, dyn)
        mean_all = f.imu.mean(axis=0)
        row = []
        for a in range(A):
            idx = np.flatnonzero(f.activity == a)
            posture[i, a] = f.imu[idx].mean(axis=0) if idx.size else mean_all
            row.append(idx)
        pools.append(row)
    p_max = max(1, max(len(ix) for row in pools for ix in row))
    pool = np.zeros((S, A, p_max), np.int64)
    pool_n = np.zeros((S, A), np.int64)
    for i, row in enumerate(pools):
        for a, ix in enumerate(row):
            pool[i, a, : ix.size] = ix
            pool_n[i, a] = ix.size
    return _SubjectTables(
        subjects=subj,
        rate_hz=float(feats[subj[0]].rate_hz),
        imu=imu,
        activity=act,
        hr=hr,
        fatigue=fat,
        hrv_std=hrv,
        length=length,
        hr_rest=phys[:, 0],
        gain=phys[:, 1],
        tau=phys[:, 2],
        drift=phys[:, 3],
        posture=posture,
        pool=pool,
        pool_n=pool_n,
    )


# ----------------------------------------------------------------------------------------------------------------------
# env
# ----------------------------------------------------------------------------------------------------------------------
