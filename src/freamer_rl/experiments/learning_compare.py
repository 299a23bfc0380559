"""Probability of improvement between a suite's arms on how they learned (suite YAML ``compare: [[A, B], ...]``).

Two readings per pair and env, over the finished runs: how soon each reaches 95% success (``frames_to_95``, the
trailing-100-episode definition; across a chain, counted from its start), and the final success rate (the final
return for tasks without success). A run that never reached 95% is slower than every run that did and tied with
every other run that did not, so an arm that stalls is compared, not dropped: the IQM column of ``summary.md`` needs
every seed to have reached 95%, this one does not. P(A > B) is the chance a run of A beats a run of B (Agarwal et al.
2021), with a 95% stratified-bootstrap interval; A is ahead only when the interval excludes 0.5, and only from
:data:`~freamer_rl.experiments.robustness_compare.VERDICT_SEEDS` seeds per arm.
"""

from __future__ import annotations

from typing import Any

from freamer_rl.experiments.robustness_compare import VERDICT_SEEDS, verdict
from freamer_rl.experiments.stats import is_missing, probability_of_improvement

__all__ = ["learning_compare_markdown"]

#: the frames-to-95% of a run that never reached it: later than any real run (finite, so that two such runs tie)
NOT_REACHED = 1e18


def _p_cell(a_vals: list[float], b_vals: list[float], a: str, b: str, env: str) -> tuple[str, str]:
    """``(P(A > B) [CI], reading)`` of the two arms' values (higher is better)."""
    p, low, high = probability_of_improvement({env: a_vals}, {env: b_vals})
    if min(len(a_vals), len(b_vals)) < VERDICT_SEEDS:
        return f"{p:.2f}", f"too few seeds (< {VERDICT_SEEDS} per arm)"
    return f"{p:.2f} [{low:.2f}, {high:.2f}]", verdict(a, b, low, high)


def _sooner(runs: list[dict]) -> list[float] | None:
    """Negated frames to 95% (higher is sooner; never reached: -NOT_REACHED); None when a run does not record it or
    the task has no success rate (CartPole, Crafter)."""
    if any("frames_to_95" in r.get("levels_unknown", ()) or is_missing(r.get("success_rate")) for r in runs):
        return None
    return [-(NOT_REACHED if r.get("frames_to_95") is None else float(r["frames_to_95"])) for r in runs]


def _final(runs: list[dict]) -> tuple[str, list[float]] | None:
    """The final success rate of every run (else the final return): ``(name, values)``; None when any is missing."""
    for key, name in (("success_rate", "final success"), ("return_mean", "final return")):
        values = [r.get(key) for r in runs]
        if not any(is_missing(v) for v in values):
            return name, [float(v) for v in values]
    return None


def _pair_cells(a: str, b: str, env: str, ra: list[dict], rb: list[dict]) -> list[str]:
    reached = [sum(r.get("frames_to_95") is not None for r in runs) for runs in (ra, rb)]
    cells = [f"{a} vs {b}", env, f"{len(ra)} / {len(rb)}"]
    sa, sb = _sooner(ra), _sooner(rb)
    if sa is None or sb is None:
        cells += ["n/a", "n/a", "n/a (no success rate, or a run predates the record)"]
    else:
        cells += [f"{reached[0]} / {reached[1]}", *_p_cell(sa, sb, a, b, env)]
    fa, fb = _final(ra), _final(rb)
    if fa is None or fb is None or fa[0] != fb[0]:
        return cells + ["n/a", "n/a"]
    p, reading = _p_cell(fa[1], fb[1], a, b, env)
    return cells + [f"{p} ({fa[0]})", reading]


def learning_compare_markdown(results: list[dict[str, Any]], pairs: list[list[str]]) -> list[str]:
    """The ``## Comparisons`` section of ``summary.md``: per pair and env that both arms finished runs on, P(A reaches
    95% sooner than B) and P(A's final success (or return) is higher), each with its interval and reading."""
    if not pairs:
        return []
    lines = [
        "",
        "## Comparisons",
        "",
        "P(A > B): the chance a run of A beats a run of B, 95% stratified-bootstrap interval; A is ahead only when "
        "the interval excludes 0.5. Sooner to 95%: a run that never reached 95% success counts as slower than every "
        "run that did (across a chain, frames from its start).",
        "",
        "| pair | env | seeds A / B | reached 95% A / B | P(A reaches 95% sooner) | reading | P(A ends higher) | "
        "reading |",
        "|---|---|---:|---:|---:|---|---:|---|",
    ]
    done = [r for r in results if r["status"] == "done"]
    for a, b in pairs:
        for env in dict.fromkeys(r["env"] for r in done):
            ra = [r for r in done if r["label"] == a and r["env"] == env]
            rb = [r for r in done if r["label"] == b and r["env"] == env]
            if ra and rb:
                lines.append("| " + " | ".join(_pair_cells(a, b, env, ra, rb)) + " |")
    return lines
