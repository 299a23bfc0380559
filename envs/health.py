"""Wearable health-management env (paper Section 5, Appendix C / J.4): a batched TorchRL :class:`EnvBase`.

Each batch element follows one subject's PAMAP2 activity timeline (real ``Protocol/subjectNNN.dat`` files when
``data_dir`` is given, else the embedded synthetic subjects of :mod:`freamer_rl.data`) at ``rate_hz`` steps
per second (default 1 Hz, one step = 1 s). The recorded IMU windows drive the ``"imu"`` observation; heart rate and
fatigue come from a physiological model the agent's interventions act on.

Observations (``B = batch_size``)
--------------------------------
=========================  =====================  =====================================================================
key                        dtype / shape          meaning
=========================  =====================  =====================================================================
``"imu"``                  float32 ``[B, 36]``    hand/chest/ankle x (acc16 xyz, acc6 xyz, gyro xyz, mag xyz), scaled
                                                  as :data:`freamer_rl.data.IMU_FEATURE_NAMES`
``"hr_features"``          float32 ``[B, 16]``    the loader's 16 heart-rate features (:func:`pamap2_features` table)
                                                  computed from the *model* heart rate; ``intensity`` (index 15) is
                                                  ``MET_eff / 12`` (= the loader's value at level 1 without Change),
                                                  rate of change and cumulative exertion restart at 0 on reset
``"heart_rate"``           float32 ``[B, 1]``     model heart rate (bpm), for plots and anomaly detection
``"activity"``             int64 ``[B]``          PAMAP2 activity id being performed (timeline, or the agent's Change)
``"level"``                float32 ``[B, 1]``     prescribed intensity level (1 = as planned, 0 after an Alert)
``("episode", "return")``  float32 ``[B, 1]``     sum of rewards since the episode's reset
``("episode", "violations")``  int64 ``[B, 1]``   number of steps that ended with heart rate > 160 bpm
``("episode", "length")``  int64 ``[B, 1]``       steps since the reset
=========================  =====================  =====================================================================

plus ``"reward"`` float32 ``[B, 1]`` and ``"done"`` / ``"terminated"`` / ``"truncated"`` bool ``[B, 1]``; the action
is ``Categorical(5)`` of shape ``[B]``. Read the per-episode metrics at ``("next", "episode", ...)`` on the step
where ``("next", "done")`` is True.

Dynamics (per step, ``dt = 1 / rate_hz`` s; subject constants ``HR_rest``, ``gain``, ``tau``, ``drift``)
-----------------------------------------------------------------------------------------------------
The agent holds an intensity ``level`` in ``[0, 2]`` (1 = as planned) and optionally an activity override.

1. Action: 0 **Continue** (nothing), 1 **Rest** (``level -= 0.25``), 2 **Increase** (``level += 0.25``, at most
   2), 3 **Change** (switch to an alternative activity type, :data:`CHANGE_TO`, at ``level = 1``, e.g. running ->
   cycling, rope jumping -> walking), 4 **Alert** (emergency stop: ``level = 0`` and ``level <= 0.25`` for the
   next 30 s; costs ``alert_cost`` unless the heart rate was above 160 bpm).
2. Effective intensity ``MET_eff = 1 + (MET(activity) - 1) * level`` (:data:`ACTIVITY_MET`).
3. Heart rate, first-order lag: ``HR_ss = HR_rest + gain (MET_eff - 1) + drift * F``;
   ``HR <- HR + (1 - exp(-dt / tau)) (HR_ss - HR) + hr_noise sqrt(dt) N(0, 1)``, clipped to [35, 230].
4. Exertion ``e = clip((HR - HR_rest) / (190 - HR_rest), 0, 1.5)``; fatigue ``F`` accumulates with exertion
   (tau 120 s) and recovers at rest (tau 240 s): ``F <- F + (1 - exp(-dt / tau_up|down)) (e - F)``.
5. The timeline advances one window; when its activity changes (a new segment), ``level = 1`` and the override
   is cleared (a running Alert stop still caps the level at 0.25).

Reward (Eq. A11) ``R = w_safe R_safe + w_target R_target + w_fatigue R_fatigue``, defaults ``(2.0, 1.0, 0.5)``:

- ``R_safe = -1[HR > 160] (1 + (HR - 160) / 20) - alert_cost 1[Alert and HR_before <= 160]
  - termination_penalty 1[HR >= 200]`` (danger zone above 160 bpm; ``alert_cost = 0.2``, penalty 10);
- ``R_target = exp(-((HR - HR_target) / 10)^2 / 2)`` in [0, 1], ``HR_target = min(HR_rest + gain (MET(planned) - 1),
  150)`` for the timeline's planned activity;
- ``R_fatigue = -F``.

Termination when ``HR >= 200`` bpm (medical emergency), truncation after ``episode_length`` steps.

Subjects: env id ``pamap2-health-varied`` gives every synthetic subject its own activity plan
(:mod:`freamer_rl.data.subject_profiles`: activity levels low / moderate / high, mean MET 2.1-5.9); the other ids
follow the protocol order.

Subject constants: synthetic subjects use their generator's ground truth; real subjects use ``HR_rest`` = 5th
percentile of their heart rate, ``gain`` = median of ``(HR - HR_rest) / (MET - 1)`` over windows with MET >= 3
(clipped to [6, 18]), ``tau = 20 s``, ``drift = 12 bpm``.

Reset: each reset batch element draws a subject (uniformly from ``subjects``) and a start window (uniformly over
the recording, wrapping around at its end), and with ``gain_jitter`` j > 0 a factor ``U(1 - j, 1 + j)`` on the
subject's ``gain`` for the episode (domain randomisation for policies that must meet unseen subjects); heart rate,
fatigue and HRV start from the recording's values there, cumulative exertion and the episode metrics from 0.
``"_reset"`` masks (``[B, 1]``) reset only those elements.

IMU observation: the timeline's window, or (after Change) a random window of the new activity from the same subject,
with its movement scaled by the level: ``imu = posture + sqrt(level) (window - posture)`` where ``posture`` is the
subject's mean IMU vector for that activity (``level = 0`` shows a motionless subject).

Seeding: ``set_seed(s)`` / ``seed=s`` fixes all randomness of the env (subject/start draws, heart-rate noise, IMU
window draws); the synthetic data itself is fixed by ``data_seed``.

Planning (:class:`freamer_rl.health.oracle.OraclePlanner`): ``snapshot()`` / ``restore(state, index)`` copy the whole
simulator state, ``planning_copy(n)`` is a detached env over the same data; an optional ``"hr_noise"`` ``[B]`` entry
next to the action replaces the step's ``N(0, 1)`` draw (common random numbers). Without it nothing changes.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import types
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from freamer_rl.data import (
    ACTIVITY_GROUP_NAMES,
    MAX_ACTIVITY_ID,
    PROTOCOL_SUBJECTS,
    HRFeatureParams,
    group_table,
    met_table,
)
from freamer_rl_envs.health_dynamics import (  # noqa: F401  (HealthDynamics and the updates are re-exported)
    HealthDynamics,
    _load_tables,
    _SubjectTables,
    exertion,
    fatigue_update,
    hrv_update,
)

logger = logging.getLogger(__name__)

__all__ = [
    "ALERT",
    "CHANGE",
    "CHANGE_TO",
    "CONTINUE",
    "INCREASE",
    "REST",
    "DEFAULT_REWARD_WEIGHTS",
    "exertion",
    "fatigue_update",
    "hrv_update",
    "HEALTH_ACTIONS",
    "HEALTH_ENV_IDS",
    "VARIED_ENV_ID",
    "HealthDynamics",
    "HealthEnv",
    "make_health_env",
]

HEALTH_ACTIONS: tuple[str, ...] = ("continue", "rest", "increase", "change", "alert")
CONTINUE, REST, INCREASE, CHANGE, ALERT = range(5)
VARIED_ENV_ID = "pamap2-health-varied"  # synthetic subjects with their own activity plans (data.subject_profiles)
HEALTH_ENV_IDS: tuple[str, ...] = ("pamap2-health", "health", "pamap2", VARIED_ENV_ID)
DEFAULT_REWARD_WEIGHTS: tuple[float, float, float] = (2.0, 1.0, 0.5)

#: Activity the **Change** action switches to, by current activity id.
CHANGE_TO: dict[int, int] = {
    **dict.fromkeys((0, 1, 2, 3, 9, 10, 11), 4),  # transient, rest -> walking
    **dict.fromkeys((16, 17, 18, 19), 4),  # household -> walking
    **{4: 7, 7: 6, 6: 4},  # walking -> Nordic walking -> cycling -> walking
    **dict.fromkeys((12, 13), 4),  # stairs -> walking
    **{5: 6, 20: 7, 24: 4},  # running -> cycling, soccer -> Nordic walking, rope jumping -> walking
}


class HealthEnv(EnvBase):
    """Batched health-management env; build it with :func:`make_health_env` (module docstring: keys, equations)."""

    batch_locked = True

    def __init__(
        self,
        tables: _SubjectTables,
        *,
        batch_size: int = 1,
        episode_length: int = 240,
        reward_weights: Sequence[float] = DEFAULT_REWARD_WEIGHTS,
        dynamics: HealthDynamics | None = None,
        feature_params: HRFeatureParams | None = None,
        seed: int | None = None,
        device: torch.device | str = "cpu",
        gain_jitter: float = 0.0,
    ) -> None:
        if not 0.0 <= float(gain_jitter) < 1.0:
            raise ValueError(f"gain_jitter: expected a fraction in [0, 1), got {gain_jitter!r}")
        for name, value in (("batch_size", batch_size), ("episode_length", episode_length)):
            if int(value) != value or value < 1:
                raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
        weights = tuple(float(w) for w in reward_weights)
        if len(weights) != 3 or not all(math.isfinite(w) for w in weights):
            raise ValueError(
                f"reward_weights: expected 3 finite numbers (w_safe, w_target, w_fatigue), got {reward_weights!r}"
            )
        super().__init__(device=device, batch_size=torch.Size([int(batch_size)]))
        self.B = int(batch_size)
        self.episode_length = int(episode_length)
        self.reward_weights = weights
        self.gain_jitter = float(gain_jitter)
        self.dyn = dynamics or HealthDynamics()
        self.fp = feature_params or HRFeatureParams()
        self._tables = tables  # kept for planning_copy
        self.subjects = tables.subjects
        self.rate_hz = tables.rate_hz
        self.dt = 1.0 / tables.rate_hz
        self._bind_tables(tables)
        self._st = self._fresh_state()
        self._rng = torch.Generator(device=self.device)
        self._make_specs()
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.set_seed(int(seed))

    def _bind_tables(self, tables: _SubjectTables) -> None:
        """The subjects' timelines and the dynamics' constants as tensors on the env's device."""
        dev = self.device

        def t(x, dtype=None):
            return torch.as_tensor(x, dtype=dtype, device=dev)

        f32 = torch.float32
        self._imu = t(tables.imu, f32)
        self._act = t(tables.activity, torch.int64)
        self._hr_data = t(tables.hr, f32)
        self._fat_data = t(tables.fatigue, f32)
        self._hrv_data = t(tables.hrv_std, f32)
        self._len = t(tables.length, torch.int64)
        self._hr_rest = t(tables.hr_rest, f32)
        self._gain = t(tables.gain, f32)
        self._alpha = t(1.0 - np.exp(-self.dt / tables.tau), f32)
        self._drift = t(tables.drift, f32)
        self._posture = t(tables.posture, f32)
        self._pool = t(tables.pool, torch.int64)
        self._pool_n = t(tables.pool_n, torch.int64)
        self._met = t(met_table(), f32)
        self._group = t(group_table(), torch.int64)
        change = np.full(MAX_ACTIVITY_ID + 1, 4, np.int64)
        change[list(CHANGE_TO)] = list(CHANGE_TO.values())
        self._change = t(change, torch.int64)
        self._eye = torch.eye(len(ACTIVITY_GROUP_NAMES), device=dev, dtype=f32)
        self._hold_steps = max(1, int(round(self.dyn.alert_hold_s * self.rate_hz)))
        self._level_delta = t([0.0, -self.dyn.level_step, self.dyn.level_step, 0.0, 0.0], f32)
        self._noise_scale = self.dyn.hr_noise * math.sqrt(self.dt)
        # bucketize(right=True) counts edges <= HR; the last edge is nudged so that exactly 160 stays "vigorous"
        edges = list(self.fp.zone_edges)
        edges[2] = float(np.nextafter(np.float32(edges[2]), np.float32(np.inf)))
        self._zone_edges = t(edges, f32)

    def _fresh_state(self) -> types.SimpleNamespace:
        """Mutable per-element state ``[B]``, in a plain namespace (nn.Module.__setattr__ is slow on the hot path)."""
        B, dev, f32 = self.B, self.device, torch.float32
        z = functools.partial(torch.zeros, B, device=dev)
        return types.SimpleNamespace(
            subject_index=z(dtype=torch.int64),  # index into self.subjects
            cursor=z(dtype=torch.int64),  # window index in the subject's timeline
            planned=z(dtype=torch.int64),  # timeline activity at the cursor
            override=torch.full((B,), -1, dtype=torch.int64, device=dev),  # activity chosen by Change, -1 none
            level=torch.ones(B, device=dev),
            hold=z(dtype=torch.int64),  # remaining steps of an Alert stop
            hr=z(dtype=f32),
            fatigue=z(dtype=f32),
            hrv_mean=z(dtype=f32),
            hrv_var=z(dtype=f32),
            roc=z(dtype=f32),
            cum=z(dtype=f32),
            steps=z(dtype=torch.int64),
            ep_return=z(dtype=f32),
            ep_viol=z(dtype=torch.int64),
            hr_rest=z(dtype=f32),
            gain=z(dtype=f32),
            alpha=z(dtype=f32),
            drift=z(dtype=f32),
            length=torch.ones(B, dtype=torch.int64, device=dev),
        )

    # ------------------------------------------------------------------------------------------------------------------
    def _make_specs(self) -> None:
        B, dev = self.B, self.device
        self.observation_spec = Composite(
            imu=Unbounded(shape=(B, 36), dtype=torch.float32, device=dev),
            hr_features=Unbounded(shape=(B, 16), dtype=torch.float32, device=dev),
            heart_rate=Unbounded(shape=(B, 1), dtype=torch.float32, device=dev),
            activity=Categorical(MAX_ACTIVITY_ID + 1, shape=(B,), dtype=torch.int64, device=dev),
            level=Unbounded(shape=(B, 1), dtype=torch.float32, device=dev),
            episode=Composite(
                {
                    "return": Unbounded(shape=(B, 1), dtype=torch.float32, device=dev),
                    "violations": Unbounded(shape=(B, 1), dtype=torch.int64, device=dev),
                    "length": Unbounded(shape=(B, 1), dtype=torch.int64, device=dev),
                },
                shape=(B,),
            ),
            shape=(B,),
        )
        self.action_spec = Categorical(len(HEALTH_ACTIONS), shape=(B,), dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(B, 1), dtype=torch.float32, device=dev)
        flag = functools.partial(Categorical, 2, shape=(B, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=(B,))

    # ------------------------------------------------------------------------------------------------------------------
    def _effective_activity(self) -> torch.Tensor:
        st = self._st
        return torch.where(st.override >= 0, st.override, st.planned)

    def _observation(self) -> dict[str, Any]:
        st, p = self._st, self.fp
        s = st.subject_index
        act = self._effective_activity()
        row = self._imu[s, st.cursor]
        use_alt = st.override >= 0
        if bool(use_alt.any()):
            n = self._pool_n[s, act]
            draw = (torch.rand(self.B, generator=self._rng, device=self.device) * n.clamp_min(1)).long()
            alt_row = self._imu[s, self._pool[s, act, draw]]
            row = torch.where((use_alt & (n > 0))[:, None], alt_row, row)
        posture = self._posture[s, act]
        imu = torch.addcmul(posture, st.level.sqrt()[:, None], row - posture)

        hr = st.hr
        met_eff = (self._met[act] - 1.0) * st.level + 1.0
        scalars = torch.stack(
            [
                torch.bucketize(hr, self._zone_edges, right=True) / 3.0,
                exertion(hr, st.hr_rest, p),
                st.fatigue,
                (st.hrv_var.clamp_min(0.0).sqrt() / p.hrv_scale).clamp_max(p.hrv_max),
                (st.roc / p.roc_scale).clamp(-p.roc_max, p.roc_max),
                st.cum / p.cum_scale_s,
                met_eff / p.met_scale,
            ],
            dim=1,
        )
        feats = torch.cat([hr[:, None] / p.hr_scale, self._eye[self._group[act]], scalars], dim=1)
        episode = {
            "return": st.ep_return[:, None].clone(),
            "violations": st.ep_viol[:, None].clone(),
            "length": st.steps[:, None].clone(),
        }
        return {
            "imu": imu,
            "hr_features": feats,
            "heart_rate": hr[:, None].clone(),
            "activity": act,
            "level": st.level[:, None].clone(),
            "episode": episode,
        }

    def _to_td(self, out: dict[str, Any]) -> TensorDictBase:
        # shapes are fixed by construction: skip TensorDict's per-entry validation (a third of the step time)
        out["episode"] = TensorDict._new_unsafe(out["episode"], batch_size=self.batch_size, device=self.device)
        return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)

    # read-only views of the state (for tests, plots and wrappers)
    @property
    def subject_index(self) -> torch.Tensor:
        """int64 ``[B]``: index into :attr:`subjects` of each element's subject."""
        return self._st.subject_index.clone()

    @property
    def cursor(self) -> torch.Tensor:
        """int64 ``[B]``: current window of each element in its subject's timeline."""
        return self._st.cursor.clone()

    @property
    def level(self) -> torch.Tensor:
        """float32 ``[B]``: intensity level set by the interventions (1 = as planned)."""
        return self._st.level.clone()

    @property
    def fatigue(self) -> torch.Tensor:
        """float32 ``[B]``: fatigue state ``F``."""
        return self._st.fatigue.clone()

    # ------------------------------------------------------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        B, dev, st = self.B, self.device, self._st
        mask = None if tensordict is None else tensordict.get("_reset", None)
        s = torch.randint(len(self.subjects), (B,), generator=self._rng, device=dev)
        cur = (torch.rand(B, generator=self._rng, device=dev) * self._len[s]).long()
        hr0 = self._hr_data[s, cur]
        gain = self._gain[s]
        if self.gain_jitter > 0.0:  # a config constant: gain_jitter 0 draws nothing, so its episodes stay the same
            gain = gain * (1.0 + self.gain_jitter * (2.0 * torch.rand(B, generator=self._rng, device=dev) - 1.0))
        new = {
            "subject_index": s,
            "cursor": cur,
            "planned": self._act[s, cur],
            "override": torch.full_like(st.override, -1),
            "level": torch.ones_like(st.level),
            "hold": torch.zeros_like(st.hold),
            "hr": hr0,
            "fatigue": self._fat_data[s, cur],
            "hrv_mean": hr0,
            "hrv_var": self._hrv_data[s, cur] ** 2,
            "roc": torch.zeros_like(st.roc),
            "cum": torch.zeros_like(st.cum),
            "steps": torch.zeros_like(st.steps),
            "ep_return": torch.zeros_like(st.ep_return),
            "ep_viol": torch.zeros_like(st.ep_viol),
            # per-element copies of the subject constants (saves gathers on every step)
            "hr_rest": self._hr_rest[s],
            "gain": gain,
            "alpha": self._alpha[s],
            "drift": self._drift[s],
            "length": self._len[s],
        }
        if mask is None:
            for name, value in new.items():
                setattr(st, name, value)
        else:
            m = mask.reshape(B).to(dev)
            for name, value in new.items():
                setattr(st, name, torch.where(m, value, getattr(st, name)))
        out = self._observation()
        false = torch.zeros(B, 1, dtype=torch.bool, device=dev)
        out.update(done=false, terminated=false.clone(), truncated=false.clone())
        return self._to_td(out)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        dyn, p, dt, st = self.dyn, self.fp, self.dt, self._st
        B, dev = self.B, self.device
        a = tensordict.get("action").reshape(B).long()
        hr_before = st.hr

        # 1. the intervention: Rest / Increase move the level, Change switches activity, Alert stops
        level = (st.level + self._level_delta[a]).clamp(0.0, dyn.level_max)
        is_change = a == CHANGE
        is_alert = a == ALERT
        st.override = torch.where(is_change, self._change[self._effective_activity()], st.override)
        level = level.masked_fill(is_change, 1.0).masked_fill(is_alert, 0.0)
        st.hold = st.hold.masked_fill(is_alert, self._hold_steps)
        st.level = torch.where(st.hold > 0, level.clamp_max(dyn.alert_level_cap), level)

        # 2-4. physiology over [t, t + dt): first-order heart-rate lag, fatigue, HRV, rate of change
        met_eff = (self._met[self._effective_activity()] - 1.0) * st.level
        hr_ss = st.hr_rest + st.gain * met_eff + st.drift * st.fatigue
        noise = tensordict.get("hr_noise", None)  # planning with common random numbers (freamer_rl.health.oracle)
        if noise is None:
            noise = torch.randn(B, generator=self._rng, device=dev)
        elif noise.shape != (B,):
            raise ValueError(
                f"hr_noise: expected shape ({B},) (one N(0, 1) draw per element), got {tuple(noise.shape)}"
            )
        hr = (hr_before + st.alpha * (hr_ss - hr_before) + self._noise_scale * noise).clamp(dyn.hr_min, dyn.hr_clip_max)
        e = exertion(hr, st.hr_rest, p)
        st.fatigue = fatigue_update(st.fatigue, e, dt, p)
        st.hrv_mean, st.hrv_var = hrv_update(st.hrv_mean, st.hrv_var, hr, dt, p)
        st.roc = (hr - hr_before) / dt
        st.cum = st.cum + e * dt
        st.hr = hr

        # reward of this step (Eq. A11)
        target = (st.hr_rest + st.gain * (self._met[st.planned] - 1.0)).clamp_max(dyn.hr_target_cap)
        danger = hr > dyn.hr_danger
        terminated = hr >= dyn.hr_critical
        r_safe = -(
            danger * (1.0 + (hr - dyn.hr_danger) / dyn.danger_slope)
            + dyn.alert_cost * (is_alert & (hr_before <= dyn.hr_danger))
            + dyn.termination_penalty * terminated
        )
        r_target = torch.exp(-0.5 * ((hr - target) / dyn.target_sigma) ** 2)
        w_safe, w_target, w_fatigue = self.reward_weights
        reward = w_safe * r_safe + w_target * r_target - w_fatigue * st.fatigue

        # 5. the timeline moves on; a new activity segment restores the planned intensity
        st.steps = st.steps + 1
        st.cursor = (st.cursor + 1) % st.length
        new_planned = self._act[st.subject_index, st.cursor]
        boundary = new_planned != st.planned
        st.planned = new_planned
        st.level = st.level.masked_fill(boundary, 1.0)
        st.override = st.override.masked_fill(boundary, -1)
        st.hold = (st.hold - 1).clamp_min(0)
        st.level = torch.where(st.hold > 0, st.level.clamp_max(dyn.alert_level_cap), st.level)  # stop persists

        st.ep_return = st.ep_return + reward
        st.ep_viol = st.ep_viol + danger
        truncated = st.steps >= self.episode_length
        out = self._observation()
        out["reward"] = reward[:, None]
        out["terminated"] = terminated[:, None]
        out["truncated"] = truncated[:, None]
        out["done"] = (terminated | truncated)[:, None]
        return self._to_td(out)

    # planning seam (freamer_rl.health.oracle): the whole simulator state is the [B] tensors of self._st + self._rng
    def snapshot(self) -> dict[str, Any]:
        """Copies of the simulator state: every per-element field (``[B]`` tensors) and ``"rng_state"``."""
        return {**{k: v.clone() for k, v in vars(self._st).items()}, "rng_state": self._rng.get_state()}

    def restore(self, state: Mapping[str, Any], index: torch.Tensor | None = None) -> None:
        """Load a :meth:`snapshot` (of this env, or of another over the same data): element ``i`` takes row
        ``index[i]`` of every field (int64 ``[B]``; ``None``: row ``i``, and the generator state is restored too)."""
        missing = sorted(set(vars(self._st)) - set(state))
        if missing:
            raise KeyError(f"restore: state lacks {missing}")
        if index is not None and (index.dtype != torch.int64 or tuple(index.shape) != (self.B,)):
            raise ValueError(
                f"restore: index must be int64 of shape ({self.B},), got {index.dtype} {tuple(index.shape)}"
            )
        new = {}
        for name, old in vars(self._st).items():  # every field checked before any is replaced
            value = state[name].to(self.device)
            new[name] = value = value.clone() if index is None else value[index]
            if value.shape != old.shape or value.dtype != old.dtype:
                raise ValueError(
                    f"restore: {name!r} must be {old.dtype} {tuple(old.shape)}, got {value.dtype} {tuple(value.shape)}"
                )
        vars(self._st).update(new)
        if index is None and "rng_state" in state:
            self._rng.set_state(state["rng_state"])

    def planning_copy(self, batch_size: int, *, hr_noise: float | None = None, seed: int = 0) -> HealthEnv:
        """A detached env over the same data, constants and reward (its own state and generator, seeded by
        ``seed``), batch ``[batch_size]``; ``hr_noise`` replaces :attr:`HealthDynamics.hr_noise` (0: noise-free)."""
        dyn = self.dyn if hr_noise is None else dataclasses.replace(self.dyn, hr_noise=float(hr_noise))
        return HealthEnv(
            self._tables,
            batch_size=batch_size,
            episode_length=self.episode_length,
            reward_weights=self.reward_weights,
            dynamics=dyn,
            feature_params=self.fp,
            seed=seed,
            device=self.device,
            gain_jitter=self.gain_jitter,
        )

    def _set_seed(self, seed: int | None) -> None:
        """Seed the env's generator (``None``: draw a seed from torch's global generator)."""
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self._rng.manual_seed(int(seed))

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(subjects={list(self.subjects)}, batch_size={self.B}, "
            f"episode_length={self.episode_length}, rate_hz={self.rate_hz:g}, reward_weights={self.reward_weights}, "
            f"device={self.device})"
        )


