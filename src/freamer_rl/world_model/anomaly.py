"""Physiological anomaly detection from the world model's surprise (paper Appendix J.5).

The per-step ``KL(q(z_t | h_t, o_t) || p(z_t | h_t))`` measures how far the observation departs from what the
world model predicted. A step is an anomaly candidate when ``KL_t > mu_D + k sigma_D`` (``k = 2``), with ``mu_D`` and
``sigma_D`` the running mean and standard deviation of the KL values (``statistic="running"``, Welford over the
whole stream) or their exponentially weighted versions (``statistic="ema"``, half-life in steps: follows slow
changes of the baseline over a long scenario).

* :class:`KLAnomalyDetector` -- the running statistics and the flag (plain module, streams of any batch shape).
* :class:`KLAnomalyTransform` -- online use inside a TorchRL env: filters the posterior each step, writes ``"kl"``
  and ``"anomaly"``.
* :func:`detect_anomalies` -- the same over a recorded KL sequence (e.g. :meth:`WorldModel.episode_kl`).
* :func:`plot_anomaly_timeline` -- the paper's Fig. 4 style picture.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs.transforms import Transform

from freamer_rl.world_model.encoder import StepEncoder
from freamer_rl.world_model.functional import gaussian_kl
from freamer_rl.world_model.rssm import WorldModel

logger = logging.getLogger(__name__)

__all__ = [
    "KLAnomalyDetector",
    "KLAnomalyTransform",
    "detect_anomalies",
    "anomaly_statistic",
    "plot_anomaly_timeline",
    "STATISTICS",
    "DEFAULT_EMA_HALFLIFE",
    "DEFAULT_HR_ZONES",
    "DEFAULT_ACTION_NAMES",
    "DANGER_HR",
]

#: (name, low bpm, high bpm, colour) -- edges as in ``freamer_rl.data`` (110 / 135 / 160; danger > 160).
DEFAULT_HR_ZONES: tuple[tuple[str, float, float, str], ...] = (
    ("Light", 0.0, 110.0, "#d8f0d2"),
    ("Moderate", 110.0, 135.0, "#fff2b3"),
    ("Vigorous", 135.0, 160.0, "#ffd1a3"),
    ("Danger", 160.0, math.inf, "#f7a6a6"),
)
#: Heart rate above which a step is in the danger zone (bpm): the lower edge of the last zone.
DANGER_HR: float = DEFAULT_HR_ZONES[-1][1]
#: The detector's statistics: exact running (Welford) mean/std, or exponentially weighted ones.
STATISTICS: tuple[str, ...] = ("running", "ema")
#: Default EMA half-life in steps (720 = one hour at the health recipes' 0.2 Hz).
DEFAULT_EMA_HALFLIFE: float = 720.0
#: The health env's actions, in index order (Appendix C).
DEFAULT_ACTION_NAMES: tuple[str, ...] = ("Continue", "Rest", "Increase", "Change", "Alert")


class KLAnomalyDetector(nn.Module):
    """Running mean/std of per-step KL values and the ``KL > mean + k_sigma * std`` flag (J.5).

    Args:
        k_sigma: number of standard deviations (2.0 in J.5).
        warmup: no step is flagged before a stream has ``warmup`` values in its statistics (the first estimates
            are too noisy to threshold against).
        momentum: ``None`` (default) for exact Welford running statistics over the whole stream; a float in
            ``(0, 1]`` for exponential moving statistics (``mean <- mean + m (x - mean)``, ``var <- (1 - m)
            (var + m (x - mean)^2)``) that follow slow drifts (e.g. over a 48-hour scenario).
        min_std: floor of the std in the threshold, so that a constant signal's numerical jitter is not flagged.
        statistic: ``"running"`` (Welford, unless ``momentum`` is given) or ``"ema"`` (exponential statistics
            with ``m = 1 - 2^(-1 / halflife)``: a value's weight halves every ``halflife`` steps).
        halflife: EMA half-life in steps (default :data:`DEFAULT_EMA_HALFLIFE`); only with ``statistic="ema"``.

    Each call of :meth:`update` with ``kl [*B]`` treats every element as an independent stream (one per env in a
    batch); the statistics take that shape on the first call. The flag of a value is decided against the
    statistics *before* it is included (a spike does not raise its own threshold), then the value is included.
    """

    def __init__(
        self,
        k_sigma: float = 2.0,
        warmup: int = 20,
        momentum: float | None = None,
        min_std: float = 1e-4,
        *,
        statistic: str = "running",
        halflife: float | None = None,
    ) -> None:
        super().__init__()
        if statistic not in STATISTICS:
            raise ValueError(f"statistic: expected one of {', '.join(STATISTICS)}, got {statistic!r}")
        if halflife is not None and statistic != "ema":
            raise ValueError(f"halflife: only used with statistic='ema', got statistic={statistic!r}")
        if statistic == "ema":
            if momentum is not None:
                raise ValueError("momentum: give either momentum or statistic='ema' with a halflife, not both")
            halflife = DEFAULT_EMA_HALFLIFE if halflife is None else float(halflife)
            if not (halflife > 0 and math.isfinite(halflife)):
                raise ValueError(f"halflife: expected a finite number of steps > 0, got {halflife!r}")
            momentum = 1.0 - 0.5 ** (1.0 / halflife)
        if momentum is not None and not 0.0 < momentum <= 1.0:
            raise ValueError(f"momentum: expected None or a float in (0, 1], got {momentum}")
        if warmup < 2:
            raise ValueError(f"warmup: expected >= 2 (a std needs two values), got {warmup}")
        self.statistic = "ema" if momentum is not None else "running"
        self.halflife = halflife
        self.k_sigma = k_sigma
        self.warmup = warmup
        self.momentum = momentum
        self.min_std = min_std
        self.register_buffer("count", None)
        self.register_buffer("mean", None)
        self.register_buffer("m2", None)  # Welford: sum of squared deviations; EMA: variance

    def reset(self) -> None:
        """Forget the statistics."""
        self.count = self.mean = self.m2 = None

    @property
    def std(self) -> torch.Tensor:
        """Current running std ``[*B]`` (zeros before two values)."""
        if self.count is None:
            raise RuntimeError("KLAnomalyDetector.std: no value seen yet")
        if self.momentum is not None:
            return self.m2.clamp(min=0).sqrt()
        return (self.m2 / (self.count - 1).clamp(min=1)).clamp(min=0).sqrt()

    @property
    def threshold(self) -> torch.Tensor:
        """``mean + k_sigma * max(std, min_std)`` of shape ``[*B]``."""
        return self.mean + self.k_sigma * self.std.clamp(min=self.min_std)

    @torch.no_grad()
    def update(self, kl: torch.Tensor, include: torch.Tensor | None = None) -> torch.Tensor:
        """Flag ``kl [*B]`` against the current statistics, then include it. Returns bool ``[*B]``.

        ``include`` (bool ``[*B]``, default all True): where False the value is neither flagged nor added to the
        statistics (e.g. the first step after a filter reset, whose KL starts from the zero state). No host sync.
        """
        kl = kl.detach().float()
        if self.count is None:
            self.count = torch.zeros(kl.shape, dtype=torch.long, device=kl.device)
            self.mean = torch.zeros_like(kl)
            self.m2 = torch.zeros_like(kl)
        elif self.count.shape != kl.shape:
            raise ValueError(
                f"kl: expected shape {tuple(self.count.shape)} (the streams seen so far), "
                f"got {tuple(kl.shape)}; call reset() to start new streams"
            )
        flags = (self.count >= self.warmup) & (kl > self.threshold)
        delta = kl - self.mean
        if self.momentum is None:
            count = self.count + 1
            mean = self.mean + delta / count
            m2 = self.m2 + delta * (kl - mean)
        else:
            first = self.count == 0
            m = self.momentum
            mean = torch.where(first, kl, self.mean + m * delta)
            m2 = torch.where(first, torch.zeros_like(kl), (1 - m) * (self.m2 + m * delta.pow(2)))
            count = self.count + 1
        if include is None:
            self.count, self.mean, self.m2 = count, mean, m2
            return flags
        inc = include.to(device=kl.device, dtype=torch.bool).expand(kl.shape)
        self.count = torch.where(inc, count, self.count)
        self.mean = torch.where(inc, mean, self.mean)
        self.m2 = torch.where(inc, m2, self.m2)
        return flags & inc

    forward = update


@torch.no_grad()
def anomaly_statistic(
    kl: torch.Tensor,
    k_sigma: float = 2.0,
    warmup: int = 20,
    momentum: float | None = None,
    min_std: float = 1e-4,
    *,
    statistic: str = "running",
    halflife: float | None = None,
    include: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Stream a recorded KL sequence ``[*B, T]`` (time last) through a fresh :class:`KLAnomalyDetector`.

    ``include`` (bool ``[*B, T]``): steps to leave out of the flags and the statistics (see
    :meth:`KLAnomalyDetector.update`). Returns ``[*B, T]`` tensors: ``flags`` (bool), ``threshold`` (``mean + k
    max(std, min_std)`` in force at the step, NaN during warm-up), ``mean``, ``std`` (before the step, NaN during
    warm-up) and ``z = (KL - mean) / max(std, min_std)`` (the detector's score: flagged iff ``z > k``; NaN during
    warm-up and where ``include`` is False).
    """
    det = KLAnomalyDetector(k_sigma, warmup, momentum, min_std, statistic=statistic, halflife=halflife)
    if det.statistic == "running":
        return _running_statistic(kl, k_sigma, warmup, min_std, include)
    flags, mean, std = [], [], []
    nan = torch.full_like(kl[..., 0], float("nan"))
    for t in range(kl.shape[-1]):
        x = kl[..., t]
        inc = None if include is None else include[..., t]
        if det.count is not None:
            ready = det.count >= warmup
            mean.append(torch.where(ready, det.mean, nan))
            std.append(torch.where(ready, det.std.clamp(min=min_std), nan))
        else:
            mean.append(nan)
            std.append(nan)
        flags.append(det.update(x, inc))
    mean_t, std_t = torch.stack(mean, -1), torch.stack(std, -1)
    z = (kl.float() - mean_t) / std_t
    if include is not None:
        z = z.masked_fill(~include.bool(), float("nan"))
    return {
        "flags": torch.stack(flags, -1),
        "threshold": mean_t + k_sigma * std_t,
        "mean": mean_t,
        "std": std_t,
        "z": z,
    }


def _running_statistic(
    kl: torch.Tensor, k_sigma: float, warmup: int, min_std: float, include: torch.Tensor | None
) -> dict[str, torch.Tensor]:
    """:func:`anomaly_statistic` with the running (Welford) statistic in closed form over the time axis: the mean
    and sample std of the included values before each step from prefix sums in float64 (no per-step loop; a 48-hour
    scenario is 34,560 steps). The same flags as streaming :class:`KLAnomalyDetector` up to float32 rounding."""
    x = kl.detach().double()
    inc = torch.ones_like(x, dtype=torch.bool) if include is None else include.to(torch.bool).expand(x.shape)
    xi = torch.where(inc, x, torch.zeros_like(x))
    count = torch.cumsum(inc.long(), -1) - inc.long()  # included values before the step
    s1 = torch.cumsum(xi, -1) - xi
    s2 = torch.cumsum(xi * xi, -1) - xi * xi
    n = count.clamp(min=1).double()
    mean = s1 / n
    var = ((s2 - s1 * mean) / (count - 1).clamp(min=1).double()).clamp(min=0)
    ready = count >= warmup
    nan = torch.full_like(x, float("nan"))
    mean_t = torch.where(ready, mean, nan).float()
    std_t = torch.where(ready, var.sqrt().clamp(min=min_std), nan).float()
    threshold = mean_t + k_sigma * std_t
    z = (kl.float() - mean_t) / std_t
    if include is not None:
        z = z.masked_fill(~inc, float("nan"))
    return {
        "flags": ready & inc & (kl.float() > threshold),
        "threshold": threshold,
        "mean": mean_t,
        "std": std_t,
        "z": z,
    }


@torch.no_grad()
def detect_anomalies(
    kl: torch.Tensor,
    k_sigma: float = 2.0,
    warmup: int = 20,
    momentum: float | None = None,
    min_std: float = 1e-4,
    *,
    statistic: str = "running",
    halflife: float | None = None,
    include: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Stream a recorded KL sequence ``[*B, T]`` (time last) through a fresh :class:`KLAnomalyDetector`.

    Returns ``(flags bool [*B, T], threshold [*B, T])`` -- the threshold in force at each step (NaN during warm-up).
    :func:`anomaly_statistic` gives the z-score and the statistics too.
    """
    out = anomaly_statistic(
        kl, k_sigma, warmup, momentum, min_std, statistic=statistic, halflife=halflife, include=include
    )
    return out["flags"], out["threshold"]


class KLAnomalyTransform(Transform):
    """Online KL anomaly monitor for a TorchRL env (J.5).

    Each step it filters the world model's posterior with the new observation -- ``(h, z)`` carried in the
    tensordict under ``deter_key``/``stoch_key`` (root = before the step, ``("next", ...)`` = after; ``step_mdp``
    moves it) -- computes ``KL(q || p)`` of that step and writes ``kl_key`` (float ``[*B, 1]``) and ``anomaly_key``
    (bool ``[*B, 1]``) from :class:`KLAnomalyDetector`. The observations are embedded with the encoder's online step
    (:class:`~freamer_rl.world_model.encoder.StepEncoder`: every health encoder, the recurrent foundation encoder
    included, and the default MLP encoder); a recurrent encoder's state (e.g. the DNC memory ``[*B, N, W]``) is
    carried like ``(h, z)`` under ``(*enc_state_key, name)``.

    At reset the posterior is computed from the zero state with the first observation (``is_first``); that KL is
    written but neither flagged nor added to the statistics (a fresh episode is not a surprise). The statistics
    run per env (batch element) across episodes; no step is flagged before ``detector.warmup`` steps of that env.

    Args:
        world_model: the trained :class:`WorldModel` (used under ``no_grad``; share it with the learner to follow
            its updates). Its encoder must implement :class:`~freamer_rl.world_model.encoder.StepEncoder`.
        action_key: the action at the root of the step tensordict.
        detector: a :class:`KLAnomalyDetector` (default ``KLAnomalyDetector()``: k=2, warm-up 20, Welford).
        sample: feed posterior samples (True) or means (False, default, deterministic) forward.
    """

    def __init__(
        self,
        world_model: WorldModel,
        *,
        action_key: NestedKey = "action",
        kl_key: NestedKey = "kl",
        anomaly_key: NestedKey = "anomaly",
        deter_key: NestedKey = ("kl_filter", "deter"),
        stoch_key: NestedKey = ("kl_filter", "stoch"),
        enc_state_key: NestedKey = ("kl_filter", "enc"),
        detector: KLAnomalyDetector | None = None,
        sample: bool = False,
    ) -> None:
        enc = world_model.encoder
        if not isinstance(enc, StepEncoder):
            raise TypeError(
                f"KLAnomalyTransform: the world model's encoder {type(enc).__name__} does not implement "
                "freamer_rl.world_model.encoder.StepEncoder (online step API)"
            )
        root = enc_state_key if isinstance(enc_state_key, tuple) else (enc_state_key,)
        self.enc_keys = {n: (*root, n) for n in enc.state_shapes()}
        super().__init__(in_keys=[], out_keys=[kl_key, anomaly_key, deter_key, stoch_key, *self.enc_keys.values()])
        self.world_model = world_model
        self.action_key = action_key
        self.kl_key, self.anomaly_key = kl_key, anomaly_key
        self.deter_key, self.stoch_key = deter_key, stoch_key
        self.detector = detector if detector is not None else KLAnomalyDetector()
        self.sample = sample

    def _filter(self, obs_td: TensorDictBase, h, z, action, is_first, enc_state) -> tuple[torch.Tensor, ...]:
        wm = self.world_model
        enc = wm.encoder
        embed, enc_state = enc.step({k: obs_td.get(k) for k in enc.obs_keys}, enc_state, is_first)
        out = wm.rssm.obs_step(h, z, action, embed, is_first=is_first, sample=self.sample)
        kl = gaussian_kl(out["post_mean"], out["post_std"], out["prior_mean"], out["prior_std"])
        return out["h"], out["z"], kl, enc_state

    def _write_state(self, td: TensorDictBase, h, z, enc_state) -> None:
        td.set(self.deter_key, h)
        td.set(self.stoch_key, z)
        for n, k in self.enc_keys.items():
            td.set(k, enc_state[n])

    @torch.no_grad()
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        wm = self.world_model
        bs = tensordict_reset.batch_size
        ref = tensordict_reset.get(next(iter(wm.obs_dims)))
        h, z = wm.rssm.initial_state(bs, device=ref.device, dtype=torch.float32)
        a = torch.zeros(*bs, wm.action_dim, device=ref.device)
        first = torch.ones(bs, dtype=torch.bool, device=ref.device)
        enc_state = wm.encoder.initial_state(bs, device=ref.device)
        h, z, kl, enc_state = self._filter(tensordict_reset, h, z, a, first, enc_state)
        self._write_state(tensordict_reset, h, z, enc_state)
        tensordict_reset.set(self.kl_key, kl.unsqueeze(-1))
        tensordict_reset.set(self.anomaly_key, torch.zeros(*bs, 1, dtype=torch.bool, device=ref.device))
        return tensordict_reset

    @torch.no_grad()
    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        for k in (self.deter_key, self.stoch_key, *self.enc_keys.values()):
            if k not in tensordict.keys(True, True):
                raise KeyError(f"KLAnomalyTransform: {k!r} missing from the step input; reset the env first")
        wm = self.world_model
        h = tensordict.get(self.deter_key)
        z = tensordict.get(self.stoch_key)
        enc_state = {n: tensordict.get(k) for n, k in self.enc_keys.items()}
        a = wm.action_to_onehot(tensordict.get(self.action_key), tensordict.batch_dims)
        h, z, kl, enc_state = self._filter(next_tensordict, h, z, a, None, enc_state)
        flags = self.detector.update(kl)
        self._write_state(next_tensordict, h, z, enc_state)
        next_tensordict.set(self.kl_key, kl.unsqueeze(-1))
        next_tensordict.set(self.anomaly_key, flags.unsqueeze(-1))
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError(
            "KLAnomalyTransform works inside an env (reset/step). For recorded data use "
            "WorldModel.episode_kl(episode) and detect_anomalies(kl)."
        )

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        bs = observation_spec.shape
        dev = observation_spec.device
        wm = self.world_model
        observation_spec.set(self.kl_key, Unbounded((*bs, 1), device=dev))
        observation_spec.set(self.anomaly_key, Categorical(2, (*bs, 1), dtype=torch.bool, device=dev))
        observation_spec.set(self.deter_key, Unbounded((*bs, wm.deter_dim), device=dev))
        observation_spec.set(self.stoch_key, Unbounded((*bs, wm.stoch_dim), device=dev))
        for n, shape in wm.encoder.state_shapes().items():
            observation_spec.set(self.enc_keys[n], Unbounded((*bs, *shape), device=dev))
        return observation_spec


def _np(x):
    """Tensor or array-like -> flat numpy array."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().reshape(-1).numpy()
    return np.asarray(x).reshape(-1)


def _action_strip(ax, x, act, action_names: Sequence[str]) -> None:
    """The agent's decisions ``act [T]`` as one coloured strip on ``ax`` with a legend of ``action_names``."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    T = act.shape[0]
    n_act = max(len(action_names), int(act.max()) + 1 if T else 1)
    base = ["#4c78a8", "#54a24b", "#f58518", "#b279a2", "#e45756", "#72b7b2", "#9d755d"]
    cmap = ListedColormap([base[i % len(base)] for i in range(n_act)])
    extent = (x[0], x[-1] if T > 1 else x[0] + 1, 0, 1)
    ax.imshow(
        act[None, :], aspect="auto", cmap=cmap, vmin=-0.5, vmax=n_act - 0.5, extent=extent, interpolation="nearest"
    )
    ax.set_yticks([])
    ax.set_ylabel("action", rotation=0, ha="right", va="center")
    names = list(action_names) + [str(i) for i in range(len(action_names), n_act)]
    ax.legend(
        handles=[Patch(color=cmap(i), label=names[i]) for i in range(n_act)],
        loc="upper center",
        bbox_to_anchor=(0.5, -0.05),
        ncol=n_act,
        fontsize=8,
        frameon=False,
    )


_KIND_COLOURS = ("#9467bd", "#17becf", "#bcbd22", "#8c564b", "#e377c2", "#7f7f7f")


def _shade_intervals(axes, intervals: Sequence[tuple[float, float, str]]) -> None:
    """Shade each ``(start, end, kind)`` on every axis; one legend entry per kind on the last axis."""
    from matplotlib.patches import Patch

    kinds = list(dict.fromkeys(k for _, _, k in intervals))
    colour = {k: _KIND_COLOURS[i % len(_KIND_COLOURS)] for i, k in enumerate(kinds)}
    for start, end, kind in intervals:
        for ax in axes:
            ax.axvspan(float(start), float(end), color=colour[kind], alpha=0.3, lw=0)
    if kinds:
        handles = [Patch(color=colour[k], alpha=0.3, label=f"labelled {k}") for k in kinds]
        axes[-1].add_artist(axes[-1].legend(handles=handles, loc="upper left", fontsize=8))


def plot_anomaly_timeline(
    heart_rate,
    actions,
    kl,
    flags,
    path: str | os.PathLike,
    zones: Sequence[tuple[str, float, float, str]] = DEFAULT_HR_ZONES,
    *,
    action_names: Sequence[str] = DEFAULT_ACTION_NAMES,
    time_hours=None,
    threshold=None,
    title: str | None = None,
    intervals: Sequence[tuple[float, float, str]] = (),
) -> str:
    """Draw the paper's Fig. 4 style timeline and save it as a PNG (matplotlib Agg canvas; no global state).

    Panels (shared time axis): heart rate with zone colour bands (default Light < 110 <= Moderate < 135 <=
    Vigorous <= 160 < Danger), the agent's decisions as a coloured strip, and the KL with flagged steps marked
    (plus the running threshold if given, e.g. from :func:`detect_anomalies`).

    Args:
        heart_rate, actions, kl, flags: 1-D sequences of equal length ``T`` (tensors or arrays); ``actions`` are
            indices into ``action_names``; ``flags`` bool.
        path: output file (``.png``); parent folders are created.
        zones: ``(name, low, high, colour)`` bands.
        time_hours: x values (default: step index).
        threshold: optional ``[T]`` KL threshold curve.
        intervals: labelled ground-truth intervals ``(start, end, kind)`` in the units of the x axis
            (``time_hours`` if given, else steps), shaded on the heart-rate and KL panels, one colour per kind.
    Returns the path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    hr, act, klv, fl = _np(heart_rate).astype(float), _np(actions).astype(int), _np(kl).astype(float), _np(flags)
    T = hr.shape[0]
    for name, arr in (("actions", act), ("kl", klv), ("flags", fl)):
        if arr.shape[0] != T:
            raise ValueError(f"plot_anomaly_timeline: {name} has length {arr.shape[0]}, heart_rate has {T}")
    fl = fl.astype(bool)
    x = _np(time_hours).astype(float) if time_hours is not None else np.arange(T, dtype=float)
    xlabel = "time (h)" if time_hours is not None else "step"

    fig = Figure(figsize=(12, 7), dpi=100)
    FigureCanvasAgg(fig)
    ax_hr, ax_act, ax_kl = fig.subplots(3, 1, sharex=True, gridspec_kw={"height_ratios": [3, 0.6, 2]})

    finite_top = max(float(np.nanmax(hr)) if T else 0.0, max(lo for _, lo, _, _ in zones)) + 15.0
    bottom = min(float(np.nanmin(hr)) if T else 0.0, 60.0) - 10.0
    for name, lo, hi, colour in zones:
        ax_hr.axhspan(max(lo, bottom), min(hi, finite_top), color=colour, alpha=0.8, lw=0, label=name)
    ax_hr.plot(x, hr, color="black", lw=1.0, label="heart rate")
    ax_hr.set_ylim(bottom, finite_top)
    ax_hr.set_ylabel("heart rate (bpm)")
    ax_hr.legend(loc="upper right", ncol=len(zones) + 1, fontsize=8)

    _action_strip(ax_act, x, act, action_names)

    ax_kl.plot(x, klv, color="#4c78a8", lw=1.0, label="KL(q || p)")
    if threshold is not None:
        ax_kl.plot(x, _np(threshold).astype(float), color="grey", ls="--", lw=1.0, label="mean + k std")
    if fl.any():
        ax_kl.scatter(x[fl], klv[fl], color="red", marker="v", s=30, zorder=3, label=f"anomaly ({int(fl.sum())})")
        for xi in x[fl]:
            ax_hr.axvline(xi, color="red", alpha=0.25, lw=0.8)
    _shade_intervals((ax_hr, ax_kl), intervals)
    ax_kl.set_ylabel("KL (nats)")
    ax_kl.set_xlabel(xlabel)
    ax_kl.legend(loc="upper right", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, format="png")
    logger.info("wrote anomaly timeline to %s", path)
    return path
