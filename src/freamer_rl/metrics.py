"""Run metrics and what the user sees of them: episode statistics, the progress display and the learning curve.

- :class:`EpisodeStats`: episodes counted over the whole run, success / return / length over the last ``window``.
- :class:`ProgressReporter`: a tqdm bar on a terminal; otherwise (output piped to a file, a batch job) one plain
  ``logging`` line every ``interval_s`` seconds with frames, frames/s, episodes, success rate and return.
- :func:`plot_learning_curve`: ``learning_curve.png``, success rate (top) and mean return (bottom) vs frames; only the
  return panel, with a note, when the env has no notion of success (success rate NaN throughout, e.g. CartPole).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

logger = logging.getLogger(__name__)

SUCCESS_TARGET = 0.95
PROGRESS_LOG_INTERVAL_S = 10.0

__all__ = [
    "SUCCESS_TARGET", "EpisodeStats", "ProgressReporter", "format_duration", "format_rate", "plot_learning_curve",
    "quiet_library_logs",
]
#: Loggers of libraries whose INFO lines (e.g. TorchRL's "Initialized LazyTensorStorage ...") are noise in a run log.
NOISY_LIBRARY_LOGGERS = ("torchrl", "tensordict")


@dataclass
class EpisodeStats:
    """Running episode statistics over the whole run and a success window of the last ``window`` episodes."""

    window: int = 100
    # episode-end entries of the "next" tensordict [N] -> bool [N]; None: the task has no success (returns only)
    success_fn: Any = None
    episodes: int = 0
    recent_success: deque = field(default_factory=deque)
    recent_return: deque = field(default_factory=deque)
    recent_length: deque = field(default_factory=deque)
    first_target_frames: int | None = None
    first_target_episodes: int | None = None

    def update(self, data: TensorDictBase, frames_before: int) -> None:
        nxt = data["next"]
        done = nxt["done"].squeeze(-1)
        if not done.any():
            return
        # order episode ends by time, then env; leading dims ([workers, envs]) are flattened into envs
        T = done.shape[-1]
        done_bt = done.reshape(-1, T)
        B = done_bt.shape[0]
        t_idx = done_bt.nonzero()
        order = torch.argsort(t_idx[:, 1] * B + t_idx[:, 0])
        t_idx = t_idx[order]

        def at_ends(key):
            return nxt[key].reshape(B, T)[t_idx[:, 0], t_idx[:, 1]]

        rets, lens = (at_ends(k).reshape(-1).tolist() for k in ("episode_reward", "step_count"))
        succ = None
        if self.success_fn is not None:
            ends = nxt.reshape(B, T)[t_idx[:, 0], t_idx[:, 1]]
            succ = self.success_fn(ends).reshape(-1).tolist()
        end_steps = t_idx[:, 1].tolist()
        for i in range(len(end_steps)):
            self.episodes += 1
            if succ is not None:
                self._push(self.recent_success, float(succ[i]))
            self._push(self.recent_return, float(rets[i]))
            self._push(self.recent_length, float(lens[i]))
            if (
                succ is not None
                and self.first_target_episodes is None
                and len(self.recent_success) >= self.window
                and self.success_rate >= SUCCESS_TARGET
            ):
                self.first_target_episodes = self.episodes
                self.first_target_frames = frames_before + (end_steps[i] + 1) * B

    def _push(self, q: deque, v: float) -> None:
        q.append(v)
        while len(q) > self.window:
            q.popleft()

    @property
    def success_rate(self) -> float:
        return sum(self.recent_success) / len(self.recent_success) if self.recent_success else float("nan")

    @property
    def mean_return(self) -> float:
        return sum(self.recent_return) / len(self.recent_return) if self.recent_return else float("nan")

    @property
    def mean_length(self) -> float:
        return sum(self.recent_length) / len(self.recent_length) if self.recent_length else float("nan")

    def state_dict(self) -> dict:
        return {
            "window": self.window,
            "episodes": self.episodes,
            "recent_success": list(self.recent_success),
            "recent_return": list(self.recent_return),
            "recent_length": list(self.recent_length),
            "first_target_frames": self.first_target_frames,
            "first_target_episodes": self.first_target_episodes,
        }

    def load_state_dict(self, sd: dict) -> None:
        self.window = sd["window"]
        self.episodes = sd["episodes"]
        self.recent_success = deque(sd["recent_success"])
        self.recent_return = deque(sd["recent_return"])
        self.recent_length = deque(sd["recent_length"])
        self.first_target_frames = sd["first_target_frames"]
        self.first_target_episodes = sd["first_target_episodes"]


def format_rate(value: float, digits: int = 2) -> str:
    """``0.625`` -> ``'0.62'``; NaN (no episode yet, or no notion of success) -> ``'n/a'``."""
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


@contextlib.contextmanager
def quiet_library_logs(names: tuple[str, ...] = NOISY_LIBRARY_LOGGERS):
    """Within the block, the ``names`` loggers show only warnings and errors; their levels are restored after.

    Left alone when ``freamer_rl`` itself logs at DEBUG (``--log-level DEBUG`` shows everything).
    """
    if logging.getLogger("freamer_rl").isEnabledFor(logging.DEBUG):
        yield
        return
    saved = {}
    for name in names:
        lib = logging.getLogger(name)
        saved[name] = lib.level
        if lib.getEffectiveLevel() < logging.WARNING:
            lib.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def format_duration(seconds: float) -> str:
    """``9.42`` -> ``'9.4 s'``, ``725`` -> ``'12 min 5 s'``, ``3780`` -> ``'1 h 3 min'``."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes} min {secs} s"
    return f"{minutes // 60} h {minutes % 60} min"


