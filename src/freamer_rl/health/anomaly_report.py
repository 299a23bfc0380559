"""The anomaly report of the health domain (paper Appendix J.5, Fig. 4). ``freamer-rl health anomaly RUN_DIR``.

* :func:`anomaly_report` -- record one long real-env episode with the trained policy, flag KL anomalies, draw the
  timeline (no ground truth).
* :func:`labelled_anomaly_report` -- run the trained world model's filter over a PAMAP2 recording with labelled
  anomalies (:mod:`freamer_rl.data.anomaly_labels`), flag, score against the labels
  (:mod:`freamer_rl.health.anomaly_scoring`) and draw the timeline with the labelled intervals.

Wrap-around: the env walks through its subject's timeline with ``cursor = (cursor + 1) % length`` from a random
start, so an env episode longer than the recording replays it from its start. The recipes' synthetic subjects are
``env.synthetic_duration_s = 1800`` s long: a 48-hour :func:`anomaly_report` episode (34,560 steps at 0.2 Hz)
wraps around the 360-window timeline ~96 times. :func:`labelled_anomaly_report` reads a recording generated for
the whole scenario and filters it once from its first window: it never wraps.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from freamer_rl.data import Pamap2Features, Pamap2Recording, load_pamap2_protocol, load_pamap2_subject, pamap2_features
from freamer_rl.data.anomaly_labels import read_labels, recording_time_range
from freamer_rl.errors import FreamerError
from freamer_rl.health.agent import HealthAgent, env_options, load_agent, logits_net
from freamer_rl.health.anomaly_scoring import interval_steps, score_report
from freamer_rl.health.anomaly_signals import channel_zscore, heart_rate_zscore, stale_mask, with_stale
from freamer_rl.run import env_registry
from freamer_rl.world_model.anomaly import (
    DANGER_HR,
    DEFAULT_ACTION_NAMES,
    DEFAULT_EMA_HALFLIFE,
    anomaly_statistic,
    detect_anomalies,
    plot_anomaly_timeline,
)
from freamer_rl.world_model.functional import gaussian_kl

__all__ = [
    "record_episode",
    "anomaly_report",
    "recording_observations",
    "recording_kl",
    "recording_scores",
    "labelled_anomaly_report",
    "FilteredRecording",
    "filter_labelled",
    "score_filtered",
    "SCORES",
]

#: per-step anomaly scores of a labelled recording (:func:`filter_recording`): the posterior's surprise (J.5), the
#: prior's one-step prediction error of the observation, its largest per-feature residual in that feature's own
#: running RMS (:func:`~freamer_rl.health.anomaly_signals.channel_zscore`), or -- no world model -- the residual of a
#: heart-rate lag predictor (:func:`~freamer_rl.health.anomaly_signals.heart_rate_zscore`)
SCORES = ("kl", "prediction", "channel", "hr_lag")
_SCORE_NAMES = {
    "kl": "KL",
    "prediction": "prediction error",
    "channel": "largest channel residual",
    "hr_lag": "heart-rate lag predictor residual",
}

#: The action index the filter is given for a recording (the subject followed the plan: Continue).
_CONTINUE = DEFAULT_ACTION_NAMES.index("Continue")
_ROC, _CUM = 13, 14  # hr_features columns that the env restarts at 0 on every reset


@torch.no_grad()
def record_episode(
    agent: HealthAgent,
    steps: int,
    *,
    seed: int = 0,
    deterministic: bool = True,
    progress_bar: bool = False,
    episode_length: int | None = None,
) -> dict[str, np.ndarray]:
    """Run the trained policy for ``steps`` steps in a one-env copy of the real env and record the timeline.

    The same computation as :class:`HealthPolicy` (posterior means fed forward, the mode of the policy when
    ``deterministic``), written as a lean tensor loop around the base env (a TransformedEnv step costs several
    times more, which matters for a 48-hour scenario: 34,560 steps at 0.2 Hz, 172,800 at 1 Hz). The env's
    ``episode_length`` is set to ``max(steps, env.episode_length)``; a termination (heart rate >= 200 bpm) resets
    the env and the filter and the recording goes on.

    Returns numpy arrays of length ``steps``, element ``t`` describing step ``t``: ``heart_rate`` (bpm, observed
    at ``t``), ``activity``, ``action``, ``kl`` (``KL(q || p)`` of the posterior after observation ``t``, J.5),
    ``reward`` and ``done`` (after the action), ``is_first``.
    """
    cfg = agent.cfg
    wm = agent.world_model
    wm.eval()
    enc = wm.encoder
    net = logits_net(agent.actor)
    length = episode_length or max(steps, cfg.env.episode_length)
    env = env_registry.make_env(
        cfg.env.adapter, cfg.env.id, seed=seed, batch_size=1, **{**env_options(cfg), "episode_length": length}
    )
    rec = {
        "heart_rate": np.empty(steps, np.float32),
        "activity": np.empty(steps, np.int64),
        "action": np.empty(steps, np.int64),
        "kl": np.empty(steps, np.float32),
        "reward": np.empty(steps, np.float32),
        "done": np.empty(steps, bool),
        "is_first": np.empty(steps, bool),
    }
    h, z = wm.rssm.initial_state((1,))
    prev = torch.zeros(1, wm.action_dim)
    state = enc.initial_state((1,))
    first = torch.ones(1, dtype=torch.bool)
    td = env.reset()
    for t in tqdm(range(steps), desc="anomaly episode", disable=not progress_bar, mininterval=2.0):
        obs = {k: td.get(k) for k in wm.obs_dims}
        embed, state = enc.step(obs, state, first)
        out = wm.rssm.obs_step(h, z, prev, embed, is_first=first, sample=False)
        h, z = out["h"], out["z"]
        logits = net(torch.cat([h, z], dim=-1))
        action = logits.argmax(-1) if deterministic else torch.distributions.Categorical(logits=logits).sample()
        prev = F.one_hot(action, wm.action_dim).float()
        td.set("action", action)
        nxt = env.step(td).get("next")
        done = bool(nxt.get("done").any())
        rec["heart_rate"][t] = float(td.get("heart_rate").reshape(-1)[0])
        rec["activity"][t] = int(td.get("activity").reshape(-1)[0])
        rec["action"][t] = int(action[0])
        rec["kl"][t] = float(gaussian_kl(out["post_mean"], out["post_std"], out["prior_mean"], out["prior_std"])[0])
        rec["reward"][t] = float(nxt.get("reward").reshape(-1)[0])
        rec["done"][t] = done
        rec["is_first"][t] = bool(first[0])
        if done:
            td = env.reset()
            first = torch.ones(1, dtype=torch.bool)
        else:
            td = nxt
            first = torch.zeros(1, dtype=torch.bool)
    env.close()
    return rec


def anomaly_report(
    checkpoint_or_model: str | Path | HealthAgent,
    run_dir: str | Path,
    hours: float = 48.0,
    *,
    seed: int = 0,
    k_sigma: float = 2.0,
    warmup: int = 20,
    momentum: float | None = None,
    deterministic: bool = True,
    progress_bar: bool = True,
    statistic: str = "running",
    halflife: float | None = None,
) -> dict[str, Any]:
    """Record one long episode with the trained policy, flag KL anomalies and draw the Fig. 4 picture.

    The scenario lasts ``hours`` at the env's step rate (``env.rate_hz``; 48 h at the recipes' 0.2 Hz = 34,560
    steps, at 1 Hz 172,800; roughly 1.5-8 ms a step on one CPU core, the foundation encoder being the slowest) and is
    recorded by :func:`record_episode` (``episode_length`` set to the whole scenario). The per-step ``KL(q || p)``
    of the online posterior (J.5) goes through :func:`~freamer_rl.world_model.anomaly.detect_anomalies`: a step is
    flagged when ``KL > running mean + k_sigma running std`` (statistics before the step, Welford or EMA with
    ``momentum``; none in the first ``warmup`` steps).

    Writes into ``run_dir``: ``anomaly_timeline.png`` (heart rate with zones, the agent's decisions, KL with flags
    and threshold; :func:`~freamer_rl.world_model.anomaly.plot_anomaly_timeline`), ``anomaly_episode.npz`` (the
    recorded arrays plus ``flag``, ``threshold``, ``time_h``) and ``anomaly_summary.json`` (returned).
    """
    agent = checkpoint_or_model if isinstance(checkpoint_or_model, HealthAgent) else load_agent(checkpoint_or_model)
    cfg = agent.cfg
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    steps = max(2, int(round(hours * 3600.0 * cfg.env.rate_hz)))
    rec = record_episode(agent, steps, seed=seed, deterministic=deterministic, progress_bar=progress_bar)
    flags, thr = detect_anomalies(
        torch.from_numpy(rec["kl"]),
        k_sigma=k_sigma,
        warmup=warmup,
        momentum=momentum,
        statistic=statistic,
        halflife=halflife,
    )
    time_h = np.arange(steps, dtype=np.float64) / cfg.env.rate_hz / 3600.0
    hr, act, kl = rec["heart_rate"], rec["action"], rec["kl"]
    png = plot_anomaly_timeline(
        hr,
        act,
        kl,
        flags,
        run_dir / "anomaly_timeline.png",
        time_hours=time_h,
        threshold=thr,
        title=f"{hours:g}-hour scenario, {cfg.encoder.kind} encoder: heart rate, decisions, KL anomalies "
        f"(KL > mean + {k_sigma:g} std)",
    )
    fl = flags.numpy()
    np.savez_compressed(run_dir / "anomaly_episode.npz", **rec, flag=fl, threshold=thr.numpy(), time_h=time_h)
    summary = {
        "hours": hours,
        "steps": steps,
        "rate_hz": cfg.env.rate_hz,
        "encoder": cfg.encoder.kind,
        "k_sigma": k_sigma,
        "statistic": statistic if momentum is None else "ema",
        "anomalies": int(fl.sum()),
        "anomaly_fraction": float(fl.mean()),
        "anomaly_hr_mean": float(hr[fl].mean()) if fl.any() else None,
        "hr_mean": float(hr.mean()),
        "hr_max": float(hr.max()),
        "danger_steps": int((hr > DANGER_HR).sum()),
        "danger_steps_flagged": int(((hr > DANGER_HR) & fl).sum()),
        "kl_mean": float(kl.mean()),
        "kl_std": float(kl.std()),
        "action_counts": {name.lower(): int((act == i).sum()) for i, name in enumerate(DEFAULT_ACTION_NAMES)},
        "return": float(rec["reward"].sum()),
        "terminations": int(rec["done"][:-1].sum()),
        "png": png,
    }
    (run_dir / "anomaly_summary.json").write_text(json.dumps(summary, indent=2))
    return summary


# ----------------------------------------------------------------------------------------------------------------------
# a recording with labelled anomalies
# ----------------------------------------------------------------------------------------------------------------------
def load_recording(data: str | Path, subject: int | None = None) -> Pamap2Recording:
    """One subject's recording: a ``subjectNNN.dat`` file, or a PAMAP2 folder (root or ``Protocol/``) holding one
    subject file (or several and ``subject``).

    Raises:
        Pamap2FormatError / FreamerError: one line -- missing path, a folder without ``subjectNNN.dat`` files, a
            folder with several and no ``subject``, a malformed file.
    """
    path = Path(data)
    if path.is_file():
        return load_pamap2_subject(path)
    recs = load_pamap2_protocol(path, None if subject is None else [subject])
    if len(recs) > 1:
        raise FreamerError(
            f"{path}: holds {len(recs)} subject files ({', '.join(f'subject{s}.dat' for s in recs)}); "
            "expected one, or name it with --subject"
        )
    return next(iter(recs.values()))


def recording_observations(feat: Pamap2Features, segment_steps: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The world model's observations of a recording, cut into filter episodes of ``segment_steps`` steps.

    The observation is the loader's (``imu [N, 36]``, ``hr_features [N, 16]``: what the env shows of a PAMAP2
    window at level 1 without Change); as at an env reset, the heart-rate rate of change (column 13) and the
    cumulative exertion (column 14) restart at 0 at every episode start. ``segment_steps = 0``: one episode (the
    cumulative exertion then grows over the whole recording, beyond the training episodes' range).

    Returns:
        ``({key: float32 [S, L, d]}, valid bool [S, L])`` with ``S = ceil(N / L)`` episodes, the last padded
        (padding invalid).
    """
    n = len(feat)
    seg = n if segment_steps <= 0 else min(int(segment_steps), n)
    s_count = -(-n // seg)
    pad = s_count * seg - n
    hr = feat.hr_features.astype(np.float32).copy()
    starts = np.arange(0, n, seg)
    cum = hr[:, _CUM].astype(np.float64)
    # cumulative exertion since the episode start, 0 at the start (the env's reset value)
    hr[:, _CUM] = cum - np.repeat(cum[starts], np.diff(np.append(starts, n)))
    hr[starts, _ROC] = 0.0
    valid = np.ones(n + pad, dtype=bool)
    valid[n:] = False

    def shape(x: np.ndarray) -> np.ndarray:
        x = np.concatenate([x, np.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape(s_count, seg, -1).astype(np.float32)

    return {"imu": shape(feat.imu), "hr_features": shape(hr)}, valid.reshape(s_count, seg)


@torch.no_grad()
def recording_scores(
    agent: HealthAgent, obs: dict[str, np.ndarray], *, progress_bar: bool = False
) -> dict[str, np.ndarray]:
    """Per-step anomaly scores float32 ``[S, L]`` of the trained filter over ``obs`` ``{key: [S, L, d]}``.

    Each of the ``S`` rows is one filter episode (run side by side as a batch): it starts from the zero state with
    ``is_first`` at step 0, feeds posterior means forward and gives the world model the action Continue (the
    subject followed the plan) -- :func:`record_episode`'s filter without the policy. Scores:

    * ``"kl"``: ``KL(q(z_t | h_t, o_t) || p(z_t | h_t))`` (J.5): how far the observation moved the latent.
    * ``"prediction"``: the prior's one-step prediction error of the observation, ``mean_j (dec(h_t, mu_prior)_j -
      y_j)^2`` over every feature ``j`` of every key, ``y`` the decoder's target (standardised with the world
      model's ``recon_norm`` statistics): how badly the model expected what it saw *before* seeing it. Unlike the
      KL it rises when a sensor freezes (forward-filled packets: an observation the model never produces).
    * ``"residual"`` (float32 ``[S, L, D]``): the per-feature residuals ``dec(h_t, mu_prior) - y`` behind
      ``"prediction"``, features in the order of the world model's keys (what the ``"channel"`` score of
      :func:`filter_recording` normalises).
    """
    wm = agent.world_model
    wm.eval()
    enc = wm.encoder
    keys = list(wm.obs_dims)
    x = {k: torch.from_numpy(v) for k, v in obs.items()}
    s_count, length = next(iter(x.values())).shape[:2]
    h, z = wm.rssm.initial_state((s_count,))
    prev = torch.zeros(s_count, wm.action_dim)
    cont = torch.nn.functional.one_hot(torch.full((s_count,), _CONTINUE), wm.action_dim).float()
    state = enc.initial_state((s_count,))
    first = torch.ones(s_count, dtype=torch.bool)
    kl = torch.empty(s_count, length)
    width = sum(int(wm.obs_dims[k]) for k in keys)
    residual = torch.empty(s_count, length, width)
    for t in tqdm(range(length), desc="filter", disable=not progress_bar, mininterval=2.0):
        obs_t = {k: v[:, t] for k, v in x.items()}
        embed, state = enc.step(obs_t, state, first)
        out = wm.rssm.obs_step(h, z, prev, embed, is_first=first, sample=False)
        h, z = out["h"], out["z"]
        kl[:, t] = gaussian_kl(out["post_mean"], out["post_std"], out["prior_mean"], out["prior_std"])
        expected = wm.decoder(torch.cat([out["h"], out["prior_mean"]], dim=-1))  # decoder targets, [S, d_k]
        residual[:, t] = torch.cat([expected[k] - wm.recon_target(k, obs_t[k]) for k in keys], dim=-1)
        prev, first = cont, torch.zeros_like(first)
    return {"kl": kl.numpy(), "prediction": residual.pow(2).mean(-1).numpy(), "residual": residual.numpy()}


def recording_kl(agent: HealthAgent, obs: dict[str, np.ndarray], *, progress_bar: bool = False) -> np.ndarray:
    """Per-step ``KL(q || p)`` float32 ``[S, L]``: the ``"kl"`` score of :func:`recording_scores`."""
    return recording_scores(agent, obs, progress_bar=progress_bar)["kl"]


def filter_recording(
    agent: HealthAgent, feat: Pamap2Features, segment_steps: int, *, warmup: int = 20
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """``({score: [N]}, include bool [N])`` of the trained filter over a windowed recording, for every score of
    :data:`SCORES` (:func:`recording_scores`, ``"channel"`` from its residuals with ``warmup``, and ``"hr_lag"``
    from the recording alone), in filter
    episodes of ``segment_steps`` steps (0 = one); ``include`` is False at each episode's first (reset) step."""
    obs, valid = recording_observations(feat, segment_steps)
    scores = recording_scores(agent, obs)
    include = valid.copy()
    include[:, 0] = False  # a fresh filter is not a surprise
    n = len(feat)
    include = include.reshape(-1)[:n]
    residual = scores.pop("residual")
    out = {k: v.reshape(-1)[:n] for k, v in scores.items()}
    out["channel"] = channel_zscore(residual.reshape(-1, residual.shape[-1])[:n], include, warmup=warmup)
    out["hr_lag"] = heart_rate_zscore(feat.heart_rate, feat.met, include, warmup=warmup)
    return out, include


def labelled_anomaly_report(
    checkpoint_or_model: str | Path | HealthAgent,
    run_dir: str | Path,
    data: str | Path,
    labels: str | Path,
    *,
    subject: int | None = None,
    statistic: str = "running",
    halflife: float | None = None,
    k_sigma: float = 2.0,
    warmup: int = 20,
    tolerance_s: float = 30.0,
    segment_steps: int | None = None,
    score: str = "kl",
    stale_steps: int = 0,
    plot: bool = True,
) -> dict[str, Any]:
    """Filter a labelled recording with the trained world model, flag anomalies of one score and rate the flags.

    The recording is windowed at the run's ``env.rate_hz`` (:func:`~freamer_rl.data.pamap2_features`, the
    observation the env builds from a PAMAP2 subject), cut into filter episodes of ``segment_steps`` steps
    (default: the training episodes' ``env.episode_length``; 0 = one episode; :func:`recording_observations`) and
    filtered (:func:`recording_scores`: ``score`` ``"kl"``, the posterior's surprise, or ``"prediction"``, the
    prior's one-step prediction error, or ``"channel"``, its largest per-feature residual in units of that feature's
    running RMS). The first step of each episode is neither flagged nor counted in the statistics. Flags: ``score >
    mean + k_sigma std`` with the ``running`` or ``ema`` statistic
    (:func:`~freamer_rl.world_model.anomaly.anomaly_statistic`); with ``stale_steps > 0`` also every step at which
    the IMU features have not changed for ``stale_steps`` steps (a frozen sensor:
    :func:`~freamer_rl.health.anomaly_signals.stale_mask`; those steps rank above all others in the threshold-free
    metrics). Scores
    (:func:`~freamer_rl.health.anomaly_scoring.score_report`): event-level precision / recall / false alarms per
    hour (a flag up to ``tolerance_s`` after an event's end still detects it), AUROC and AUC-PR of the raw score
    and of the detector's z-score, strict and point-adjusted.

    Writes into ``run_dir``: ``anomaly_timeline.png`` (with the labelled intervals), ``anomaly_scores.json``
    (returned) and ``anomaly_scores.npz`` (``score``, ``kl``, ``prediction``, ``z``, ``flag``, ``threshold``, ``label``, ``valid``,
    ``heart_rate``, ``time_h``, ``events``, ``kinds``).

    Raises:
        AnomalyLabelsError / Pamap2FormatError: one line naming the file (and line) at fault.
    """
    filtered = filter_labelled(
        checkpoint_or_model, data, labels, subject=subject, segment_steps=segment_steps, warmup=warmup
    )
    return score_filtered(
        filtered,
        run_dir,
        statistic=statistic,
        halflife=halflife,
        k_sigma=k_sigma,
        tolerance_s=tolerance_s,
        score=score,
        stale_steps=stale_steps,
        plot=plot,
    )


@dataclass
class FilteredRecording:
    """A labelled recording windowed at the run's step rate and filtered once (every score of :data:`SCORES`):
    what :func:`score_filtered` flags and scores, as often as a threshold sweep needs."""

    data: str
    labels: str
    subject: int
    encoder: str
    recording_hours: float
    feat: Pamap2Features
    intervals: list
    scores: dict[str, np.ndarray]  # {score: [N]}
    include: np.ndarray  # bool [N]: not a filter episode's first step
    segment_steps: int
    warmup: int


def filter_labelled(
    checkpoint_or_model: str | Path | HealthAgent,
    data: str | Path,
    labels: str | Path,
    *,
    subject: int | None = None,
    segment_steps: int | None = None,
    warmup: int = 20,
) -> FilteredRecording:
    """Load a labelled recording (checked before the slower agent is loaded), window it and filter it
    (:func:`filter_recording`; ``segment_steps`` default: the run's ``env.episode_length``)."""
    rec = load_recording(data, subject)
    intervals = read_labels(labels, time_range=recording_time_range(rec))
    agent = checkpoint_or_model if isinstance(checkpoint_or_model, HealthAgent) else load_agent(checkpoint_or_model)
    cfg = agent.cfg
    feat = pamap2_features(rec, rate_hz=cfg.env.rate_hz)
    seg = cfg.env.episode_length if segment_steps is None else int(segment_steps)
    scores, include = filter_recording(agent, feat, seg, warmup=warmup)
    return FilteredRecording(
        data=str(data),
        labels=str(labels),
        subject=rec.subject,
        encoder=cfg.encoder.kind,
        recording_hours=rec.duration_s / 3600.0,
        feat=feat,
        intervals=intervals,
        scores=scores,
        include=include,
        segment_steps=seg if seg > 0 else len(feat),
        warmup=warmup,
    )


def score_filtered(
    filtered: FilteredRecording,
    run_dir: str | Path,
    *,
    statistic: str = "running",
    halflife: float | None = None,
    k_sigma: float = 2.0,
    tolerance_s: float = 30.0,
    score: str = "kl",
    stale_steps: int = 0,
    plot: bool = True,
) -> dict[str, Any]:
    """Flag one score of a :class:`FilteredRecording` and rate the flags (:func:`labelled_anomaly_report`)."""
    if score not in SCORES:
        raise ValueError(f"score: expected one of {', '.join(SCORES)}, got {score!r}")
    if int(stale_steps) != stale_steps or stale_steps < 0:
        raise ValueError(f"stale_steps: expected an integer >= 0 (0: off), got {stale_steps!r}")
    feat, intervals, scores = filtered.feat, filtered.intervals, filtered.scores
    step_s = 1.0 / feat.rate_hz
    include = filtered.include & np.isfinite(scores[score])  # the channel score's own warm-up
    stat = anomaly_statistic(
        torch.from_numpy(scores[score]).float(),
        k_sigma=k_sigma,
        warmup=filtered.warmup,
        statistic=statistic,
        halflife=halflife,
        include=torch.from_numpy(include),
    )
    arrays = {k: stat[k].numpy() for k in ("flags", "z", "threshold")}
    stale = stale_mask(feat.imu, int(stale_steps)) & include
    raw, arrays["flags"] = with_stale(scores[score], arrays["flags"], stale)
    arrays["z"], _ = with_stale(arrays["z"], arrays["flags"], stale)
    arrays.update(
        score=raw,
        stale=stale,
        **scores,
        valid=include,
        heart_rate=feat.heart_rate,
        kinds=np.asarray([a.kind for a in intervals]),
    )
    arrays["events"] = interval_steps(
        [a.start_s for a in intervals], [a.end_s for a in intervals], feat.timestamp, step_s
    )
    arrays["time_h"] = (feat.timestamp - feat.timestamp[0] + step_s) / 3600.0
    summary = {
        "data": filtered.data,
        "labels": filtered.labels,
        "subject": filtered.subject,
        "encoder": filtered.encoder,
        "rate_hz": feat.rate_hz,
        "steps": len(feat),
        "hours": len(feat) * step_s / 3600.0,
        "recording_hours": filtered.recording_hours,
        "wraps": False,
        "segment_steps": filtered.segment_steps,
        "score": score,
        "stale_steps": int(stale_steps),
        "stale_flagged_steps": int(stale.sum()),
        "statistic": statistic,
        "ema_halflife": (DEFAULT_EMA_HALFLIFE if halflife is None else float(halflife)) if statistic == "ema" else None,
        "k_sigma": k_sigma,
        "warmup": filtered.warmup,
        **_scores(arrays, step_s, int(round(tolerance_s / step_s))),
    }
    return _write_labelled(Path(run_dir), summary, arrays, plot)


def _scores(a: dict[str, np.ndarray], step_s: float, tol: int) -> dict[str, Any]:
    """The summary's metrics: event level and the raw score's AUROC / AUC-PR at the top, the z-score's beside."""
    common = {"step_s": step_s, "tolerance": tol, "valid": a["valid"], "kinds": list(a["kinds"])}
    on_kl = score_report(a["score"], a["flags"], a["events"], **common)
    on_z = score_report(a["z"], a["flags"], a["events"], **common)
    return {
        "tolerance_s": tol * step_s,
        **on_kl["event"],
        "auroc": on_kl["strict"]["auroc"],
        "auc_pr": on_kl["strict"]["auc_pr"],
        "auroc_point_adjusted": on_kl["point_adjusted"]["auroc"],
        "auc_pr_point_adjusted": on_kl["point_adjusted"]["auc_pr"],
        "recall_by_kind": on_kl["recall_by_kind"],
        "raw_score": {"strict": on_kl["strict"], "point_adjusted": on_kl["point_adjusted"]},
        "z_score": {"strict": on_z["strict"], "point_adjusted": on_z["point_adjusted"]},
        "anomalous_steps": on_kl["anomalous_steps"],
        "flagged_steps": on_kl["flagged_steps"],
        "flagged_fraction": float(a["flags"].mean()),
    }


def _write_labelled(run_dir: Path, summary: dict, a: dict[str, np.ndarray], plot: bool) -> dict[str, Any]:
    """Write ``anomaly_scores.npz``, the timeline (if ``plot``) and ``anomaly_scores.json``; return the summary."""
    run_dir.mkdir(parents=True, exist_ok=True)
    n = a["kl"].shape[0]
    label = np.zeros(n, dtype=bool)
    for s, e in a["events"]:
        label[s:e] = True
    rest = {k: v for k, v in a.items() if k != "flags"}
    np.savez_compressed(run_dir / "anomaly_scores.npz", flag=a["flags"], label=label, **rest)
    if plot:
        t, step_h = a["time_h"], 1.0 / summary["rate_hz"] / 3600.0
        summary["png"] = plot_anomaly_timeline(
            a["heart_rate"],
            np.full(n, _CONTINUE),
            a["score"],
            a["flags"],
            run_dir / "anomaly_timeline.png",
            time_hours=t,
            threshold=a["threshold"],
            intervals=[(t[s] - step_h, t[e - 1], k) for (s, e), k in zip(a["events"], a["kinds"])],
            title=f"{summary['hours']:.3g}-hour labelled recording, {summary['encoder']} encoder: "
            f"{_SCORE_NAMES[summary['score']]} > mean + "
            f"{summary['k_sigma']:g} std ({summary['statistic']}); recall {_fmt(summary['recall'])}, "
            f"{_fmt(summary['fa_per_hour'])} false alarms/h",
        )
    (run_dir / "anomaly_scores.json").write_text(json.dumps(summary, indent=2))
    return summary


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"
