"""The health section of a suite's ``summary.md`` (paper Table 15), from the runs whose ``summary.json`` holds the
health trainer's evaluation: per label, each :data:`HEALTH_METRICS` value as mean +- sample std across seeds, the
encoder's parameters, the reward's mean with a 95% bootstrap interval, per-seed values and the ratio of mean rewards
to the first label's with its interval. :mod:`freamer_rl.experiments.report` calls :func:`health_summary` per label
and :func:`health_markdown` for the section, and :func:`loso_markdown` for the leave-one-subject-out overall rows."""

from __future__ import annotations

import statistics
from typing import Any

import numpy as np

from freamer_rl.experiments.stats import is_missing, mean_ratio_ci, stratified_bootstrap_ci, task_mean_ci

__all__ = ["HEALTH_METRICS", "health_markdown", "health_summary", "loso_markdown"]

#: the health trainer's summary.json metrics (paper Table 15): (key, column, digits); ``params_encoder`` beside them
HEALTH_METRICS = (
    ("eval_return_mean", "Reward", 1),
    ("eval_violations_mean", "Violations", 2),
    ("recon_mse", "MSE", 3),
    ("imagination_horizon", "Horizon", 1),
    # the run's return over the oracle planner's / the heart-rate rule's on the same episodes (eval.references)
    ("eval_fraction_of_oracle", "of oracle", 3),
    ("eval_vs_hr_threshold", "/ HR rule", 3),
    # does the world model rank the held actions as the real env does (freamer_rl.health.oracle.action_ranking)
    ("eval_action_rank_spearman", "Rank rho", 2),
    ("eval_action_rank_top1", "Top-1", 2),
)


def health_summary(done: list[dict], env: str) -> dict[str, Any]:
    """One label's health columns over its finished runs ``done`` (runs.csv rows): ``<metric>_mean`` / ``_std``,
    the reward's bootstrap interval ``eval_return_ci_low`` / ``_high`` and ``eval_return_per_seed``; the per-seed
    rewards under the private ``_eval_return_values`` (for the ratios; not a CSV column)."""
    row: dict[str, Any] = {}
    for key in (*(k for k, _, _ in HEALTH_METRICS), "params_encoder"):
        vals = [float(r[key]) for r in done if not is_missing(r.get(key))]
        row[f"{key}_mean"] = statistics.mean(vals) if vals else None
        row[f"{key}_std"] = statistics.stdev(vals) if len(vals) > 1 else (0.0 if vals else None)
    rewards = [float(r["eval_return_mean"]) for r in done if not is_missing(r.get("eval_return_mean"))]
    row["_eval_return_values"] = rewards
    ci = stratified_bootstrap_ci({env: rewards}, np.mean) if rewards else (None, None, None)
    row["eval_return_ci_low"], row["eval_return_ci_high"] = ci[1], ci[2]
    row["eval_return_per_seed"] = " / ".join(f"{v:.1f}" for v in rewards)
    return row


def _health_reward_cells(row: dict, first: dict) -> list[str]:
    """Table 15's reward mean [CI], per-seed values and ratio to ``first`` [CI]."""
    mean, low, high = row["eval_return_mean_mean"], row["eval_return_ci_low"], row["eval_return_ci_high"]
    cells = [f"{mean:.1f} [{low:.1f}, {high:.1f}]", row["eval_return_per_seed"]]
    if row is first:
        return [*cells, ""]
    ratio, r_low, r_high = mean_ratio_ci(row["_eval_return_values"], first["_eval_return_values"])
    return [*cells, f"{ratio:.2f} [{r_low:.2f}, {r_high:.2f}]"]