def _is_terminal() -> bool:
    return all(getattr(s, "isatty", lambda: False)() for s in (sys.stdout, sys.stderr))


class ProgressReporter:
    """Progress of a run: a tqdm bar when ``bar`` and both stdout and stderr are terminals, otherwise one plain log
    line at the first batch and then every ``interval_s`` seconds (no carriage-return noise in a piped log)."""

    def __init__(self, total: int, initial: int, *, bar: bool, interval_s: float = PROGRESS_LOG_INTERVAL_S) -> None:
        self.total = total
        self.interval_s = interval_s
        self._last_log: float | None = None
        self._frames_at_log, self._t_at_log = initial, time.perf_counter()
        self._pbar = None
        if bar and _is_terminal():
            from tqdm.auto import tqdm

            self._pbar = tqdm(total=total, initial=initial, unit="frames", dynamic_ncols=True)

    def update(self, frames: int, new_frames: int, stats: EpisodeStats) -> None:
        """After a batch: ``frames`` trained on so far, ``new_frames`` of them from this batch."""
        if self._pbar is not None:
            self._pbar.update(new_frames)
            self._pbar.set_postfix(ep=stats.episodes, success=format_rate(stats.success_rate),
                                   ret=format_rate(stats.mean_return))  # fmt: skip
            return
        now = time.perf_counter()
        if self._last_log is not None and now - self._last_log < self.interval_s:
            return
        fps = (frames - self._frames_at_log) / max(now - self._t_at_log, 1e-9)
        logger.info(
            "frames %d/%d (%.0f%%) | %.0f frames/s | episodes %d | success %s | return %s",
            frames, self.total, 100.0 * frames / max(self.total, 1), fps,
            stats.episodes, format_rate(stats.success_rate), format_rate(stats.mean_return),
        )  # fmt: skip
        self._last_log = self._t_at_log = now
        self._frames_at_log = frames

    def close(self) -> None:
        if self._pbar is not None:
            self._pbar.close()


def plot_learning_curve(rows: list[dict], path: Path, title: str = "", window: int | None = None) -> None:
    """Success rate (last-``window`` episodes) over mean return vs frames, two stacked panels, one PNG.

    ``rows``: progress rows with ``frames``, ``success_rate`` and ``return_mean`` (NaN before the first episode);
    ``window``: the episodes they average over (``logging.success_window``), for the axis labels.
    Without any finite success rate (an env with no notion of success) only the return panel is drawn, with a note.
    Written atomically (temporary file, then ``os.replace``).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recent = f"(last {window} episodes)" if window else "(recent episodes)"
    frames = [r["frames"] for r in rows]
    success = [float(r.get("success_rate", math.nan)) for r in rows]
    has_success = any(math.isfinite(s) for s in success)
    if has_success:
        fig, (ax_s, ax_r) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
        ax_s.plot(frames, success, color="tab:green", marker="." if len(rows) < 30 else None)
        ax_s.axhline(SUCCESS_TARGET, color="grey", ls=":", lw=1, label=f"target {SUCCESS_TARGET:.2f}")
        ax_s.set_ylim(-0.02, 1.02)
        ax_s.set_ylabel(f"success rate\n{recent}")
        ax_s.legend(loc="lower right", frameon=False)
        ax_s.grid(alpha=0.3)
        ax_s.set_title(title)
    else:
        fig, ax_r = plt.subplots(1, 1, figsize=(7, 3.5))
        ax_r.set_title(title)
        ax_r.text(0.01, 0.97, "this env reports no success: return only", transform=ax_r.transAxes,
                  ha="left", va="top", fontsize=8, color="dimgrey")  # fmt: skip
    ax_r.plot(frames, [float(r.get("return_mean", math.nan)) for r in rows], color="tab:blue",
              marker="." if len(rows) < 30 else None)  # fmt: skip
    ax_r.set_ylabel(f"mean return\n{recent}")
    ax_r.set_xlabel("frames")
    ax_r.grid(alpha=0.3)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
