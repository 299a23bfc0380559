"""The anomaly report of the health domain (paper Appendix J.5, Fig. 4): record one long real-env episode with
the trained policy, flag KL anomalies, draw the timeline. ``freamer-rl health anomaly RUN_DIR``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from freamer_rl.health.agent import HealthAgent, env_options, load_agent, logits_net
from freamer_rl.run import env_registry
from freamer_rl.world_model.anomaly import DANGER_HR, DEFAULT_ACTION_NAMES, detect_anomalies, plot_anomaly_timeline
from freamer_rl.world_model.functional import gaussian_kl

__all__ = ["record_episode", "anomaly_report"]


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
    flags, thr = detect_anomalies(torch.from_numpy(rec["kl"]), k_sigma=k_sigma, warmup=warmup, momentum=momentum)
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
