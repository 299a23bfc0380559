"""Robustness of a suite's policies to corrupted modalities: evaluation conditions, their jobs and their report.

A suite's optional ``evaluate:`` section (:class:`EvaluateConfig`) names conditions, each a list of
``env.corrupt``-style entries applied at evaluation only (``[]``: clean)::

    evaluate:
      episodes: 100            # per condition per run
      seed: 12345
      deterministic: false
      metric: return_mean      # or success_rate: the score R of the robustness tables
      conditions:
        - {label: clean}
        - {label: grid_salt_0.25, corrupt: [{key: grid, kind: salt, level: 0.25}]}
        - {label: embed_state_2, corrupt: [{key: embed.state, kind: gaussian, level: 2}], group: embed.state}
      compare: [[fm_pre, concat]]   # probability of improvement between entry labels
      compare_on: [R]          # of R under each corruption; score: of the score under every condition

A condition's ``group`` (default ``<key>:<kind>`` of its entries, ``clean`` for the clean one) and ``level`` (default
its first entry's level, 0 when clean) place it on a curve R(level). After training, every finished run is evaluated
under every condition into ``<run_dir>/eval/<label>.json`` (:func:`evaluate_condition`: the evaluator's dict plus
``condition``, ``group``, ``level``, ``checkpoint_frames``; ``error`` when it failed). :func:`write_robustness` turns
those files into ``robustness.csv`` (per run x condition: score and R = score / the same run's clean score),
``robustness.md`` (IQM with 95% stratified-bootstrap intervals over seeds, the worst condition per arm, probability
of improvement between the ``compare`` pairs), ``robustness_<group>.png`` and, for FreamerV1 runs,
``gates_<group>.png`` (each modality's gate sigma(alpha) and refiner displacement against the level).
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from freamer_rl.config.checks import run_name_problem
from freamer_rl.config.sections import CorruptionConfig, check_corruption_entry
from freamer_rl.errors import ConfigError, FreamerError
from freamer_rl.experiments.report import read_json
from freamer_rl.experiments.robustness_compare import (
    COMPARE_ON,
    by_env,
    check_pairs,
    compare_markdown,
    compare_table,
)
from freamer_rl.experiments.stats import iqm_ci, mean_ratio_ci, stratified_bootstrap_ci
from freamer_rl.experiments.workers import error_line
from freamer_rl.run.checkpoint import atomic_write_text, read_checkpoint
from freamer_rl.run.rundir import write_rows_csv
from freamer_rl.trainers.registry import evaluate_any, resolve_checkpoint

logger = logging.getLogger(__name__)

__all__ = [
    "EVAL_DIR",
    "EvalCondition",
    "EvaluateConfig",
    "check_evaluate",
    "checkpoint_frames",
    "condition_group",
    "condition_level",
    "eval_path",
    "eval_state",
    "evaluate_condition",
    "robustness_rows",
    "write_robustness",
]

EVAL_DIR = "eval"
METRICS = ("return_mean", "success_rate")
#: the evaluator's per-episode values of each metric (run.evaluation.run_episodes), for one-seed intervals
EPISODE_VALUES = {"return_mean": "episode_returns", "success_rate": "episode_successes"}
_CKPT_FRAMES = re.compile(r"checkpoint_(\d+)\.pt")


@dataclass
class EvalCondition:
    label: str = ""
    corrupt: list[CorruptionConfig] = field(default_factory=list)  # []: clean
    group: str | None = None  # default "<key>:<kind>" of the entries ("clean" without entries)
    level: float | None = None  # default the first entry's level (0 when clean)


@dataclass
class EvaluateConfig:
    episodes: int = 100
    seed: int = 12345
    deterministic: bool = False
    num_envs: int | None = None  # None: the run's env.num_envs
    metric: str = "return_mean"
    conditions: list[EvalCondition] = field(default_factory=list)
    compare: list[list[str]] = field(default_factory=list)
    # what P(A > B) compares (experiments.robustness_compare): R under each corruption, and/or the score under every
    # condition (for arms trained with the corruption, whose clean scores differ)
    compare_on: list[str] = field(default_factory=lambda: ["R"])


def condition_group(c: EvalCondition) -> str:
    if c.group is not None:
        return c.group
    return ",".join(f"{e.key}:{e.kind}" for e in c.corrupt) if c.corrupt else "clean"


def condition_level(c: EvalCondition) -> float:
    if c.level is not None:
        return float(c.level)
    return float(c.corrupt[0].level) if c.corrupt else 0.0


def clean_condition(cfg: EvaluateConfig) -> EvalCondition:
    return next(c for c in cfg.conditions if not c.corrupt)


def _check_condition(c: EvalCondition, where: str) -> None:
    if problem := run_name_problem(c.label):
        raise ConfigError(f"{where}.label: {problem}")
    for j, e in enumerate(c.corrupt):
        check_corruption_entry(e, f"{where}.corrupt[{j}]")
    if c.group is not None and not c.group.strip():
        raise ConfigError(f"{where}.group: expected a name, got an empty string")
    if c.level is not None and not math.isfinite(c.level):
        raise ConfigError(f"{where}.level: expected a finite number, got {c.level!r}")
    if not c.corrupt and c.level not in (None, 0.0):
        raise ConfigError(f"{where}.level: the clean condition sits at level 0, got {c.level!r}")


def check_evaluate(cfg: EvaluateConfig, labels: list[str]) -> None:
    """The ``evaluate`` section against the suite's entry ``labels``; one ConfigError naming the field otherwise."""
    if cfg.episodes < 1:
        raise ConfigError(f"evaluate.episodes: expected at least 1, got {cfg.episodes}")
    if cfg.seed < 0:
        raise ConfigError(f"evaluate.seed: expected a seed >= 0, got {cfg.seed}")
    if cfg.num_envs is not None and cfg.num_envs < 1:
        raise ConfigError(f"evaluate.num_envs: expected at least 1 (or leave it out), got {cfg.num_envs}")
    if cfg.metric not in METRICS:
        raise ConfigError(f"evaluate.metric: expected one of {', '.join(METRICS)}, got {cfg.metric!r}")
    if not cfg.conditions:
        raise ConfigError("evaluate.conditions: list the conditions to evaluate, a clean one ({label: clean}) first")
    seen: set[str] = set()
    clean = []
    for i, c in enumerate(cfg.conditions):
        _check_condition(c, f"evaluate.conditions[{i}]")
        if c.label in seen:
            raise ConfigError(f"evaluate.conditions[{i}].label: {c.label!r} is used twice")
        seen.add(c.label)
        clean += [i] if not c.corrupt else []
    if not clean:
        raise ConfigError(
            "evaluate.conditions: a clean condition (no corrupt entries, e.g. {label: clean}) is required: "
            "R = score / the clean score"
        )
    if len(clean) > 1:
        raise ConfigError(f"evaluate.conditions[{clean[1]}]: a second clean condition (no corrupt entries)")
    if not cfg.compare_on or len(set(cfg.compare_on)) != len(cfg.compare_on):
        raise ConfigError(
            f"evaluate.compare_on: expected distinct entries of {', '.join(COMPARE_ON)}, got {cfg.compare_on}"
        )
    for on in cfg.compare_on:
        if on not in COMPARE_ON:
            raise ConfigError(f"evaluate.compare_on: expected entries of {', '.join(COMPARE_ON)}, got {on!r}")
    check_pairs(cfg.compare, labels, "evaluate.compare")


