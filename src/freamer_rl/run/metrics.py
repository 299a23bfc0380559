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
from tqdm.auto import tqdm

from freamer_rl.run.checkpoint import run_file_errors

logger = logging.getLogger(__name__)

SUCCESS_TARGET = 0.95
#: success rates whose first reaching every run records: the exact episode (and its frame) at which the trailing
#: ``window``-episode success rate first reaches the level (summary ``frames_to_80`` / ``episodes_to_80``, ``_95``)
SUCCESS_LEVELS = (0.8, SUCCESS_TARGET)
PROGRESS_LOG_INTERVAL_S = 10.0

__all__ = [
    "RETURN_SERIES",
    "SUCCESS_LEVELS",
    "SUCCESS_TARGET",
    "EpisodeStats",
    "LogMeans",
    "ProgressReporter",
    "format_duration",
    "format_rate",
    "json_safe",
    "plot_learning_curve",
    "quiet_library_logs",
]
#: Loggers of libraries whose INFO lines (e.g. TorchRL's "Initialized LazyTensorStorage ...") are noise in a run log.
NOISY_LIBRARY_LOGGERS = ("torchrl", "tensordict")


@dataclass
class EpisodeStats:
    """Running episode statistics over the whole run and a success window of the last ``window`` episodes.

    ``first_reached[level]``: ``(frames, episodes)`` at the episode whose end first brings the trailing ``window``-episode
    success rate to ``level`` or above (a full window only), for each of :data:`SUCCESS_LEVELS`; the frame counts
    every env's steps up to that episode's time step within its batch. ``None``: not known (a checkpoint older than the
    level's record). The project's one definition of "frames / episodes to X% success" (reports and chains use it).
    ``return_target`` (``logging.return_target``): the same for the windowed mean return reaching a level
    (``first_return``), e.g. CartPole's 475.
    """

    window: int = 100
    # episode-end entries of the "next" tensordict [N] -> bool [N]; None: the task has no success (returns only)
    success_fn: Any = None
    episodes: int = 0
    recent_success: deque = field(default_factory=deque)
    recent_return: deque = field(default_factory=deque)
    recent_length: deque = field(default_factory=deque)
    first_reached: dict[float, tuple[int, int] | None] = field(default_factory=dict)
    return_target: float | None = None
    first_return: tuple[int, int] | None = None

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
            frames = frames_before + (end_steps[i] + 1) * B
            if succ is not None and len(self.recent_success) >= self.window:
                self._note_levels(frames)
            if (
                self.return_target is not None
                and self.first_return is None
                and len(self.recent_return) >= self.window
                and self.mean_return >= self.return_target
            ):
                self.first_return = (frames, self.episodes)

    def _note_levels(self, frames: int) -> None:
        rate = self.success_rate
        for level in SUCCESS_LEVELS:
            if level not in self.first_reached and rate >= level:
                self.first_reached[level] = (frames, self.episodes)

    def frames_to(self, level: float) -> int | None:
        """Frames at which the windowed success rate first reached ``level`` (``None``: not yet, or not known)."""
        hit = self.first_reached.get(level)
        return None if hit is None else hit[0]

    def episodes_to(self, level: float) -> int | None:
        """Episodes at which the windowed success rate first reached ``level`` (``None``: not yet, or not known)."""
        hit = self.first_reached.get(level)
        return None if hit is None else hit[1]

    def level_summary(self) -> dict[str, int | None]:
        """``{"frames_to_80": ..., "episodes_to_80": ..., "frames_to_95": ..., "episodes_to_95": ...}``."""
        out: dict[str, int | None] = {}
        for level in SUCCESS_LEVELS:
            pct = round(100 * level)
            out[f"frames_to_{pct}"] = self.frames_to(level)
            out[f"episodes_to_{pct}"] = self.episodes_to(level)
        if self.return_target is not None:
            out["return_target"] = self.return_target
            out["frames_to_return"], out["episodes_to_return"] = self.first_return or (None, None)
        return out

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
            "first_reached": [[level, None if hit is None else list(hit)] for level, hit in self.first_reached.items()],
            "first_return": None if self.first_return is None else [self.return_target, *self.first_return],
        }

    def load_state_dict(self, sd: dict) -> None:
        self.window = sd["window"]
        self.episodes = sd["episodes"]
        self.recent_success = deque(sd["recent_success"])
        self.recent_return = deque(sd["recent_return"])
        self.recent_length = deque(sd["recent_length"])
        if "first_reached" in sd:
            self.first_reached = {float(lv): None if hit is None else tuple(hit) for lv, hit in sd["first_reached"]}
            hit = sd.get("first_return")  # kept only if it was recorded for the same target
            self.first_return = None if hit is None or hit[0] != self.return_target else (int(hit[1]), int(hit[2]))
            return
        # a checkpoint from before SUCCESS_LEVELS recorded only the 95% level; the others are not known
        old = sd.get("first_target_frames"), sd.get("first_target_episodes")
        self.first_reached = {level: None for level in SUCCESS_LEVELS if level != SUCCESS_TARGET}
        if old[0] is not None:
            self.first_reached[SUCCESS_TARGET] = (int(old[0]), int(old[1]))


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
    line at the first batch and then every ``interval_s`` seconds (no carriage-return noise in a piped log).

    ``total``: the frames the run will have collected at its end (the collector's own total, a whole number of
    batches); the shown share is capped at 100 % in any case. ``unit``: what ``frames`` counts.
    """

    def __init__(
        self,
        total: int,
        initial: int,
        *,
        bar: bool,
        interval_s: float = PROGRESS_LOG_INTERVAL_S,
        desc: str | None = None,
    ) -> None:
        self.total = max(int(total), int(initial), 1)
        self.interval_s = interval_s
        self._last_log: float | None = None
        self._frames_at_log, self._t_at_log = initial, time.perf_counter()
        self._pbar = None
        if bar and _is_terminal():
            self._pbar = tqdm(
                total=self.total, initial=min(initial, self.total), unit="frames", desc=desc, dynamic_ncols=True
            )

    def update(
        self, frames: int, new_frames: int, stats: EpisodeStats | None = None, extra: dict[str, str] | None = None
    ) -> None:
        """After a batch: ``frames`` trained on so far, ``new_frames`` of them from this batch; ``stats`` (episodes,
        success, return) and/or ``extra`` (name -> shown text) describe the run so far."""
        shown = {}
        if stats is not None:
            shown = {
                "episodes": str(stats.episodes),
                "success": format_rate(stats.success_rate),
                "return": format_rate(stats.mean_return),
            }
        shown.update(extra or {})
        if self._pbar is not None:
            # a last batch may end past the planned total (a stop condition never does): never past 100 %
            self._pbar.update(max(min(frames, self.total) - self._pbar.n, 0))
            self._pbar.set_postfix(shown)
            return
        now = time.perf_counter()
        if self._last_log is not None and now - self._last_log < self.interval_s:
            return
        fps = (frames - self._frames_at_log) / max(now - self._t_at_log, 1e-9)
        details = "".join(f" | {k} {v}" for k, v in shown.items())
        logger.info(
            "frames %d/%d (%.0f%%) | %.0f frames/s%s",
            frames,
            self.total,
            min(100.0, 100.0 * frames / self.total),
            fps,
            details,
        )
        self._last_log = self._t_at_log = now
        self._frames_at_log = frames

    def close(self) -> None:
        if self._pbar is not None:
            self._pbar.close()


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, inf) as ``None``, so ``json.dumps`` writes valid JSON (``null``)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def _recent_label(rows: list[dict], window: int | None) -> str:
    """What the windowed columns average over: ``(last 100 episodes)`` only once 100 episodes exist."""
    if not window:
        return "(recent episodes)"
    episodes = int(rows[-1].get("episodes") or 0) if rows else 0
    if episodes >= window:
        return f"(last {window} episodes)"
    return f"(all {episodes} episodes so far, < {window})"


def _finite_points(rows: list[dict], key: str) -> tuple[list, list]:
    pts = [
        (r["frames"], float(r[key]))
        for r in rows
        if isinstance(r.get(key), (int, float)) and math.isfinite(float(r[key]))
    ]
    return ([p[0] for p in pts], [p[1] for p in pts]) if pts else ([], [])


#: the return series of a collector-based run's progress rows: (column, legend label or None)
RETURN_SERIES: tuple[tuple[str, str | None], ...] = (("return_mean", None),)


def plot_learning_curve(
    rows: list[dict],
    path: Path,
    title: str = "",
    window: int | None = None,
    *,
    returns: tuple[tuple[str, str | None], ...] = RETURN_SERIES,
    return_label: str | None = None,
) -> None:
    """Success rate (last-``window`` episodes) over the return series vs frames, two stacked panels, one PNG.

    ``rows``: progress rows with ``frames``, optionally ``episodes`` and ``success_rate``, and the ``returns``
    columns (``(column, legend label)``; NaN or absent values are left out, so a sparse column such as the health
    run's ``eval_return_mean`` draws only its points). ``window``: the episodes ``success_rate`` / ``return_mean``
    average over (``logging.success_window``). The success rate is drawn only from the row at which ``window``
    episodes exist (before that it is "n/a", evaluation-protocol rule), and the axis says "(last N episodes)" only
    then. Without any such success rate only the return panel is drawn, with a note. ``return_label``: the return
    axis label (default "mean return" and the window). Written atomically; a full disk is one FreamerError line.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recent = _recent_label(rows, window)
    full = [r for r in rows if not window or int(r.get("episodes") or 0) >= window]
    s_frames, success = _finite_points(full, "success_rate")
    if success:
        fig, (ax_s, ax_r) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
        ax_s.plot(s_frames, success, color="tab:green", marker="." if len(success) < 30 else None)
        ax_s.axhline(SUCCESS_TARGET, color="grey", ls=":", lw=1, label=f"target {SUCCESS_TARGET:.2f}")
        ax_s.set_ylim(-0.02, 1.02)
        ax_s.set_ylabel(f"success rate\n{recent}")
        ax_s.legend(loc="lower right", frameon=False)
        ax_s.grid(alpha=0.3)
        ax_s.set_title(title)
    else:
        fig, ax_r = plt.subplots(1, 1, figsize=(7, 3.5))
        ax_r.set_title(title)
        has_any = any(math.isfinite(float(r.get("success_rate", math.nan))) for r in rows)
        note = (
            f"success rate n/a: fewer than {window} episodes so far"
            if has_any
            else "this env reports no success: return only"
        )
        ax_r.text(0.01, 0.97, note, transform=ax_r.transAxes, ha="left", va="top", fontsize=8, color="dimgrey")
    for key, label in returns:
        xs, ys = _finite_points(rows, key)
        if xs:
            ax_r.plot(xs, ys, marker="." if len(xs) < 30 else None, label=label)
    if any(label for _, label in returns) and ax_r.get_lines():
        ax_r.legend(loc="lower right", frameon=False)
    ax_r.set_ylabel(return_label or f"mean return\n{recent}")
    ax_r.set_xlabel("frames")
    ax_r.grid(alpha=0.3)
    fig.tight_layout()
    with run_file_errors(path):
        tmp = path.with_suffix(".tmp.png")
        try:
            fig.savefig(tmp, dpi=100)
            os.replace(tmp, path)
        finally:
            plt.close(fig)
            tmp.unlink(missing_ok=True)


class LogMeans:
    """Running means of per-step logs (losses, grad norms) over the steps of one batch: ``add(logs)`` per step,
    ``means(prefix)`` at the end. Tensors are detached and read once per value (one host sync per entry)."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def add(self, logs: dict[str, Any]) -> None:
        for k, v in logs.items():
            self.sums[k] = self.sums.get(k, 0.0) + float(v.detach() if torch.is_tensor(v) else v)
            self.counts[k] = self.counts.get(k, 0) + 1

    def means(self, prefix: str = "") -> dict[str, float]:
        return {f"{prefix}{k}": s / self.counts[k] for k, s in self.sums.items()}