def make_health_env(
    env_id: str | None = None,
    *,
    data_dir: str | None = None,
    subjects: Iterable[int] | None = None,
    batch_size: int = 1,
    episode_length: int = 240,
    seed: int | None = None,
    reward_weights: Sequence[float] = DEFAULT_REWARD_WEIGHTS,
    device: torch.device | str = "cpu",
    rate_hz: float = 1.0,
    synthetic_duration_s: float = 1800.0,
    data_seed: int = 0,
    dynamics: HealthDynamics | None = None,
    gain_jitter: float = 0.0,
) -> HealthEnv:
    """Build a batched :class:`HealthEnv` (``batch_size=[batch_size]``).

    Args:
        env_id: optional, for the ``factory(env_id, *, seed, **options)`` adapter convention; one of
            :data:`HEALTH_ENV_IDS` or ``None``; :data:`VARIED_ENV_ID`: synthetic subjects with their own activity
            plans (:mod:`freamer_rl.data.subject_profiles`, the same physiology), refused with ``data_dir``.
        data_dir: PAMAP2 root (holding ``Protocol/``) or the ``Protocol`` folder; ``None`` = synthetic subjects
            (:func:`freamer_rl.data.synthetic_recording`, ``synthetic_duration_s`` each, fixed by
            ``data_seed``).
        subjects: subject numbers (101-109); ``None`` = all files found (real) or 101, 102, 103 (synthetic).
        batch_size: number of simultaneous subjects/episodes.
        episode_length: truncation horizon in steps (240 steps = 4 min at 1 Hz).
        seed: seeds the env's generator (``None`` draws one from torch's global generator).
        reward_weights: ``(w_safe, w_target, w_fatigue)`` of Eq. A11, default ``(2.0, 1.0, 0.5)``.
        device: device of the env's tensors.
        rate_hz: steps per second (the 100 Hz data is windowed; 1 Hz default, 10 Hz for finer control; the
            health recipes use 0.2 Hz so that a 15-step imagination spans the heart-rate dynamics).
        dynamics: :class:`HealthDynamics` constants.
        gain_jitter: domain randomisation of the physiology: each reset scales its subject's heart-rate ``gain``
            (bpm per MET) by ``U(1 - j, 1 + j)`` for that episode (the target heart rate follows), so a policy
            trains on fitter and less fit versions of its subjects; 0 (default): the subject's own gain, and no
            extra random draw (the same episodes as before the option existed).

    Raises:
        ValueError: unknown ``env_id``, bad ``subjects`` / ``batch_size`` / ``episode_length`` / ``reward_weights``.
        freamer_rl.data.Pamap2FormatError: missing or malformed PAMAP2 files.
    """
    if env_id is not None and env_id.lower() not in HEALTH_ENV_IDS:
        raise ValueError(f"unknown health env id {env_id!r}; valid ids: {', '.join(HEALTH_ENV_IDS)} (or None)")
    if (varied := env_id is not None and env_id.lower() == VARIED_ENV_ID) and data_dir is not None:
        raise ValueError(f"env id {VARIED_ENV_ID!r} is for synthetic subjects; data_dir {str(data_dir)!r} is real data")
    subj: tuple[int, ...] | None = None
    if subjects is not None:
        subj = tuple(sorted({int(x) for x in subjects}))
        if not subj or any(x not in PROTOCOL_SUBJECTS for x in subj):
            raise ValueError(f"subjects: expected numbers in 101..109, got {subjects!r}")
    dyn = dynamics or HealthDynamics()
    tables = _load_tables(
        None if data_dir is None else str(data_dir),
        subj,
        float(rate_hz),
        float(synthetic_duration_s),
        int(data_seed),
        dyn,
        varied,
    )
    return HealthEnv(
        tables,
        batch_size=batch_size,
        episode_length=episode_length,
        reward_weights=reward_weights,
        dynamics=dyn,
        seed=seed,
        device=device,
        gain_jitter=gain_jitter,
    )