# -- evaluation jobs -----------------------------------------------------------------------------------------------
def eval_path(run_dir: Path, label: str) -> Path:
    return Path(run_dir) / EVAL_DIR / f"{label}.json"


def checkpoint_frames(run_dir: Path) -> int | None:
    """The frames of the checkpoint an evaluation of ``run_dir`` loads (from its file name when it has them); None
    when the run has no checkpoint."""
    try:
        path = resolve_checkpoint(run_dir)
    except FreamerError:
        return None
    if found := _CKPT_FRAMES.fullmatch(path.name):
        return int(found.group(1))
    frames = read_checkpoint(path).get("frames")
    return None if frames is None else int(frames)


def eval_state(path: Path, frames: int | None) -> str:
    """``done`` (a result for the checkpoint of ``frames``), ``stale`` (for another checkpoint), ``failed``, ``new``."""
    data = read_json(path)
    if data is None:
        return "new"
    if data.get("error"):
        return "failed"
    return "done" if frames is not None and data.get("checkpoint_frames") == frames else "stale"


def eval_job(cfg: EvaluateConfig, c: EvalCondition, run_dir: Path, tag: str, log_level: int) -> dict[str, Any]:
    """The payload of :func:`evaluate_condition` (plain data: it crosses to a spawned worker)."""
    return {
        "run_dir": str(run_dir),
        "tag": f"{tag} eval {c.label}",
        "condition": c.label,
        "group": condition_group(c),
        "level": condition_level(c),
        "corrupt": [{**asdict(e), "when": "eval"} for e in c.corrupt],
        "options": {
            "episodes": cfg.episodes,
            "deterministic": cfg.deterministic,
            "num_envs": cfg.num_envs,
            "seed": cfg.seed,
        },
        "log_level": log_level,
    }


