"""Command line of the health domain.

    freamer-rl health anomaly RUN_DIR_OR_CHECKPOINT [--hours 48] [--out DIR] [--seed 0]
    freamer-rl health train recipes/health/health_foundation.yaml [--run-dir DIR] [--no-resume] [key=value ...]

``anomaly`` runs :func:`~freamer_rl.health.anomaly_report.anomaly_report` (Fig. 4 picture, default output: the run
directory). ``train`` is an alias of ``freamer-rl train`` for health recipes (the registry entry
:func:`freamer_rl.trainers.health.train`, resumable) and prints the summary as JSON.
:func:`main` takes ``argv`` so that ``freamer-rl health ...`` can delegate to it.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from freamer_rl.config.loader import load_config
from freamer_rl.errors import FreamerError
from freamer_rl.health.anomaly_report import anomaly_report
from freamer_rl.health.config import HealthConfig
from freamer_rl.trainers.health import train as train_health  # the registry entry (its STRUCTURAL)


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
    return parser


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
        else:
            ckpt = Path(args.checkpoint)
            out = Path(args.out) if args.out else (ckpt if ckpt.is_dir() else ckpt.parent)
            summary = anomaly_report(ckpt, out, hours=args.hours, seed=args.seed, k_sigma=args.k_sigma)
    except (FreamerError, FileNotFoundError) as err:
        sys.stderr.write(f"error: {err}\n")
        return 2
    sys.stdout.write(json.dumps(summary, indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(prog="python -m freamer_rl.health.cli"))
