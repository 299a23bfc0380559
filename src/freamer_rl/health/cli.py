"""Command line of the health domain.

    freamer-rl health anomaly RUN_DIR_OR_CHECKPOINT [--hours 48] [--out DIR] [--seed 0]
        [--statistic running|ema] [--ema-halflife STEPS] [--k-sigma 2]
        [--data FILE_OR_FOLDER --labels LABELS.csv [--subject N] [--tolerance-s 30] [--segment-steps N]
         [--score kl|prediction|channel|hr_lag] [--stale-steps N]]
    freamer-rl health train recipes/health/health_foundation.yaml [--run-dir DIR] [--no-resume] [key=value ...]
    freamer-rl health baselines recipes/health/health_foundation.yaml [--depth 4] [--horizon 12] [--json FILE] [key=value ...]

``freamer-rl health corruption RUN [RUN ...] --key imu[0:12] --kind gaussian --levels 0,0.5,1,2`` (the sensor
corruption sweep of :mod:`freamer_rl.experiments.health_corruption`) is dispatched by the top-level ``freamer-rl``
(it aggregates with :mod:`freamer_rl.experiments.stats`, a tier above this one); one run's corrupted evaluation is
``freamer-rl eval RUN --corrupt imu[0:12]:gaussian:1.0``.

``anomaly`` runs :func:`~freamer_rl.health.anomaly_report.anomaly_report` (Fig. 4 picture, default output: the run
directory); with ``--data`` and ``--labels`` it filters that labelled recording instead and scores the flags
(:func:`~freamer_rl.health.anomaly_report.labelled_anomaly_report`: ``anomaly_scores.json`` next to
``anomaly_timeline.png``; labelled scenarios come from
:func:`freamer_rl.data.anomaly_labels.write_anomaly_scenario`). ``baselines`` prints the ceiling table
(:func:`~freamer_rl.health.reference.ceiling_table`: the oracle planner, the heart-rate rule and fixed policies on the
recipe's evaluation episodes, each as a fraction of the oracle). ``train`` is an alias of ``freamer-rl train`` for health recipes (the registry entry
:func:`freamer_rl.trainers.health.train`, resumable) and prints the summary as JSON.
:func:`main` takes ``argv`` so that ``freamer-rl health ...`` can delegate to it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from freamer_rl.config.loader import load_config
from freamer_rl.errors import ConfigError, FreamerError
from freamer_rl.health.anomaly_report import SCORES, anomaly_report, labelled_anomaly_report
from freamer_rl.health.config import HealthConfig
from freamer_rl.health.reference import ceiling_table, format_ceiling_table
from freamer_rl.trainers.health import train as train_health  # the registry entry (its STRUCTURAL)
from freamer_rl.world_model.anomaly import STATISTICS


def build_parser(prog: str = "freamer-rl health") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="FreamerV1 wearable health management (Section 5)")
    sub = parser.add_subparsers(dest="command", required=True)
    p_train = sub.add_parser("train", help="collect, train the world model and the policy in imagination, evaluate")
    p_train.add_argument("recipe", nargs="?", default=None, help="YAML recipe (recipes/health/health_*.yaml)")
    p_train.add_argument("overrides", nargs="*", help="dotted overrides, e.g. run.seed=1 collect.iterations=5")
    p_train.add_argument("--run-dir", default=None, help="output directory (default runs/health-<kind>-s<seed>-<time>)")
    p_train.add_argument(
        "--no-resume",
        action="store_true",
        help="start from scratch; refused when the run directory already holds checkpoints",
    )
    p_an = sub.add_parser("anomaly", help="record a long episode, flag KL anomalies, draw the Fig. 4 timeline")
    p_an.add_argument("checkpoint", help="run directory or its checkpoint.pt")
    p_an.add_argument("--hours", type=float, default=48.0)
    p_an.add_argument("--out", default=None, help="output directory (default: the run directory)")
    p_an.add_argument("--seed", type=int, default=0)
    p_an.add_argument("--k-sigma", type=float, default=2.0)
    p_an.add_argument("--statistic", choices=STATISTICS, default="running", help="running (Welford) or ema mean/std")
    p_an.add_argument("--ema-halflife", type=float, default=None, help="EMA half-life in steps (--statistic ema)")
    p_an.add_argument("--data", default=None, help="a labelled PAMAP2 recording: subjectNNN.dat or its folder")
    p_an.add_argument("--labels", default=None, help="its labels CSV (start_s,end_s,kind)")
    p_an.add_argument("--subject", type=int, default=None, help="the subject, when --data holds several")
    p_an.add_argument("--tolerance-s", type=float, default=30.0, help="a flag this long after an event still counts")
    p_an.add_argument(
        "--segment-steps", type=int, default=None, help="filter episode length (default env.episode_length; 0: one)"
    )
    p_an.add_argument(
        "--score",
        choices=SCORES,
        default="kl",
        help="with --data: the per-step score flagged, kl (the posterior's surprise), prediction (the prior's "
        "one-step prediction error of the observation), channel (its largest per-feature residual in that "
        "feature's running RMS) or hr_lag (no world model: the residual of a heart-rate lag predictor)",
    )
    p_an.add_argument(
        "--stale-steps",
        type=int,
        default=0,
        help="with --data: also flag steps whose IMU features have not changed for N steps (a frozen sensor; 0: off)",
    )
    p_b = sub.add_parser("baselines", help="the ceiling table: an oracle planner on the true simulator vs the rules")
    p_b.add_argument("recipe", help="health recipe: its env and eval sections set the episodes")
    p_b.add_argument("overrides", nargs="*", help="dotted overrides, e.g. eval.num_envs=32 eval.seed=0")
    p_b.add_argument("--depth", type=int, default=4, help="oracle: exhaustive search depth (5**depth sequences)")
    p_b.add_argument("--horizon", type=int, default=12, help="oracle: steps simulated per candidate")
    p_b.add_argument("--json", default=None, help="also write the rows as JSON to this file")
    return parser


def _baselines(args: argparse.Namespace) -> str:
    """``freamer-rl health baselines RECIPE``: the ceiling table as markdown (rows as JSON with ``--json``)."""
    for flag, value in (("--depth", args.depth), ("--horizon", args.horizon)):
        if value < 1:
            raise ConfigError(f"{flag}: expected an integer >= 1, got {value}")
    cfg = load_config(args.recipe, list(args.overrides), schema=HealthConfig)
    rows = ceiling_table(cfg, depth=args.depth, horizon=args.horizon)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2, default=str) + "\n")
    return format_ceiling_table(rows)


def _anomaly(args: argparse.Namespace) -> dict:
    ckpt = Path(args.checkpoint)
    out = Path(args.out) if args.out else (ckpt if ckpt.is_dir() else ckpt.parent)
    if args.ema_halflife is not None and args.statistic != "ema":
        raise ConfigError("--ema-halflife: only used with --statistic ema")
    checks = (
        ("--ema-halflife", args.ema_halflife, lambda v: v > 0, "a number of steps > 0"),
        ("--k-sigma", args.k_sigma, lambda v: v >= 0, "a number >= 0"),
        ("--tolerance-s", args.tolerance_s, lambda v: v >= 0, "seconds >= 0"),
        ("--segment-steps", args.segment_steps, lambda v: v >= 0, "an integer >= 0 (0: one filter episode)"),
        ("--stale-steps", args.stale_steps, lambda v: v >= 0, "an integer >= 0 (0: off)"),
    )
    for flag, value, ok, expected in checks:
        if value is not None and not (math.isfinite(value) and ok(value)):
            raise ConfigError(f"{flag}: expected {expected}, got {value!r}")
    if (args.data is None) != (args.labels is None):
        raise ConfigError("--data and --labels: give both (a labelled recording) or neither (an env episode)")
    if args.data is None:
        return anomaly_report(
            ckpt,
            out,
            hours=args.hours,
            seed=args.seed,
            k_sigma=args.k_sigma,
            statistic=args.statistic,
            halflife=args.ema_halflife,
        )
    return labelled_anomaly_report(
        ckpt,
        out,
        args.data,
        args.labels,
        subject=args.subject,
        statistic=args.statistic,
        halflife=args.ema_halflife,
        k_sigma=args.k_sigma,
        tolerance_s=args.tolerance_s,
        segment_steps=args.segment_steps,
        score=args.score,
        stale_steps=args.stale_steps,
    )


def main(argv: list[str] | None = None, prog: str = "freamer-rl health") -> int:
    args = build_parser(prog).parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "train":
            recipe, overrides = args.recipe, list(args.overrides)
            if recipe is not None and "=" in recipe and not Path(recipe).is_file():
                recipe, overrides = None, [recipe, *overrides]  # no recipe, only overrides
            cfg = load_config(recipe, overrides, schema=HealthConfig)
            summary = train_health(cfg, args.run_dir, resume=not args.no_resume)
        elif args.command == "baselines":
            sys.stdout.write(_baselines(args) + "\n")
            return 0
        else:
            summary = _anomaly(args)
    except (FreamerError, FileNotFoundError) as err:
        sys.stderr.write(f"error: {err}\n")
        return 2
    sys.stdout.write(json.dumps(summary, indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(prog="python -m freamer_rl.health.cli"))
