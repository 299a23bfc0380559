"""Sensor corruption against the health encoders (issue 22, part 5): does the Foundation encoder's lead over the MLP
grow with sensor noise (the paper's "the advantage grows with encoder noise")?

    freamer-rl health corruption RUN [RUN ...] --key imu[0:12] --kind gaussian --levels 0,0.5,1,2
        [--episodes 20] [--seed 12345] [--deterministic] [--compare foundation,mlp] [--out DIR]

Every trained health run (a run directory or its checkpoint) is evaluated clean and at each level with the
corruption ``KEY:KIND:LEVEL`` applied to the real env's observations the encoder reads
(:func:`freamer_rl.health.evaluation.corruption_for`: ``imu[0:12]`` hand, ``imu[12:24]`` chest, ``imu[24:36]``
ankle, ``hr_features``); every evaluation uses the same env seed and reseeds torch's generator with it (the policy's
action samples and the noise), so the episodes are the same for every run and level and the levels differ only by
the corruption.
Written to ``--out`` (default ``health_corruption/`` in the working directory):

* ``corruption.csv`` -- per run x level: encoder, seed, return, clean return, ``R = return / clean return``, the
  violations and the filter's mean per-step KL (the anomaly statistic) on the same corrupted episodes;
* ``corruption.md`` -- per encoder x level the IQM over runs of return and of R with 95% bootstrap intervals
  (:mod:`freamer_rl.experiments.stats`), the mean KL, and per level the difference A - B (``--compare``, default
  foundation - mlp) of the IQM return and of the IQM R with a 95% bootstrap interval (each arm's runs resampled on
  their own): the lead "grows with noise" only where the R difference is above 0 with its interval;
* ``corruption.json`` -- the rows and both tables.

A gaussian level 0 draws no noise, so its row equals the clean evaluation exactly.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from freamer_rl.config.sections import CorruptionConfig, check_corruption_entry, corruption_target
from freamer_rl.errors import ConfigError, FreamerError
from freamer_rl.experiments.stats import difference_ci, iqm_ci
from freamer_rl.run.checkpoint import atomic_write_text
from freamer_rl.run.rundir import write_rows_csv
from freamer_rl.trainers.registry import evaluate_any

logger = logging.getLogger(__name__)

__all__ = ["parse_levels", "sweep_rows", "encoder_table", "difference_table", "write_sweep", "main"]

FIELDS = ["run", "encoder", "seed", "level", "return", "clean_return", "R", "violations", "kl_mean", "episodes"]


def parse_levels(text: str, key: str, kind: str) -> list[float]:
    """``--levels 0,0.5,1`` as floats, each checked as ``kind``'s level (one ConfigError naming the flag)."""
    try:
        levels = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--levels: expected comma-separated numbers, e.g. 0,0.5,1,2, got {text!r}") from None
    if not levels:
        raise ConfigError("--levels: give at least one level, e.g. 0,0.5,1,2")
    if len(set(levels)) != len(levels):
        raise ConfigError(f"--levels: a level is given twice ({text!r})")
    for level in levels:
        check_corruption_entry(CorruptionConfig(key=key, kind=kind, level=level, when="eval"), "corruption")
    return levels


def _run_seed(run: Path) -> Any:
    """``run.seed`` from the run directory's config.yaml (None when it has none)."""
    path = (run if run.is_dir() else run.parent) / "config.yaml"
    data = yaml.safe_load(path.read_text()) if path.is_file() else None
    return ((data or {}).get("run") or {}).get("seed")


