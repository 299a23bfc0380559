"""Tables and plots of a benchmark suite (:mod:`freamer_rl.experiments.suite`), rebuilt from its run folders alone.

Each run folder holds what its trainer wrote (``progress.csv``, ``summary.json``) plus the suite's markers:
``done.json`` (written when the trainer returned; its ``total_frames`` is the budget it was trained for) and
``failed.txt`` (the error line of the last failed attempt). :func:`write_report` turns them into ``runs.csv``,
``summary.csv`` / ``summary.md``, ``curves.csv`` and ``curve_<env>_<metric>.png`` (mean across seeds with a min-max
band). Runs whose ``summary.json`` holds the health trainer's evaluation (:data:`HEALTH_METRICS`) add the paper's
Table 15 to ``summary.md``: per label, mean +- sample std across seeds.

A chain entry's run (:attr:`RunRecord.stages` set) holds one folder per stage; its row counts frames, episodes,
wall time and frames / episodes to 80% and 95% across the stages (the earlier stages' totals plus the last stage's), takes
its final metrics from the last stage, and its curve is the last stage's with frames and episodes shifted by the
earlier stages'. ``summary.md`` marks its label ``(chain)``.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import statistics
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freamer_rl.experiments.chain_report import chain_stage_markdown
from freamer_rl.experiments.health_table import (
    HEALTH_METRICS,
    HEALTH_REFERENCES,
    health_markdown,
    health_summary,
    loso_markdown,
)
from freamer_rl.experiments.learning_compare import learning_compare_markdown
from freamer_rl.experiments.stats import iqm_ci
from freamer_rl.experiments.stats import is_missing as _missing
from freamer_rl.run.checkpoint import atomic_write_text
from freamer_rl.run.metrics import SUCCESS_LEVELS
from freamer_rl.run.rundir import write_rows_csv

logger = logging.getLogger(__name__)

__all__ = [
    "DONE_NAME",
    "FAILED_NAME",
    "HEALTH_METRICS",
    "PLOT_METRICS",
    "RunRecord",
    "band_curves",
    "failed_line",
    "mean_std",
    "plot_bands",
    "read_json",
    "read_run",
    "run_status",
    "write_report",
]

DONE_NAME = "done.json"
FAILED_NAME = "failed.txt"
#: progress.csv columns copied into curves.csv (those a run has); the last three are plotted where present
CURVE_KEYS = ("episodes", "success_rate", "return_mean", "crafter_score")
PLOT_METRICS = ("success_rate", "return_mean", "crafter_score")
#: summary.json's frames / episodes to each of SUCCESS_LEVELS (run.metrics.EpisodeStats: the exact episode at which the
#: trailing 100-episode success rate first reaches the level), the only definition the reports use
LEVEL_KEYS = tuple(f"{kind}_to_{round(100 * lv)}" for lv in SUCCESS_LEVELS for kind in ("frames", "episodes"))
#: the same for the windowed mean return reaching ``logging.return_target`` (runs that set one)
RETURN_KEYS = ("return_target", "frames_to_return", "episodes_to_return")
#: final metrics: (runs.csv column, summary.json key, progress.csv column)
FINAL_METRICS = (
    ("success_rate", "final_success_rate", "success_rate"),
    ("return_mean", "final_return_mean", "return_mean"),
    ("crafter_score", "crafter_score", "crafter_score"),
)


# -- helpers -----------------------------------------------------------------------------------------------------
def mean_std(values: list, empty: str = "n/a") -> str:
    """``"mean ± sample std"`` of the values that are not None/NaN (one value: itself; none: ``empty``)."""
    vals = [v for v in values if not _missing(v)]
    if not vals:
        return empty
    if len(vals) == 1:
        return f"{vals[0]:,.2f}"
    return f"{statistics.mean(vals):,.2f} ± {statistics.stdev(vals):,.2f}"


def _as_float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def band_curves(runs: list[dict], y_key: str, x_key: str = "frames", points: int = 200) -> tuple:
    """One method's seeds (``runs``: dicts with ``rows`` and optionally ``finished``) on a common x grid: ``(grid
    [points], ys [len(runs), points])``. The grid ends at the shortest unfinished run; a finished run that stopped
    early (at its success target) holds its last value up to the longest run, so the mean of an arm whose seeds stop
    at different frames does not end at the first seed's stop. Rows without ``y_key`` count as NaN; before a run's
    first value its row is NaN."""
    ends = [_as_float(r["rows"][-1][x_key]) for r in runs]
    open_ends = [x for x, r in zip(ends, runs) if not r.get("finished")]
    grid = np.linspace(0, min(open_ends) if open_ends else max(ends), points)
    ys = []
    for r in runs:
        xs = np.array([_as_float(row[x_key]) for row in r["rows"]], dtype=float)
        vs = np.array([_as_float(row.get(y_key)) for row in r["rows"]], dtype=float)
        ok = ~np.isnan(vs)
        # np.interp holds the last value past a run's end: only a finished run reaches past it (the grid above)
        ys.append(np.interp(grid, xs[ok], vs[ok], left=np.nan) if ok.any() else np.full_like(grid, np.nan))
    return grid, np.array(ys)


def plot_bands(
    results: list[dict],
    path: Path,
    y_key: str,
    title: str,
    *,
    x_key: str = "frames",
    target: float | None = None,
    ylabel: str | None = None,
    colors: dict | None = None,
    order: list[str] | None = None,
) -> None:
    """Per method (``results``: dicts with ``method``, ``rows`` and optionally ``finished``): the mean curve across
    seeds with a min-max band, the seeds on one grid by :func:`band_curves`. ``order``: the methods' order (default
    sorted)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    methods = order if order is not None else sorted({r["method"] for r in results})
    for i, m in enumerate(methods):
        runs = [r for r in results if r["method"] == m and r["rows"]]
        if not runs:
            continue
        grid, ys = band_curves(runs, y_key, x_key)
        if np.isnan(ys).all():
            continue
        color = (colors or {}).get(m, f"C{i}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN grid points before a seed's first episode
            ax.plot(grid, np.nanmean(ys, axis=0), color=color, label=f"{m} (mean of {len(runs)} seeds)")
            ax.fill_between(grid, np.nanmin(ys, axis=0), np.nanmax(ys, axis=0), color=color, alpha=0.2, lw=0)
    if target is not None:
        ax.axhline(target, color="k", ls=":", lw=0.8)
    ax.set_xlabel(x_key)
    ax.set_ylabel(ylabel or y_key)
    ax.set_title(title, fontsize=9)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# -- reading run folders -----------------------------------------------------------------------------------------------
@dataclass
class RunRecord:
    """What the report needs of one run: where it is and what it is (from the suite plan)."""

    label: str
    env: str
    env_dir: str
    seed: int
    run_dir: Path
    target_frames: int | None = None
    error: str | None = None  # a problem found before the run started (its config does not load)
    stages: list[str] | None = None  # a chain entry's run: its stages' folder names in order; None: one recipe

    @property
    def tag(self) -> str:
        """``label/env/seed<k>``: how logs and results name the run."""
        return f"{self.label}/{self.env}/seed{self.seed}"


def read_json(path: Path) -> dict | None:
    """A JSON object file, or None when it is missing, unreadable or not an object."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _read_progress(path: Path) -> list[dict]:
    """progress.csv rows as floats ([] when absent); rows without a number in ``frames`` are dropped."""
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        rows = [{k: _as_float(v) for k, v in r.items() if k} for r in csv.DictReader(f)]
    return [r for r in rows if not math.isnan(r.get("frames", math.nan))]


def _stage_views(run_dir: Path, stages: list[str]) -> list[tuple[dict, list[dict], int, int]]:
    """Per stage of a chain run, in order: its summary.json (``{}`` before it finished), progress rows, frames and
    episodes so far."""
    views = []
    for name in stages:
        summary = read_json(run_dir / name / "summary.json") or {}
        rows = _read_progress(run_dir / name / "progress.csv")
        last = rows[-1] if rows else {}
        frames = max(
            [f for f in (_as_float(summary.get("frames")), last.get("frames", math.nan)) if not math.isnan(f)] or [0]
        )
        episodes = summary.get("episodes", last.get("episodes"))
        views.append((summary, rows, int(frames), 0 if _missing(episodes) else int(episodes)))
    return views


def _chain_view(rec: RunRecord) -> tuple[dict, list[dict]]:
    """A chain run as one run: a summary-like dict counted across the stages and the last stage's shifted curve."""
    views = _stage_views(rec.run_dir, rec.stages or [])
    if not views:
        return {}, []
    frames_before = sum(v[2] for v in views[:-1])
    episodes_before = sum(v[3] for v in views[:-1])
    last, rows, _, _ = views[-1]
    kept = ("final_success_rate", "final_return_mean", "crafter_score", "trainable_params")
    summary = {k: v for k, v in last.items() if k in kept}
    privileged = sorted({p for v in views for p in v[0].get("privileged") or []})  # any stage's
    if privileged:
        summary["privileged"] = privileged
    summary["episodes"] = episodes_before + views[-1][3]
    for key in LEVEL_KEYS:
        if key in last:
            before = frames_before if key.startswith("frames") else episodes_before
            summary[key] = None if _missing(last[key]) else before + int(last[key])
    walls = [_as_float(v[0].get("wall_time_s")) for v in views]
    if not any(math.isnan(w) for w in walls) and sum(walls) > 0:
        summary["wall_time_s"] = sum(walls)
        summary["fps"] = (frames_before + views[-1][2]) / sum(walls)
    shift = {"frames": frames_before, "episodes": episodes_before}
    return summary, [{k: v + shift.get(k, 0) for k, v in row.items()} for row in rows]


def run_status(run_dir: Path, target_frames: int | None, stages: list[str] | None = None) -> tuple[str, int]:
    """``(status, frames)``: ``done`` (finished for this budget), ``failed`` (last attempt), ``partial``, ``new``.
    ``stages``: a chain run's stage folders (frames are counted across them)."""
    summary = (read_json(run_dir / "summary.json") or {}) if stages is None else {}
    done = read_json(run_dir / DONE_NAME)
    frames = int(_as_float(summary.get("frames")) if summary.get("frames") is not None else 0)
    if stages is not None:
        frames = sum(v[2] for v in _stage_views(run_dir, stages))
    if done is not None:
        budget = done.get("total_frames")
        if target_frames is None or budget is None or budget >= target_frames:
            return "done", int(done.get("frames") or frames)
    if target_frames is not None and summary and frames >= target_frames:
        return "done", frames
    rows = _read_progress(run_dir / "progress.csv")
    frames = int(rows[-1]["frames"]) if rows else frames
    if (run_dir / FAILED_NAME).is_file():
        return "failed", frames
    return ("partial" if frames else "new"), frames


def failed_line(run_dir: Path) -> str:
    """The error line a failed attempt left in ``failed.txt``."""
    try:
        lines = (run_dir / FAILED_NAME).read_text().strip().splitlines()
    except OSError:
        lines = []
    return lines[0] if lines else "failed (no error recorded)"


def _final(summary: dict, last: dict, skey: str, pkey: str) -> float | None:
    v = summary.get(skey)
    if _missing(v):
        v = last.get(pkey)
    return None if _missing(v) else float(v)


def read_run(rec: RunRecord) -> dict[str, Any]:
    """One runs.csv row (plus ``rows``: its progress curve) from the run folder."""
    status, frames = ("failed", 0) if rec.error else run_status(rec.run_dir, rec.target_frames, rec.stages)
    if rec.stages is not None:
        summary, rows = _chain_view(rec)
        summary = summary if status == "done" else {}
    else:
        summary = (read_json(rec.run_dir / "summary.json") or {}) if status == "done" else {}
        rows = _read_progress(rec.run_dir / "progress.csv")
    last = rows[-1] if rows else {}
    error = rec.error if rec.error or status != "failed" else failed_line(rec.run_dir)
    out: dict[str, Any] = {
        "label": rec.label,
        "env": rec.env,
        "seed": rec.seed,
        "status": status,
        "frames": frames,
        "episodes": summary.get("episodes", last.get("episodes")),
    }
    for col, skey, pkey in FINAL_METRICS:
        out[col] = _final(summary, last, skey, pkey)
    for key in (*LEVEL_KEYS, *RETURN_KEYS):
        out[key] = summary.get(key)
    out["trainable_params"] = summary.get("trainable_params")
    out["privileged"] = " ".join(summary.get("privileged") or [])  # settings that read what the agent cannot see
    # a summary.json older than a level's record (frames_to_80 came later) does not know it: "n/a", not "not reached"
    out["levels_unknown"] = sorted(k for k in LEVEL_KEYS if summary and k not in summary)
    fps, wall = summary.get("fps"), summary.get("wall_time_s")
    out["fps"] = None if _missing(fps) else round(float(fps), 1)
    out["wall_time_s"] = None if _missing(wall) else round(float(wall), 1)
    out["episodes"] = None if _missing(out["episodes"]) else int(out["episodes"])
    for key in (*(k for k, _, _ in HEALTH_METRICS), *HEALTH_REFERENCES, "params_encoder"):
        out[key] = None if _missing(summary.get(key)) else summary[key]
    out["encoder"] = summary.get("encoder")  # health runs: the encoder kind and the held-out subjects (LOSO rows)
    out["eval_subjects"] = " ".join(str(s) for s in summary.get("eval_subjects") or [])
    out.update(error=error, run_dir=str(rec.run_dir), env_dir=rec.env_dir, chain=rec.stages is not None, rows=rows)
    out["stages"] = rec.stages  # a chain run's stage folders (the per-stage table), not a runs.csv column
    return out


# -- tables --------------------------------------------------------------------------------------------------------
RUN_FIELDS = [
    "label",
    "env",
    "seed",
    "status",
    "frames",
    "episodes",
    "success_rate",
    "return_mean",
    *LEVEL_KEYS,
    *RETURN_KEYS,
    "crafter_score",
    "fps",
    "wall_time_s",
    "trainable_params",
    "privileged",
    "error",
    "run_dir",
]


def _spread(values: list[float]) -> tuple[float | None, float | None, float | None]:
    vals = [v for v in values if not _missing(v)]
    if not vals:
        return None, None, None
    return statistics.mean(vals), min(vals), max(vals)


def _per_seed(runs: list[dict], key: str) -> str:
    """``"1,234 / 2,004 / — / n/a"``: one value per done seed, ``—`` where the run never reached the target, ``n/a``
    where its summary.json predates the key."""

    def cell(r: dict) -> str:
        if key in r.get("levels_unknown", ()):
            return "n/a"
        return "—" if r.get(key) is None else f"{int(r[key]):,}"

    return " / ".join(cell(r) for r in runs)


def _group(results: list[dict]) -> dict[tuple[str, str], list[dict]]:
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in results:
        groups.setdefault((r["label"], r["env"]), []).append(r)
    return groups


def summary_rows(results: list[dict]) -> list[dict[str, Any]]:
    """Per label x env: the seeds done and, across them, mean / min / max of each final metric."""
    out = []
    for (label, env), runs in _group(results).items():
        done = [r for r in runs if r["status"] == "done"]
        row: dict[str, Any] = {
            "label": label,
            "env": env,
            "seeds_done": len(done),
            "seeds": len(runs),
            "done_seeds": " ".join(str(r["seed"]) for r in done),
            "failed": sum(r["status"] == "failed" for r in runs),
            "chain": any(r.get("chain") for r in runs),
            "privileged": " ".join(sorted({r["privileged"] for r in done if r.get("privileged")})),
        }
        for key in ("frames", "success_rate", "return_mean", "crafter_score", "fps", "trainable_params"):
            row[f"{key}_mean"], row[f"{key}_min"], row[f"{key}_max"] = _spread([r.get(key) for r in done])
        row["crafter_score_per_seed"] = " / ".join(
            "—" if _missing(r.get("crafter_score")) else f"{r['crafter_score']:.2f}" for r in done
        )
        row.update(health_summary(done, env))
        targets = {r.get("return_target") for r in done} - {None}
        row["return_target"] = targets.pop() if len(targets) == 1 else None  # mixed targets: no column
        for key in (*LEVEL_KEYS, "frames_to_return"):
            reached = [r[key] for r in done if r.get(key) is not None]
            known = all(key not in r.get("levels_unknown", ()) for r in done)
            known = known and (key != "frames_to_return" or row["return_target"] is not None)
            row[f"{key}_mean"] = statistics.mean(reached) if reached and known else None
            row[f"{key}_reached"] = len(reached) if known else None
            row[f"{key}_per_seed"] = _per_seed(done, key)
        _add_iqm(row, env, "success_rate", [r.get("success_rate") for r in done])
        _add_iqm(row, env, "return_mean", [r.get("return_mean") for r in done])
        row["return_mean_per_seed"] = " / ".join(
            "—" if _missing(r.get("return_mean")) else f"{r['return_mean']:.2f}" for r in done
        )
        # episodes and frames to 95%: only when every seed reached it (an IQM of the reached ones would flatter the arm)
        for key in ("episodes_to_95", "frames_to_95"):
            every = row[f"{key}_reached"] == len(done)
            _add_iqm(row, env, key, [r.get(key) for r in done] if every else [])
        out.append(row)
    return out


def _add_iqm(row: dict, env: str, key: str, values: list) -> None:
    """``<key>_iqm`` / ``_iqm_low`` / ``_iqm_high``: IQM over the seeds with its 95% stratified-bootstrap interval
    (:func:`freamer_rl.experiments.stats.iqm_ci`); None without values."""
    vals = [float(v) for v in values if not _missing(v)]
    point, low, high = iqm_ci({env: vals}) if vals else (None, None, None)
    row[f"{key}_iqm"], row[f"{key}_iqm_low"], row[f"{key}_iqm_high"] = point, low, high


def _cell(row: dict, key: str, digits: int) -> str:
    mean, lo, hi = row[f"{key}_mean"], row[f"{key}_min"], row[f"{key}_max"]
    if mean is None:
        return ""
    if lo == hi:
        return f"{mean:,.{digits}f}"
    return f"{mean:,.{digits}f} ({lo:,.{digits}f}–{hi:,.{digits}f})"


def _iqm_cell(row: dict, key: str, digits: int) -> str:
    """``"IQM [low, high]"``; for episodes to 95% without every seed reaching it, how many did."""
    if not row["seeds_done"]:
        return ""
    point = row[f"{key}_iqm"]
    if point is None:
        reached = row.get(f"{key}_reached")
        return "" if reached is None else f"{reached}/{row['seeds_done']} seeds reached"
    return f"{point:,.{digits}f} [{row[f'{key}_iqm_low']:,.{digits}f}, {row[f'{key}_iqm_high']:,.{digits}f}]"


def _to95(row: dict, key: str) -> str:
    if not row["seeds_done"]:
        return ""
    mean = row[f"{key}_mean"]
    head = "n/a" if row[f"{key}_reached"] is None else "not reached" if mean is None else f"{mean:,.0f}"
    return f"{head} [{row[f'{key}_per_seed']}]"


def summary_markdown(name: str, rows: list[dict], results: list[dict], compare: list[list[str]] | None = None) -> str:
    """summary.md: the per-arm table, then the chain stages, the ``compare`` pairs, health tables, failures."""
    has_crafter = any(r["crafter_score_mean"] is not None for r in rows)
    # envs without a notion of success (Crafter, CartPole): no success or to-95% columns
    has_success = any(r["success_rate_mean"] is not None for r in rows)
    head = ["label", "env", "seeds done", "frames"] + (["final success"] if has_success else []) + ["final return"]
    head += ["Crafter score [per seed]"] if has_crafter else []
    head += (
        ["episodes to 95% [per seed]", "frames to 95% [per seed]", "frames to 80% [per seed]"] if has_success else []
    )
    targets = sorted({r["return_target"] for r in rows if r.get("return_target") is not None})
    head += [f"frames to return {t:g} [per seed]" for t in targets]
    head += ["frames/s", "trainable params"]
    head += (
        ["final success IQM [95% CI]", "episodes to 95% IQM [95% CI]", "frames to 95% IQM [95% CI]"]
        if has_success
        else []
    )
    head += [] if has_success else ["final return IQM [95% CI] [per seed]"]
    note = (
        "Final values: mean (min–max) across the seeds done; to X%: the exact episode (and its frame) at which the "
        "trailing 100-episode success rate first reached X, as the mean of the seeds that reached it, then each "
        "seed's value (— not reached; n/a: its summary.json predates the record); frames to return: the same for "
        "the trailing 100-episode mean return. IQM: interquartile mean over the seeds done with a 95% "
        "stratified-bootstrap interval (episodes and frames to 95% only when every seed reached it)."
    )
    lines = [
        f"# Suite {name}",
        "",
        note,
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * 2 + "---:|" * (len(head) - 2),
    ]
    for r in rows:
        seeds = f"{r['seeds_done']}/{r['seeds']}" + (f" ({r['done_seeds']})" if r["done_seeds"] else "")
        label = f"{r['label']} (chain)" if r.get("chain") else r["label"]
        label += " (privileged)" if r.get("privileged") else ""
        cells = [label, r["env"], seeds, _cell(r, "frames", 0)]
        cells += [_cell(r, "success_rate", 3)] if has_success else []
        cells += [_cell(r, "return_mean", 2)]
        cells += [f"{_cell(r, 'crafter_score', 2)} [{r['crafter_score_per_seed']}]"] if has_crafter else []
        cells += [_to95(r, k) for k in ("episodes_to_95", "frames_to_95", "frames_to_80")] if has_success else []
        cells += [_to95(r, "frames_to_return") if r.get("return_target") == t else "" for t in targets]
        cells += [_cell(r, "fps", 0), _cell(r, "trainable_params", 0)]
        if has_success:
            cells += [_iqm_cell(r, k, d) for k, d in (("success_rate", 3), ("episodes_to_95", 0), ("frames_to_95", 0))]
        if not has_success:  # tasks scored by their return (CartPole, Pendulum, Crafter): its IQM and every seed's
            cells += [f"{_iqm_cell(r, 'return_mean', 2)} [{r['return_mean_per_seed']}]" if r["seeds_done"] else ""]
        lines.append("| " + " | ".join(cells) + " |")
    if any(r.get("chain") for r in rows):
        lines += [
            "",
            "(chain): a curriculum chain; its frames, episodes and to-95% values are counted across all its stages, "
            "its final values are its last stage's (the env shown).",
        ]
        lines += chain_stage_markdown(results)
    privileged = [r for r in rows if r.get("privileged")]
    if privileged:
        lines += [
            "",
            "(privileged): the arm reads what the agent cannot observe, so it is not a like-for-like comparison:",
        ]
        lines += [f"- {r['label']}: {r['privileged']}" for r in privileged]
    lines += learning_compare_markdown(results, compare or [])
    lines += health_markdown(rows)
    lines += loso_markdown(results)
    failed = [r for r in results if r["status"] == "failed"]
    if failed:
        lines += ["", "## Failed runs", ""]
        lines += [f"- {r['label']} / {r['env']} / seed {r['seed']}: {r['error']}" for r in failed]
    pending = [r for r in results if r["status"] in ("partial", "new")]
    if pending:
        items = [
            f"{r['label']} / {r['env']} / seed {r['seed']} ({r['status']}, {r['frames']:,} frames)" for r in pending
        ]
        lines += ["", f"Not finished: {'; '.join(items)}."]
    return "\n".join(lines) + "\n"


# -- the report ----------------------------------------------------------------------------------------------------
def _curve_rows(results: list[dict]) -> list[dict]:
    keys = [k for k in CURVE_KEYS if any(k in row for r in results for row in r["rows"])]
    return [
        {
            "label": r["label"],
            "env": r["env"],
            "seed": r["seed"],
            "frames": int(row["frames"]),
            **{k: row.get(k) for k in keys},
        }
        for r in results
        for row in r["rows"]
    ]


def _plots(output: Path, results: list[dict], labels: list[str]) -> list[Path]:
    written = []
    for env_dir in dict.fromkeys(r["env_dir"] for r in results):
        runs = [
            {"method": r["label"], "rows": r["rows"], "finished": r["status"] == "done"}
            for r in results
            if r["env_dir"] == env_dir
        ]
        env = next(r["env"] for r in results if r["env_dir"] == env_dir)
        for metric in PLOT_METRICS:
            if not any(not _missing(row.get(metric)) for run in runs for row in run["rows"]):
                continue
            path = output / f"curve_{env_dir}_{metric}.png"
            target = 0.95 if metric == "success_rate" else None
            plot_bands(
                runs,
                path,
                metric,
                f"{env}: {metric}\nmean, min-max across seeds; a seed stopped at its target holds its last value",
                target=target,
                order=[lb for lb in labels if any(run["method"] == lb for run in runs)],
            )
            written.append(path)
    return written


def write_report(
    output: Path, name: str, records: list[RunRecord], compare: list[list[str]] | None = None
) -> list[dict[str, Any]]:
    """Write runs.csv, summary.csv, summary.md, curves.csv and the curve PNGs into ``output``; returns runs.csv's
    rows (with each run's ``rows``). ``compare``: pairs of labels for summary.md's "Comparisons" section."""
    output.mkdir(parents=True, exist_ok=True)
    results = [read_run(rec) for rec in records]
    health = [
        k
        for k in (*(k for k, _, _ in HEALTH_METRICS), *HEALTH_REFERENCES)
        if any(r.get(k) is not None for r in results)
    ]
    health += ["params_encoder", "encoder", "eval_subjects"] if health else []
    write_rows_csv(output / "runs.csv", results, fields=RUN_FIELDS[:-2] + health + RUN_FIELDS[-2:])
    rows = summary_rows(results)
    write_rows_csv(output / "summary.csv", [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows])
    atomic_write_text(output / "summary.md", summary_markdown(name, rows, results, compare or []))
    curves = _curve_rows(results)
    write_rows_csv(output / "curves.csv", curves, fields=list(curves[0]) if curves else None)
    plots = _plots(output, results, list(dict.fromkeys(rec.label for rec in records)))
    logger.info("suite %s: report in %s (%d runs, %d plots)", name, output, len(results), len(plots))
    return results
