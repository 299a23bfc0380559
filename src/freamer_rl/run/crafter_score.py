"""The official Crafter score (Hafner, "Benchmarking the Spectrum of Agent Capabilities", ICLR 2022).

For each achievement ``i`` (22 in Crafter), ``s_i`` is the percentage of *all* episodes so far in which it was
unlocked at least once; the score is the geometric mean with a 1% offset::

    S = exp( mean_i ln(1 + s_i) ) - 1          s_i in percent, S in [0, 100]

so one achievement at 100% and the rest at 0% gives ``101 ** (1/22) - 1 = 0.23``, every achievement at 100% gives 100;
published numbers at 1M steps: random agent 1.6, PPO 4.6, DreamerV2 10.0, human experts 50.5. Achievements with no
defined rate (no episode yet) are left out of the mean, as crafter's own analysis does with ``nanmean``.

:class:`CrafterScore` reads collected TorchRL batches: at every step where ``("next", "done")`` is True, the
``("next", "achievements")`` vector (bool or counts ``[A]``, non-zero = unlocked in this episode so far, the Crafter
adapter's ``"achievements"`` key) is what that episode unlocked. It never imports crafter or the adapters: the
achievement names come from the caller (``freamer_rl_envs.crafter.CRAFTER_ACHIEVEMENTS``).

Files written by :meth:`CrafterScore.write_report` into a run directory:

=============================  ===================================================================================
``crafter_score.json``         score, episodes, success rate (%) and unlocking episodes per achievement
``crafter_achievements.md``    the same as a Markdown table
``crafter_achievements.png``   horizontal bars of the success rates (log scale, 0.01% .. 100%, as in the paper)
=============================  ===================================================================================
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from freamer_rl.run.checkpoint import atomic_write_text

logger = logging.getLogger(__name__)

__all__ = ["CrafterScore", "crafter_score"]

SCORE_JSON = "crafter_score.json"
REPORT_MD = "crafter_achievements.md"
REPORT_PNG = "crafter_achievements.png"
_FORMULA = "exp(mean_i ln(1 + s_i)) - 1, s_i = % of episodes unlocking achievement i"
_LOG_FLOOR = 0.01  # percent: left edge of the log-scale bar chart


def crafter_score(success_rates: Iterable[float]) -> float:
    """``exp(mean_i ln(1 + s_i)) - 1`` over the finite rates ``s_i`` (percent, in ``[0, 100]``); NaN if none.

    Raises:
        ValueError: a rate outside ``[0, 100]`` (rates are percentages; fractions in ``[0, 1]`` cannot be told
            apart and give a far lower score).
    """
    rates = [float(s) for s in success_rates]
    bad = [s for s in rates if not math.isnan(s) and not 0.0 <= s <= 100.0]
    if bad:
        raise ValueError(f"success_rates: expected percentages in [0, 100] (or NaN), got {bad}")
    finite = [s for s in rates if not math.isnan(s)]
    if not finite:
        return math.nan
    return math.exp(sum(math.log1p(s) for s in finite) / len(finite)) - 1.0


class CrafterScore:
    """Per-achievement success rates and the Crafter score over every episode passed to :meth:`update`.

    Args:
        achievement_names: names of the ``A`` entries of the achievements vector, in its order.
        achievements_key: key of the ``[*B, T, A]`` achievements-so-far entry of a collected batch.
        done_key: key of the ``[*B, T, 1]`` (or ``[*B, T]``) episode-end flags.

    State: ``episodes`` (int) and ``unlocked`` (list of ``A`` ints, the episodes that unlocked each achievement).
    """

    def __init__(
        self,
        achievement_names: Sequence[str],
        *,
        achievements_key: str | tuple[str, ...] = ("next", "achievements"),
        done_key: str | tuple[str, ...] = ("next", "done"),
    ) -> None:
        names = tuple(str(n) for n in achievement_names)
        if not names:
            raise ValueError("achievement_names: expected at least one name, got none")
        if len(set(names)) != len(names):
            dupes = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"achievement_names: duplicate names {dupes}")
        self.names = names
        self.achievements_key = achievements_key
        self.done_key = done_key
        self.episodes = 0
        self.unlocked = [0] * len(names)

    def update(self, data: TensorDictBase) -> int:
        """Count the episodes that end in ``data`` (``[*B, T]``, any batch shape); returns how many ended.

        Raises:
            KeyError: ``data`` lacks the achievements or done entry.
            ValueError: the achievements' last dim is not ``A`` or their leading dims differ from the done flags'.
        """
        ach = data.get(self.achievements_key, None)
        done = data.get(self.done_key, None)
        for key, value in ((self.achievements_key, ach), (self.done_key, done)):
            if value is None:
                raise KeyError(f"CrafterScore.update: batch has no {key!r} entry (keys: {list(data.keys(True))})")
        if ach.ndim < 1 or ach.shape[-1] != len(self.names):
            raise ValueError(
                f"CrafterScore.update: {self.achievements_key!r} has shape {tuple(ach.shape)}, expected "
                f"[..., {len(self.names)}] (one entry per achievement name)"
            )
        if done.shape == (*ach.shape[:-1], 1):
            done = done.squeeze(-1)
        if done.shape != ach.shape[:-1]:
            raise ValueError(
                f"CrafterScore.update: {self.done_key!r} has shape {tuple(done.shape)}, expected "
                f"{tuple(ach.shape[:-1])} or {(*ach.shape[:-1], 1)} to match {self.achievements_key!r}"
            )
        ends = ach[done.to(torch.bool)]  # [N, A]
        n = int(ends.shape[0])
        if n:
            counts = (ends != 0).sum(0).tolist()
            self.unlocked = [u + int(c) for u, c in zip(self.unlocked, counts)]
            self.episodes += n
        return n

    def success_rates(self) -> dict[str, float]:
        """``{name: s_i}``, the percentage of episodes so far that unlocked each achievement (NaN before any)."""
        if self.episodes == 0:
            return {name: math.nan for name in self.names}
        return {name: 100.0 * u / self.episodes for name, u in zip(self.names, self.unlocked)}

    def score(self) -> float:
        """The Crafter score of :func:`crafter_score` over :meth:`success_rates` (NaN before any episode)."""
        return crafter_score(self.success_rates().values())

    # -- resume -------------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Plain types only (safe under ``torch.load(weights_only=True)`` and JSON)."""
        return {"names": list(self.names), "episodes": int(self.episodes), "unlocked": [int(u) for u in self.unlocked]}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output.

        Raises:
            ValueError: the state was saved for other achievement names, or is inconsistent.
        """
        missing = {"names", "episodes", "unlocked"} - set(state)
        if missing:
            raise ValueError(f"CrafterScore.load_state_dict: missing entries {sorted(missing)}")
        names, episodes, unlocked = tuple(state["names"]), int(state["episodes"]), [int(u) for u in state["unlocked"]]
        if names != self.names:
            raise ValueError(
                f"CrafterScore.load_state_dict: saved for achievements {list(names)}, this score "
                f"tracks {list(self.names)}"
            )
        if len(unlocked) != len(names) or episodes < 0 or any(not 0 <= u <= episodes for u in unlocked):
            raise ValueError(
                f"CrafterScore.load_state_dict: inconsistent counts (episodes={episodes}, unlocked={unlocked})"
            )
        self.episodes, self.unlocked = episodes, unlocked

    # -- report -------------------------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """What ``crafter_score.json`` holds (NaN written as ``null``)."""
        score = self.score()
        rates = self.success_rates()
        return {
            "score": None if math.isnan(score) else score,
            "episodes": self.episodes,
            "formula": _FORMULA,
            "success_rates_percent": {k: None if math.isnan(v) else v for k, v in rates.items()},
            "unlocked_episodes": dict(zip(self.names, self.unlocked)),
        }

    def write_report(self, run_dir: str | Path, *, log_scale: bool = True) -> dict[str, Path]:
        """Write ``crafter_score.json``, ``crafter_achievements.md`` and ``crafter_achievements.png`` (each replaced
        atomically) into ``run_dir``; returns ``{"json": path, "md": path, "png": path}``."""
        run_dir = Path(run_dir)
        if not run_dir.is_dir():
            raise FileNotFoundError(f"CrafterScore.write_report: run_dir {run_dir} is not a directory")
        paths = {"json": run_dir / SCORE_JSON, "md": run_dir / REPORT_MD, "png": run_dir / REPORT_PNG}
        atomic_write_text(paths["json"], json.dumps(self.summary(), indent=2) + "\n")
        atomic_write_text(paths["md"], self.markdown())
        self.plot(paths["png"], log_scale=log_scale)
        logger.info("Crafter score %.2f over %d episodes: %s", self.score(), self.episodes, paths["md"])
        return paths

    def markdown(self) -> str:
        """The per-achievement table and the score, as Markdown."""
        score = self.score()
        lines = [
            "# Crafter achievements",
            "",
            f"Crafter score: **{_fmt(score)}** over {self.episodes} episodes ({_FORMULA}; random agent 1.6, "
            "human experts 50.5).",
            "",
            "| achievement | episodes unlocked | success rate (%) |",
            "|---|---:|---:|",
        ]
        for (name, rate), count in zip(self.success_rates().items(), self.unlocked):
            lines.append(f"| {name} | {count} | {_fmt(rate)} |")
        return "\n".join(lines) + "\n"

    def plot(self, path: str | Path, *, log_scale: bool = True) -> None:
        """Horizontal bars of the success rates, one per achievement (in name order, top to bottom)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        path = Path(path)
        rates = [0.0 if math.isnan(r) else r for r in self.success_rates().values()]
        ys = list(range(len(rates)))[::-1]
        fig, ax = plt.subplots(figsize=(7, 0.28 * len(rates) + 1.4))
        if log_scale:  # bars from the floor, so 0% shows as no bar instead of an undefined log
            left = _LOG_FLOOR
            widths = [max(r, left) - left for r in rates]
            ax.set_xscale("log")
            ax.set_xlim(left, 100.0)
        else:
            left, widths = 0.0, rates
            ax.set_xlim(0.0, 100.0)
        ax.barh(ys, widths, left=left, color="tab:blue", height=0.7)
        for y, r in zip(ys, rates):  # the value beside its bar, or inside a long one
            inside = r > 50.0
            x = (r / 1.15 if inside else max(r, left) * 1.15) if log_scale else (r - 1.0 if inside else r + 1.0)
            ax.text(
                x,
                y,
                f"{r:.1f}",
                va="center",
                ha="right" if inside else "left",
                fontsize=7,
                color="white" if inside else "black",
            )
        ax.set_yticks(ys, [n.replace("_", " ") for n in self.names], fontsize=8)
        ax.set_xlabel("success rate (%)" + (", log scale" if log_scale else ""))
        ax.set_title(f"Crafter score {_fmt(self.score())} ({self.episodes} episodes)")
        ax.grid(axis="x", alpha=0.3)
        fig.tight_layout()
        tmp = path.with_suffix(".tmp.png")
        fig.savefig(tmp, dpi=100)
        plt.close(fig)
        os.replace(tmp, path)


def _fmt(value: float) -> str:
    return "n/a" if math.isnan(value) else f"{value:.2f}"
