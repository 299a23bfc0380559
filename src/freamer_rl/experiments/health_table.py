"""The health section of a suite's ``summary.md`` (paper Table 15), from the runs whose ``summary.json`` holds the
health trainer's evaluation: per label, each :data:`HEALTH_METRICS` value as mean +- sample std across seeds, the
encoder's parameters, the reward's mean with a 95% bootstrap interval, per-seed values and the ratio of mean rewards
to the first label's with its interval. :mod:`freamer_rl.experiments.report` calls :func:`health_summary` per label
and :func:`health_markdown` for the section, and :func:`loso_markdown` for the leave-one-subject-out overall rows."""

from __future__ import annotations

import math
import statistics
from typing import Any

import numpy as np

from freamer_rl.experiments.stats import is_missing, mean_ratio_ci, stratified_bootstrap_ci, subject_bootstrap_ci

__all__ = ["HEALTH_METRICS", "HEALTH_REFERENCES", "health_markdown", "health_summary", "loso_markdown"]

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


#: the heart-rate rule's and the oracle planner's return on a run's own evaluation episodes (summary.json,
#: eval.references), beside the run's ``eval_return_mean`` in runs.csv and the leave-one-subject-out section
HEALTH_REFERENCES = ("eval_ref_hr_threshold_return", "eval_ref_oracle_return")
#: the heart-rate controller (the rule plus Increase back to plan), where a report scored it (NaN elsewhere)
CONTROLLER_REFERENCE = "eval_ref_hr_controller_return"
LOSO_VALUES = ("eval_return_mean", *HEALTH_REFERENCES, CONTROLLER_REFERENCE)


def _loso_folds(results: list[dict]) -> dict[str, dict[str, list[dict[str, float]]]]:
    """``{encoder: {held-out subjects: [{value: float} per seed]}}`` over the finished health runs that name their
    evaluation subjects (a missing reference is NaN); only encoders evaluated on two or more held-out sets (folds)."""
    folds: dict[str, dict[str, list[dict[str, float]]]] = {}
    for r in results:
        if r["status"] != "done" or is_missing(r.get("eval_return_mean")) or not r.get("eval_subjects"):
            continue
        values = {k: math.nan if is_missing(r.get(k)) else float(r[k]) for k in LOSO_VALUES}
        folds.setdefault(r.get("encoder") or r["label"], {}).setdefault(r["eval_subjects"], []).append(values)
    return {enc: f for enc, f in folds.items() if len(f) > 1}


def _fold_values(by_fold: dict[str, list[dict[str, float]]], value) -> dict[str, list[float]]:
    """``{fold: [value(run) per seed]}``; folds where it is NaN for every seed are left out."""
    out = {f: [value(run) for run in runs] for f, runs in by_fold.items()}
    return {f: [v for v in vals if math.isfinite(v)] for f, vals in out.items() if any(map(math.isfinite, vals))}


def _ci_cell(scores: dict[str, list[float]], digits: int = 1) -> str:
    if not scores:
        return ""
    point, low, high = subject_bootstrap_ci(scores)
    return f"{point:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def _loso_row(enc: str, by_fold: dict[str, list[dict[str, float]]]) -> str:
    """One encoder's overall row: reward, the rule and the oracle on the same episodes, the paired difference to the
    rule (and to the heart-rate controller, where scored) and the fraction of the oracle (each a mean over folds with
    its subject bootstrap), folds at or above the rule, and each fold's mean reward / rule."""
    reward = _fold_values(by_fold, lambda r: r["eval_return_mean"])
    rule = _fold_values(by_fold, lambda r: r["eval_ref_hr_threshold_return"])
    oracle = _fold_values(by_fold, lambda r: r["eval_ref_oracle_return"])
    vs_rule = _fold_values(by_fold, lambda r: r["eval_return_mean"] - r["eval_ref_hr_threshold_return"])
    vs_controller = _fold_values(by_fold, lambda r: r["eval_return_mean"] - r[CONTROLLER_REFERENCE])
    of_oracle = _fold_values(by_fold, lambda r: r["eval_return_mean"] / r["eval_ref_oracle_return"])
    at_rule = sum(np.mean(v) >= 0 for v in vs_rule.values())
    per_fold = ", ".join(
        f"{f}: {np.mean(reward[f]):.1f}" + (f" / {np.mean(rule[f]):.1f}" if f in rule else "") for f in sorted(reward)
    )
    runs = sum(len(v) for v in by_fold.values())
    cells = [enc, str(len(by_fold)), str(runs), _ci_cell(reward), _ci_cell(rule), _ci_cell(oracle)]
    cells += [_ci_cell(vs_rule), _ci_cell(vs_controller), _ci_cell(of_oracle, 3)]
    cells += [f"{at_rule}/{len(vs_rule)}" if vs_rule else "", per_fold]
    return "| " + " | ".join(cells) + " |"


def loso_markdown(results: list[dict]) -> list[str]:
    """The leave-one-subject-out section of summary.md (``[]`` unless some encoder was evaluated on two or more
    held-out subject sets): per encoder, one :func:`_loso_row`. Every interval is a two-level bootstrap
    (:func:`~freamer_rl.experiments.stats.subject_bootstrap_ci`: the held-out subjects resampled, then each one's
    seeds), so it says how the encoder would do on a new subject, not only on a new seed of these nine."""
    folds = _loso_folds(results)
    if not folds:
        return []
    lines = [
        "",
        "## Leave-one-subject-out, overall (per encoder)",
        "",
        "Reward: the real-env evaluation return on the held-out subject; HR rule / oracle: the heart-rate rule's and "
        "the oracle planner's return on the same episodes; - HR rule: the paired difference; of oracle: reward / "
        "oracle; - controller: the paired difference to the heart-rate controller (the rule plus Increase back to plan "
        "below 145 bpm; empty where not scored). Each a mean over the folds (every fold weighs the same) with a 95% "
        "two-level bootstrap interval (folds resampled, then each fold's seeds). At >= rule: folds whose mean reward "
        "is at or above the rule's. "
        "Per fold: held-out subjects: mean reward / mean HR rule over its seeds.",
        "",
        "| encoder | folds | runs | reward [95% CI] | HR rule | oracle | - HR rule [95% CI] | - controller [95% CI] "
        "| of oracle [95% CI] | at >= rule | per fold |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    return lines + [_loso_row(enc, by_fold) for enc, by_fold in folds.items()]
