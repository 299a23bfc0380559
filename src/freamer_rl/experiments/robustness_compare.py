"""Probability of improvement between a robustness suite's named arms (``evaluate.compare``), read from the rows of
``robustness.csv`` (:func:`freamer_rl.experiments.robustness.robustness_rows`).

Two quantities can be compared (``evaluate.compare_on``): ``R``, the share of its own clean score a run keeps under a
corrupted condition (the question for a policy trained clean: does it lose less?), and ``score``, the evaluation
score itself under every condition, the clean one included (the question when the corruption was part of training:
R divides by a clean score the arms reach at different speeds, and an arm that learnt less can lose less of it).
P(A > B) is the chance a run of A beats a run of B (Agarwal et al. 2021), with a 95% stratified-bootstrap interval;
an arm is ahead only when the interval excludes 0.5, and only from ``VERDICT_SEEDS`` seeds per arm.
"""

from __future__ import annotations

import math
from typing import Any

from freamer_rl.errors import ConfigError
from freamer_rl.experiments.stats import probability_of_improvement

__all__ = ["COMPARE_ON", "VERDICT_SEEDS", "by_env", "check_pairs", "compare_markdown", "compare_table", "verdict"]

#: ``evaluate.compare_on`` choices
COMPARE_ON = ("R", "score")
#: fewest seeds per arm for an interval and a verdict: a bootstrap over two seeds has three distinct resamples per
#: arm, and two runs of A above two of B read P = 1 [1, 1]
VERDICT_SEEDS = 3


def by_env(rows: list[dict], key: str) -> dict[str, list[float]]:
    """``{env: [values over seeds]}`` of the finite ``key`` values (the strata of the bootstrap)."""
    out: dict[str, list[float]] = {}
    for r in rows:
        if math.isfinite(r[key]):
            out.setdefault(r["env"], []).append(r[key])
    return out


def check_pairs(pairs: list[list[str]], labels: list[str], field: str) -> None:
    """Each pair names two different entry labels; ConfigError naming ``field[i]`` otherwise."""
    for i, pair in enumerate(pairs):
        if len(pair) != 2 or pair[0] == pair[1]:
            raise ConfigError(f"{field}[{i}]: expected two different entry labels [A, B], got {pair}")
        for arm in pair:
            if arm not in labels:
                raise ConfigError(f"{field}[{i}]: {arm!r} is not an entry label ({', '.join(labels)})")


def verdict(a: str, b: str, low: float, high: float) -> str:
    """The protocol's reading of P(A > B) [low, high]: an arm is ahead only when the interval excludes 0.5."""
    if low > 0.5:
        return f"{a} ahead of {b}"
    if high < 0.5:
        return f"{b} ahead of {a}"
    return "no clear difference"


def _pair_row(rows: list[dict], a: str, b: str, condition: str, on: str) -> dict[str, Any]:
    ra = by_env([r for r in rows if r["label"] == a and r["condition"] == condition], on)
    rb = by_env([r for r in rows if r["label"] == b and r["condition"] == condition], on)
    row = {"a": a, "b": b, "condition": condition, "on": on, "p": math.nan, "low": math.nan, "high": math.nan}
    if not set(ra) & set(rb):
        row["verdict"] = f"n/a (no env with {on} for both)"
        return row
    row["p"], row["low"], row["high"] = probability_of_improvement(ra, rb)
    row["verdict"] = verdict(a, b, row["low"], row["high"])
    if min(sum(map(len, ra.values())), sum(map(len, rb.values()))) < VERDICT_SEEDS:
        row["low"] = row["high"] = math.nan  # a bootstrap of 1-2 seeds: no interval to speak of
        row["verdict"] = f"too few seeds (< {VERDICT_SEEDS} per arm)"
    return row


def compare_table(rows: list[dict], cfg: Any) -> list[dict[str, Any]]:
    """Per ``cfg.compare_on`` quantity x ``cfg.compare`` pair x condition (R: the corrupted ones; score: all):
    P(A > B) with its interval and verdict."""
    out = []
    for on in cfg.compare_on:
        conditions = [c.label for c in cfg.conditions if c.corrupt or on == "score"]
        out += [_pair_row(rows, a, b, c, on) for a, b in cfg.compare for c in conditions]
    return out


def compare_markdown(pairs: list[dict], ci: Any) -> list[str]:
    """The "Probability of improvement" section of robustness.md (``ci``: the report's interval formatter)."""
    lines = [
        "",
        "## Probability of improvement",
        "",
        "P(A > B): the chance a run of A beats a run of B on R (keeps more of its clean score) or on the score "
        "itself; A is ahead only when the 95% interval excludes 0.5.",
        "",
        "| of | A | B | condition | P(A > B) [95% CI] | verdict |",
        "|---|---|---|---|---:|---|",
    ]
    return lines + [
        f"| {p['on']} | {p['a']} | {p['b']} | {p['condition']} | {ci(p['p'], p['low'], p['high'], 2)} | "
        f"{p['verdict']} |"
        for p in pairs
    ]
