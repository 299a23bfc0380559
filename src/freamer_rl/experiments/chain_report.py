"""The per-stage table of a suite's chain entries: how far each arm got through its curriculum, and how fast.

A chain run's row in ``summary.md`` counts frames across its stages and shows its last stage's success; an arm that
stalls on an intermediate stage (trains it to the stage's cap and never moves on with 90%) shows only a low final
success there. This table says where: per arm and stage, how many seeds finished the stage, the frames they trained
in it and their success over its last 100 episodes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["chain_stage_markdown"]


def _stage_summary(run_dir: str, stage: str) -> dict[str, Any] | None:
    """The stage's summary.json (it is written when the stage finishes), or None."""
    try:
        data = json.loads((Path(run_dir) / stage / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _spread(values: list[float], fmt: str) -> str:
    """``mean (min–max)`` of ``values`` in ``fmt``, or the one value."""
    mean, lo, hi = sum(values) / len(values), min(values), max(values)
    if lo == hi:
        return format(mean, fmt)
    return f"{format(mean, fmt)} ({format(lo, fmt)}–{format(hi, fmt)})"


def _stage_cell(runs: list[dict[str, Any]], stage: str) -> str:
    """``k/n seeds · frames · success`` of the runs that finished ``stage``; "—" when none did."""
    done = [s for s in (_stage_summary(r["run_dir"], stage) for r in runs) if s is not None]
    frames = [float(s["frames"]) for s in done if s.get("frames") is not None]
    success = [float(s["final_success_rate"]) for s in done if s.get("final_success_rate") is not None]
    if not frames:
        return "—"
    cell = f"{len(done)}/{len(runs)}: {_spread(frames, ',.0f')} frames"
    return cell + (f", success {_spread(success, '.2f')}" if success else "")


def chain_stage_markdown(results: list[dict[str, Any]]) -> list[str]:
    """The ``## Chain stages`` section of ``summary.md`` for the chain runs among ``results`` (runs.csv rows with
    ``stages`` and ``run_dir``); [] when there are none. Partial runs count for the stages they finished."""
    chains = [r for r in results if r.get("stages") and r["status"] in ("done", "partial")]
    if not chains:
        return []
    stages = list(dict.fromkeys(s for r in chains for s in r["stages"]))
    labels = list(dict.fromkeys(r["label"] for r in chains))
    lines = [
        "",
        "## Chain stages",
        "",
        "Per arm and stage: seeds that finished the stage / seeds started, the frames they trained in it, mean "
        "(min–max), and their success over its last 100 episodes. A stage ends at its move-on success rate "
        "(`run.stop_at_success`) or at its frame cap.",
        "",
        "| arm | " + " | ".join(stages) + " |",
        "|---|" + "---:|" * len(stages),
    ]
    for label in labels:
        runs = [r for r in chains if r["label"] == label]
        lines.append(f"| {label} | " + " | ".join(_stage_cell(runs, s) for s in stages) + " |")
    return lines