def sweep_rows(
    runs: Sequence[str | Path],
    key: str,
    kind: str,
    levels: Sequence[float],
    *,
    episodes: int = 20,
    seed: int = 12345,
    deterministic: bool = False,
) -> list[dict[str, Any]]:
    """Per run x level one row (``FIELDS``): the evaluation of the run with ``key:kind:level`` (the corrupted levels
    first, so a key the agent does not read fails before any clean evaluation is spent), R against its clean one."""
    rows = []
    for run in map(Path, runs):
        per_level = {}
        for level in levels:
            entry = CorruptionConfig(key=key, kind=kind, level=level, when="eval")
            torch.manual_seed(seed)  # the same action samples and noise stream at every level (common random numbers)
            per_level[level] = evaluate_any(
                run, corrupt=[entry], episodes=episodes, deterministic=deterministic, seed=seed
            )
        torch.manual_seed(seed)
        clean = evaluate_any(run, corrupt=[], episodes=episodes, deterministic=deterministic, seed=seed)
        base = float(clean["return_mean"])
        for level, res in per_level.items():
            ret = float(res["return_mean"])
            rows.append(
                {
                    "run": str(run),
                    "encoder": res.get("encoder", res.get("trainer", "?")),
                    "seed": _run_seed(run),
                    "level": level,
                    "return": ret,
                    "clean_return": base,
                    "R": ret / base if base != 0 and math.isfinite(base) else math.nan,
                    "violations": float(res.get("violations_mean", math.nan)),
                    "kl_mean": float(res.get("kl_mean", math.nan)),
                    "episodes": res.get("episodes"),
                }
            )
        logger.info("corruption sweep: %s done (clean return %.2f)", run, base)
    return rows


def _finite(rows: list[dict], field: str) -> list[float]:
    return [r[field] for r in rows if math.isfinite(r[field])]


def encoder_table(rows: list[dict]) -> list[dict[str, Any]]:
    """Per encoder x level: runs, IQM return and IQM R with 95% bootstrap intervals (runs resampled), mean KL."""
    out = []
    for enc in dict.fromkeys(r["encoder"] for r in rows):
        for level in sorted({r["level"] for r in rows}):
            sel = [r for r in rows if r["encoder"] == enc and r["level"] == level]
            entry: dict[str, Any] = {"encoder": enc, "level": level, "n": len(sel)}
            for field in ("return", "R"):
                vals = _finite(sel, field)
                point, low, high = iqm_ci({"health": vals}) if vals else (math.nan,) * 3
                entry.update({f"{field}_iqm": point, f"{field}_low": low, f"{field}_high": high})
            kl = _finite(sel, "kl_mean")
            entry["kl_mean"] = float(np.mean(kl)) if kl else math.nan
            out.append(entry)
    return out


def difference_table(rows: list[dict], a: str, b: str) -> list[dict[str, Any]]:
    """Per level: ``a - b`` of the IQM return and of the IQM R, each with its 95% bootstrap interval."""
    out = []
    for level in sorted({r["level"] for r in rows}):
        sa = [r for r in rows if r["encoder"] == a and r["level"] == level]
        sb = [r for r in rows if r["encoder"] == b and r["level"] == level]
        entry: dict[str, Any] = {"a": a, "b": b, "level": level, "n_a": len(sa), "n_b": len(sb)}
        for field in ("return", "R"):
            d, low, high = difference_ci(_finite(sa, field), _finite(sb, field))
            entry.update({f"{field}_diff": d, f"{field}_low": low, f"{field}_high": high})
        out.append(entry)
    return out