def evaluate_condition(job: dict[str, Any]) -> dict[str, Any]:
    """Worker: evaluate one run under one condition and write ``<run_dir>/eval/<condition>.json`` (with ``error``
    when it failed; the suite goes on)."""
    logging.basicConfig(
        force=True, level=job["log_level"], format=f"%(asctime)s %(levelname)s [{job['tag']}] %(name)s: %(message)s"
    )
    run_dir = Path(job["run_dir"])
    head = {"condition": job["condition"], "group": job["group"], "level": job["level"]}
    t0 = time.perf_counter()
    try:
        frames = checkpoint_frames(run_dir)
        if frames is None:
            raise FreamerError(f"no checkpoint in run directory {run_dir}")
        corrupt = [CorruptionConfig(**e) for e in job["corrupt"]]  # [] is an explicitly clean evaluation
        result = evaluate_any(run_dir, corrupt=corrupt, **job["options"])
        out = {**head, **result, "checkpoint_frames": frames, "seconds": round(time.perf_counter() - t0, 1)}
    except Exception as err:  # recorded; the other evaluations go on
        error = error_line(err)
        if not isinstance(err, FreamerError):
            logger.exception("evaluation %s failed", job["tag"])
        out = {**head, "error": error}
    path = eval_path(run_dir, job["condition"])
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(out, default=str, indent=1) + "\n")
    return {"ok": "error" not in out, "error": out.get("error"), "seconds": time.perf_counter() - t0}