def health_markdown(rows: list[dict]) -> list[str]:
    """The Table 15 section of summary.md (``[]`` when no run has the health evaluation): per label x env, each
    :data:`HEALTH_METRICS` value as mean +- sample std across the seeds done, the encoder's parameters, and the
    reward difference to the first such label."""
    rows = [r for r in rows if r["eval_return_mean_mean"] is not None]
    if not rows:
        return []
    first = rows[0]
    head = [
        "label",
        "seeds done",
        *(col for _, col, _ in HEALTH_METRICS),
        "params (encoder)",
        f"reward vs {first['label']}",
        "reward mean [95% CI]",
        "reward per seed",
        f"reward / {first['label']} [95% CI]",
    ]
    lines = [
        "",
        "## Health world model (paper Table 15)",
        "",
        "Reward: real-env evaluation return per episode; Violations: steps with HR > 160 bpm per episode; MSE: "
        "reconstruction MSE per feature (raw units, held-out episodes); Horizon: open-loop imagined steps before "
        "the reward prediction error exceeds the tolerance; Rank rho / Top-1: Spearman correlation of imagined and real "
        "returns of each action held for the imagination horizon, and how often the imagined best action is a real "
        "best one; of oracle / / HR rule: the return over the oracle planner's / the heart-rate rule's on the same "
        "episodes. Mean +- sample std across the seeds done; the reward's "
        "mean with a 95% bootstrap interval over the seeds, each seed's value, and the ratio of mean rewards to the "
        "first label's with a 95% bootstrap interval (each arm's seeds resampled on their own).",
        "",
        "| " + " | ".join(head) + " |",
        "|---|" + "---:|" * (len(head) - 1),
    ]
    for r in rows:
        cells = [r["label"], str(r["seeds_done"])]
        cells += [
            f"{r[f'{k}_mean']:.{d}f} +- {r[f'{k}_std']:.{d}f}" if r[f"{k}_mean"] is not None else ""
            for k, _, d in HEALTH_METRICS
        ]
        params = r["params_encoder_mean"]
        cells.append("" if params is None else f"{params:,.0f}")
        delta = r["eval_return_mean_mean"] - first["eval_return_mean_mean"]
        cells.append("" if r is first else f"{delta:+.1f}")
        cells += _health_reward_cells(r, first)
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _loso_folds(results: list[dict]) -> dict[str, dict[str, list[float]]]:
    """``{encoder: {held-out subjects: [reward per seed]}}`` over the finished health runs that name their
    evaluation subjects; only encoders evaluated on two or more held-out sets (folds)."""
    folds: dict[str, dict[str, list[float]]] = {}
    for r in results:
        if r["status"] != "done" or is_missing(r.get("eval_return_mean")) or not r.get("eval_subjects"):
            continue
        enc = r.get("encoder") or r["label"]
        folds.setdefault(enc, {}).setdefault(r["eval_subjects"], []).append(float(r["eval_return_mean"]))
    return {enc: f for enc, f in folds.items() if len(f) > 1}


def loso_markdown(results: list[dict]) -> list[str]:
    """The leave-one-subject-out section of summary.md (``[]`` unless some encoder was evaluated on two or more
    held-out subject sets): per encoder, the reward over all folds with a 95% stratified-bootstrap interval (each
    fold's seeds resampled within the fold, so every fold keeps its weight), the folds and seeds done, and each
    fold's mean."""
    folds = _loso_folds(results)
    if not folds:
        return []
    lines = [
        "",
        "## Leave-one-subject-out, overall (per encoder)",
        "",
        "Reward: the real-env evaluation return on the held-out subject, averaged over the folds; 95% stratified "
        "bootstrap interval with the folds as strata. Per fold: held-out subjects = mean over its seeds.",
        "",
        "| encoder | folds | runs | reward [95% CI] | per fold |",
        "|---|---:|---:|---:|---|",
    ]
    for enc, by_fold in folds.items():
        point, low, high = task_mean_ci(by_fold)  # every fold weighs the same, whatever its seeds done
        runs = sum(len(v) for v in by_fold.values())
        per_fold = ", ".join(f"{f}: {np.mean(v):.1f}" for f, v in sorted(by_fold.items()))
        lines.append(f"| {enc} | {len(by_fold)} | {runs} | {point:.1f} [{low:.1f}, {high:.1f}] | {per_fold} |")
    return lines