def _ci(point: float, low: float, high: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(point) else f"{point:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def sweep_markdown(spec: str, meta: dict, encoders: list[dict], diffs: list[dict]) -> str:
    lines = [
        f"# Health sensor corruption: {spec}",
        "",
        f"Return over {meta['episodes']} real-env episodes per run and level (env seed {meta['seed']}, "
        f"{'deterministic' if meta['deterministic'] else 'sampled'} actions); R = return / the same run's clean "
        "return; IQM over runs with a 95% bootstrap interval; KL: the filter's mean per-step KL(q || p) (the "
        "anomaly statistic) on the same corrupted episodes.",
        "",
        "| encoder | level | runs | return IQM [95% CI] | R IQM [95% CI] | mean KL |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for e in encoders:
        lines.append(
            f"| {e['encoder']} | {e['level']:g} | {e['n']} | {_ci(e['return_iqm'], e['return_low'], e['return_high'], 2)}"
            f" | {_ci(e['R_iqm'], e['R_low'], e['R_high'])} | {e['kl_mean']:.3f} |"
        )
    if diffs:
        a, b = diffs[0]["a"], diffs[0]["b"]
        lines += [
            "",
            f"## {a} - {b} per level",
            "",
            "Difference of the IQMs, 95% bootstrap interval (each arm's runs resampled on their own). The lead grows "
            "with noise where the R difference is above 0 with its interval.",
            "",
            f"| level | runs {a} / {b} | return diff [95% CI] | R diff [95% CI] |",
            "|---:|---:|---:|---:|",
        ]
        lines += [
            f"| {d['level']:g} | {d['n_a']} / {d['n_b']} | {_ci(d['return_diff'], d['return_low'], d['return_high'], 2)}"
            f" | {_ci(d['R_diff'], d['R_low'], d['R_high'])} |"
            for d in diffs
        ]
        if min(min(d["n_a"], d["n_b"]) for d in diffs) < 3:
            lines += ["", "Fewer than 3 runs per encoder: the intervals resample too few runs to be trusted."]
    return "\n".join(lines) + "\n"


def write_sweep(out: Path, rows: list[dict], spec: str, meta: dict, compare: tuple[str, str]) -> list[Path]:
    """corruption.csv / .md / .json in ``out``; the difference table only when both ``compare`` encoders ran."""
    out.mkdir(parents=True, exist_ok=True)
    encoders = encoder_table(rows)
    present = {r["encoder"] for r in rows}
    diffs = difference_table(rows, *compare) if set(compare) <= present else []
    write_rows_csv(out / "corruption.csv", rows, fields=FIELDS)
    atomic_write_text(out / "corruption.md", sweep_markdown(spec, meta, encoders, diffs))
    payload = {"corruption": spec, **meta, "rows": rows, "encoders": encoders, "differences": diffs}
    atomic_write_text(out / "corruption.json", json.dumps(payload, indent=1, default=str) + "\n")
    return [out / "corruption.csv", out / "corruption.md", out / "corruption.json"]


def build_parser(prog: str = "freamer-rl health corruption") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="evaluate health runs against a sensor corruption level")
    p.add_argument("runs", nargs="+", help="health run directories (or their checkpoint.pt)")
    p.add_argument("--key", required=True, help="imu, imu[0:12] (hand), imu[12:24] (chest), imu[24:36], hr_features")
    p.add_argument("--kind", default="gaussian", help="gaussian, dropout, dropout_episode, stale, noisy_tv")
    p.add_argument("--levels", default="0,0.5,1,2", help="comma-separated levels of the kind")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=12345, help="env seed of every evaluation")
    p.add_argument("--deterministic", action="store_true", help="argmax actions instead of sampling")
    p.add_argument("--compare", default="foundation,mlp", help="A,B: the encoders whose difference A - B is shown")
    p.add_argument("--out", default="health_corruption", help="output directory")
    return p


def main(argv: list[str] | None = None, prog: str = "freamer-rl health corruption") -> int:
    args = build_parser(prog).parse_args(argv)
    try:
        if args.episodes < 1:
            raise ConfigError(f"--episodes: expected at least 1, got {args.episodes}")
        compare = tuple(v.strip() for v in args.compare.split(","))
        if len(compare) != 2 or compare[0] == compare[1] or not all(compare):
            raise ConfigError(f"--compare: expected two different encoder kinds A,B, got {args.compare!r}")
        corruption_target(CorruptionConfig(key=args.key), "corruption")
        levels = parse_levels(args.levels, args.key, args.kind)
        missing = [r for r in args.runs if not Path(r).exists()]
        if missing:
            raise ConfigError(f"runs: no such run directory or checkpoint: {', '.join(missing)}")
        rows = sweep_rows(
            args.runs,
            args.key,
            args.kind,
            levels,
            episodes=args.episodes,
            seed=args.seed,
            deterministic=args.deterministic,
        )
        meta = {"episodes": args.episodes, "seed": args.seed, "deterministic": args.deterministic}
        written = write_sweep(Path(args.out), rows, f"{args.key}:{args.kind}", meta, compare)
    except FreamerError as err:
        sys.stderr.write(f"error: {err}\n")
        return 2
    sys.stdout.write("\n".join(map(str, written)) + "\n")
    return 0