# -- the report ----------------------------------------------------------------------------------------------------
def _number(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def robustness_rows(results: list[dict], cfg: EvaluateConfig) -> list[dict[str, Any]]:
    """robustness.csv: per done run (``results``: runs.csv rows with ``run_dir``) x condition, the score (the
    ``metric`` of the evaluation), the same run's clean score and R = score / clean (NaN when the clean score is 0 or
    missing), plus the gate / displacement means FreamerV1 reports (``extras``)."""
    clean = clean_condition(cfg)
    rows = []
    for r in (r for r in results if r["status"] == "done"):
        evals = {c.label: read_json(eval_path(Path(r["run_dir"]), c.label)) for c in cfg.conditions}
        base = _number((evals[clean.label] or {}).get(cfg.metric))
        for c in cfg.conditions:
            data = evals[c.label] or {}
            score = _number(data.get(cfg.metric)) if not data.get("error") else math.nan
            ratio = score / base if math.isfinite(base) and base != 0 and math.isfinite(score) else math.nan
            extras = {k: _number(v) for k, v in data.items() if k.startswith(TELEMETRY_PREFIXES)}
            episodes = data.get(EPISODE_VALUES[cfg.metric]) if math.isfinite(score) else None
            rows.append(
                {
                    "label": r["label"],
                    "env": r["env"],
                    "seed": r["seed"],
                    "condition": c.label,
                    "group": condition_group(c),
                    "level": condition_level(c),
                    "score": score,
                    "clean_score": base,
                    "R": ratio,
                    "checkpoint_frames": data.get("checkpoint_frames"),
                    "error": data.get("error") or (None if data else "not evaluated"),
                    "extras": extras,
                    "episode_scores": episodes or [],
                    "clean_episode_scores": (evals[clean.label] or {}).get(EPISODE_VALUES[cfg.metric]) or [],
                }
            )
    return rows


def _iqm(rows: list[dict], key: str) -> tuple[float, float, float]:
    scores = by_env(rows, key)
    return iqm_ci(scores) if scores else (math.nan, math.nan, math.nan)


def _episode_intervals(row: dict, clean: bool) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
    """One run's score and R with 95% bootstrap intervals over its evaluation episodes (a corrupted condition's and
    the clean condition's resampled on their own; the clean R is 1 by definition); None without per-episode values."""
    eps, clean_eps = row["episode_scores"], row["clean_episode_scores"]
    if len(eps) < 2 or len(clean_eps) < 2:
        return None
    score = stratified_bootstrap_ci({"episodes": eps}, lambda x: float(np.mean(x)))
    ratio = (row["R"],) * 3 if clean else (row["R"], *mean_ratio_ci(eps, clean_eps)[1:])
    return (row["score"], *score[1:]), ratio


def arm_table(rows: list[dict], cfg: EvaluateConfig, labels: list[str]) -> list[dict[str, Any]]:
    """Per arm (entry label, stratified over envs) x condition: seeds with a score, IQM of score and of R [95% CI].

    The intervals resample seeds; an arm with one seed on one env has none to resample, so its intervals resample
    that run's evaluation episodes instead (``interval: episodes``; they leave out the run-to-run spread)."""
    out = []
    for label in labels:
        for c in cfg.conditions:
            sel = [r for r in rows if r["label"] == label and r["condition"] == c.label]
            if not sel:
                continue
            (s, s_lo, s_hi), (q, q_lo, q_hi) = _iqm(sel, "score"), _iqm(sel, "R")
            done = [r for r in sel if math.isfinite(r["score"])]
            one_run = _episode_intervals(done[0], not c.corrupt) if len(done) == 1 else None
            if one_run is not None:
                (s, s_lo, s_hi), (q, q_lo, q_hi) = one_run
            out.append(
                {
                    "label": label,
                    "condition": c.label,
                    "group": condition_group(c),
                    "level": condition_level(c),
                    "n": sum(math.isfinite(r["score"]) for r in sel),
                    "score_iqm": s,
                    "score_low": s_lo,
                    "score_high": s_hi,
                    "R_iqm": q,
                    "R_low": q_lo,
                    "R_high": q_hi,
                    "interval": "episodes" if one_run is not None else "seeds",
                }
            )
    return out


def _ci(point: float, low: float, high: float, digits: int = 3, mark: str = "") -> str:
    if not math.isfinite(point):
        return "n/a"
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"{point:.{digits}f}{mark}"
    return f"{point:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]{mark}"


#: marks an interval over one run's evaluation episodes (arm_table's ``interval: episodes``)
EPISODES_MARK = " (e)"


def robustness_markdown(name: str, cfg: EvaluateConfig, arms: list[dict], pairs: list[dict], rows: list[dict]) -> str:
    lines = [
        f"# Suite {name}: robustness",
        "",
        f"Score: evaluation `{cfg.metric}` over {cfg.episodes} episodes per run and condition (seed {cfg.seed}, "
        f"{'deterministic' if cfg.deterministic else 'sampled'} actions); R = score / the same run's clean score. "
        "IQM over seeds with a 95% stratified-bootstrap interval (strata: envs).",
        "",
        "| arm | condition | group | level | n seeds | score IQM [95% CI] | R IQM [95% CI] |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for a in arms:
        lines.append(
            f"| {a['label']} | {a['condition']} | {a['group']} | {a['level']:g} | {a['n']} | "
            f"{_ci(a['score_iqm'], a['score_low'], a['score_high'], mark=_mark(a))} | "
            f"{_ci(a['R_iqm'], a['R_low'], a['R_high'], mark=_mark(a))} |"
        )
    if any(a["interval"] == "episodes" for a in arms):
        lines += [
            "",
            f"{EPISODES_MARK.strip()}: one seed, so the interval resamples that run's {cfg.episodes} evaluation "
            "episodes (the clean ones separately for R); it leaves out the run-to-run spread, which seeds would show.",
        ]
    lines += ["", "## Worst condition per arm", "", "| arm | worst condition | R IQM [95% CI] |", "|---|---|---:|"]
    for label in dict.fromkeys(a["label"] for a in arms):
        corrupted = [
            a
            for a in arms
            if a["label"] == label and a["condition"] != clean_condition(cfg).label and math.isfinite(a["R_iqm"])
        ]
        if corrupted:
            w = min(corrupted, key=lambda a: a["R_iqm"])
            lines.append(f"| {label} | {w['condition']} | {_ci(w['R_iqm'], w['R_low'], w['R_high'], mark=_mark(w))} |")
        else:
            lines.append(f"| {label} | n/a | n/a |")
    if pairs:
        lines += compare_markdown(pairs, _ci)
    if any(r["extras"] for r in rows):
        lines += [
            "",
            "gates_<group>.png: per modality, against the level (mean across seeds; FreamerV1): the gate "
            "sigma(alpha), the score-based input gate and mixing weight (model.flow.reliability runs) and the "
            "refiner displacement. sigma(alpha) is a trained weight, so under evaluation-only corruption it stays "
            "where training left it; the input gate, the weight and the displacement respond per step. Whether a "
            "trained gate closes on a modality corrupted during training shows across entries trained with "
            "env.corrupt.",
        ]
    missing = [r for r in rows if r["error"]]
    if missing:
        lines += ["", "## Missing evaluations", ""]
        lines += [f"- {r['label']} / {r['env']} / seed {r['seed']} / {r['condition']}: {r['error']}" for r in missing]
    return "\n".join(lines) + "\n"


def _mark(arm: dict) -> str:
    return EPISODES_MARK if arm["interval"] == "episodes" else ""


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


def _groups(cfg: EvaluateConfig) -> list[str]:
    return list(dict.fromkeys(condition_group(c) for c in cfg.conditions if c.corrupt))


def plot_robustness(path: Path, group: str, arms: list[dict], labels: list[str]) -> bool:
    """R(level) per arm (IQM with its 95% CI band) for one group's conditions; level 0 is the clean condition
    (R = 1). False when no arm has a point to draw."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    drawn = False
    for i, label in enumerate(labels):
        pts = sorted(
            (a["level"], a["R_iqm"], a["R_low"], a["R_high"])
            for a in arms
            if a["label"] == label and a["group"] == group and math.isfinite(a["R_iqm"])
        )
        if not pts:
            continue
        x, y, lo, hi = (np.array(v, dtype=float) for v in zip((0.0, 1.0, 1.0, 1.0), *pts))
        ax.plot(x, y, color=f"C{i}", marker="o", label=f"{label} (IQM, 95% CI)")
        ax.fill_between(x, lo, hi, color=f"C{i}", alpha=0.2, lw=0)
        drawn = True
    ax.axhline(1.0, color="k", ls=":", lw=0.8)
    ax.set_xlabel("corruption level")
    ax.set_ylabel("R = score / clean score")
    ax.set_title(f"robustness: {group}")
    if drawn:
        ax.legend(fontsize=8)
    fig.tight_layout()
    if drawn:
        fig.savefig(path, dpi=100)
    plt.close(fig)
    return drawn


#: FreamerV1's per-modality telemetry in an evaluation (prefix -> kind): the trained gate sigma(alpha), the
#: score-based input gate and mixing weight (model.flow.reliability), the refiner's displacement
TELEMETRY_KINDS = {
    "gate_input_": "gate_input",
    "weight_": "weight",
    "fm_displacement_": "fm_displacement",
    "gate_": "gate",
}
TELEMETRY_PREFIXES = tuple(TELEMETRY_KINDS)


def _telemetry_kind(key: str) -> tuple[str, str]:
    """``(kind, modality)`` of a telemetry key (the first matching prefix of :data:`TELEMETRY_KINDS`)."""
    prefix = next(p for p in TELEMETRY_PREFIXES if key.startswith(p))
    return TELEMETRY_KINDS[prefix], key[len(prefix) :]


def gate_points(rows: list[dict], cfg: EvaluateConfig, group: str) -> dict[tuple[str, str, str], list[tuple]]:
    """``{(label, kind, modality): [(level, mean across seeds), ...]}`` (kinds: :data:`TELEMETRY_KINDS`) for the
    clean condition (level 0) and the group's conditions, from the runs whose evaluation reports them."""
    levels = {c.label: condition_level(c) for c in cfg.conditions if not c.corrupt or condition_group(c) == group}
    acc: dict[tuple[str, str, str], dict[float, list[float]]] = {}
    for r in rows:
        if r["condition"] not in levels:
            continue
        for key, v in r["extras"].items():
            kind, modality = _telemetry_kind(key)
            if math.isfinite(v):
                acc.setdefault((r["label"], kind, modality), {}).setdefault(levels[r["condition"]], []).append(v)
    return {k: sorted((lv, float(np.mean(vs))) for lv, vs in d.items()) for k, d in acc.items()}


def plot_gates(path: Path, group: str, points: dict[tuple[str, str, str], list[tuple]], labels: list[str]) -> bool:
    """Three panels against the level: each modality's gate (sigma(alpha) dotted, the score-based input gate solid),
    its mixing weight (reliability runs only) and its refiner displacement (mean across seeds; colour: modality,
    line style: arm). False when nothing reports them."""
    if not points:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    panel = {"gate": 0, "gate_input": 0, "weight": 1, "fm_displacement": 2}
    modalities = sorted({m for _, _, m in points})
    styles = ("-", "--", ":", "-.")
    for (label, kind, modality), pts in sorted(points.items()):
        ax = axes[panel[kind]]
        x, y = zip(*pts)
        style = styles[labels.index(label) % len(styles)] if label in labels else "-"
        hit = f"embed.{modality}:" in f"{group}:"  # the corrupted modality (embedding noise names it) stands out
        color = f"C{modalities.index(modality)}"
        style = ":" if kind == "gate" and any(k[1] == "gate_input" for k in points) else style
        name = f"{label}: {modality}" + (" (input gate)" if kind == "gate_input" else "")
        ax.plot(x, y, marker="o", ls=style, lw=2.5 if hit else 1.2, color=color, label=name)
    for ax, ylabel in zip(axes, ("residual gate", "mixing weight (reliability)", "refiner displacement")):
        ax.set_xlabel(f"corruption level ({group})")
        ax.set_ylabel(ylabel)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
        else:  # say why a panel is blank rather than leave an empty frame
            ax.text(0.5, 0.5, f"no run reports a {ylabel}", ha="center", va="center", transform=ax.transAxes)
    fig.suptitle(f"gates against corruption: {group} (mean across seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def write_robustness(output: Path, name: str, results: list[dict], cfg: EvaluateConfig) -> list[Path]:
    """robustness.csv, robustness.md and the R(level) / gate plots from the run folders' eval jsons (``results``:
    the runs.csv rows of :func:`freamer_rl.experiments.report.write_report`); returns the files written."""
    labels = list(dict.fromkeys(r["label"] for r in results))
    rows = robustness_rows(results, cfg)
    fields = ["label", "env", "seed", "condition", "group", "level", "score", "clean_score", "R"]
    write_rows_csv(output / "robustness.csv", rows, fields=[*fields, "checkpoint_frames", "error"])
    arms, pairs = arm_table(rows, cfg, labels), compare_table(rows, cfg)
    atomic_write_text(output / "robustness.md", robustness_markdown(name, cfg, arms, pairs, rows))
    written = [output / "robustness.csv", output / "robustness.md"]
    for group in _groups(cfg):
        path = output / f"robustness_{_safe(group)}.png"
        written += [path] if plot_robustness(path, group, arms, labels) else []
        path = output / f"gates_{_safe(group)}.png"
        written += [path] if plot_gates(path, group, gate_points(rows, cfg, group), labels) else []
    logger.info("suite %s: robustness report in %s (%d evaluations)", name, output, len(rows))
    return written
