"""``freamer-rl`` command line: train, eval, params -- for every domain -- and the health anomaly report.

    freamer-rl train recipes/minigrid_multiroom_n2s4.yaml optim.lr=3e-4 run.seed=1
    freamer-rl train recipes/health/health_foundation.yaml collect.iterations=5
    freamer-rl eval runs/<name>/checkpoints/checkpoint_000100000.pt --episodes 50
    freamer-rl eval runs/<health run>                     (any domain: the checkpoint records its trainer)
    freamer-rl params recipes/minigrid_multiroom_n2s4_clip.yaml
    freamer-rl health anomaly runs/<health run> --hours 48
    freamer-rl suite recipes/suites/n2s4_baselines.yaml --jobs 2    (recipes x envs x seeds, resumable; see suite.py)

``train``/``params`` dispatch on the recipe's ``trainer:`` key and ``eval`` on the checkpoint's trainer through the
registry :data:`freamer_rl.trainers.registry.TRAINERS` (``freamer-rl health train`` is an alias of ``train``).

User errors (bad recipe key or type, unknown env id, a modality the env lacks, missing CLIP weights, a checkpoint
from another config or one that is not plain tensors and data, a run directory in use by another run, ``--no-resume``
on a run that has checkpoints, an output folder that cannot be written, a size too large to allocate) print one
``error:`` line and exit with status 2; ``--debug`` shows the traceback.
Ctrl-C exits with 130 and SIGTERM with 143, both after writing a checkpoint; rerunning the same command resumes
(also after ``kill -9``: from the last periodic checkpoint).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from freamer_rl import __version__
from freamer_rl.config.sections import CorruptionConfig, check_corruption
from freamer_rl.errors import ConfigError, FreamerError
from freamer_rl.experiments.chain import run_chain
from freamer_rl.experiments.health_corruption import main as health_corruption_main
from freamer_rl.experiments.suite import dry_run_listing, run_suite
from freamer_rl.health.cli import main as health_main
from freamer_rl.run.params import OFFLINE_NOTE, format_parameter_table
from freamer_rl.run.rundir import Terminated
from freamer_rl.trainers.registry import evaluate_any, get_trainer, load_recipe

logger = logging.getLogger("freamer_rl")


def _result_json(result: dict) -> str:
    """An evaluation as indented JSON with each list of numbers (the per-episode values) on one line."""
    flat = {k: v for k, v in result.items() if isinstance(v, list) and all(isinstance(x, int | float) for x in v)}
    text = json.dumps({k: (f"@{k}@" if k in flat else v) for k, v in result.items()}, indent=2, default=str)
    for k, v in flat.items():
        text = text.replace(json.dumps(f"@{k}@"), json.dumps(v))
    return text


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="freamer-rl", description="FreamerV1 with TorchRL")
    parser.add_argument("--debug", action="store_true", help="show tracebacks for user errors")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    parser.add_argument("--version", action="version", version=f"freamer-rl {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p_train = sub.add_parser("train", help="train from a YAML recipe")
    p_train.add_argument("recipe", help="path to a recipe YAML")
    p_train.add_argument("overrides", nargs="*", help="dotted overrides, e.g. optim.lr=3e-4 run.seed=1")
    p_train.add_argument("--run-dir", default=None, help="run directory (default: run.output_dir/run.name)")
    p_train.add_argument(
        "--no-resume",
        action="store_true",
        help="start from scratch; refused (nothing is deleted) when the run directory already holds checkpoints: "
        "use another run.name / --run-dir, or delete the old run yourself",
    )

    p_chain = sub.add_parser(
        "chain", help="train a chain of recipes (a curriculum), each stage starting from the previous one's weights"
    )
    p_chain.add_argument("chain", help="path to a chain YAML (freamer_rl.experiments.chain)")
    p_chain.add_argument(
        "overrides",
        nargs="*",
        help="dotted overrides: a chain-file key (name, seed, output_dir, overrides, stages) edits the chain file, "
        "e.g. seed=1; any other key goes to every stage after the stage's own, so it wins, e.g. "
        "run.total_frames=2048 shrinks every stage",
    )

    p_suite = sub.add_parser(
        "suite", help="a benchmark suite: recipes x envs x seeds, resumable; CSV/Markdown tables and learning curves"
    )
    p_suite.add_argument("suite", help="path to a suite YAML (freamer_rl.experiments.suite)")
    p_suite.add_argument("--jobs", type=int, default=1, help="runs trained at a time, one process each (default 1)")
    p_suite.add_argument("--output", default=None, help="results folder (default: the suite's output, results/<name>)")
    p_suite.add_argument("--report-only", action="store_true", help="rebuild tables and plots without training")
    p_suite.add_argument("--dry-run", action="store_true", help="list the runs and their status; train nothing")
    p_suite.add_argument(
        "--only",
        action="append",
        default=None,
        metavar="LABEL",
        help="train (and evaluate) only this entry; repeat for more; the report still covers every run",
    )

    p_eval = sub.add_parser("eval", help="evaluate a checkpoint of any domain")
    p_eval.add_argument("checkpoint", help="a checkpoint .pt file or a run directory (uses its latest checkpoint)")
    p_eval.add_argument("--episodes", type=int, default=20)
    p_eval.add_argument("--deterministic", action="store_true", help="argmax actions instead of sampling")
    p_eval.add_argument("--num-envs", type=int, default=None)
    p_eval.add_argument("--seed", type=int, default=12345)
    p_eval.add_argument(
        "--corrupt",
        action="append",
        default=None,
        metavar="KEY:KIND:LEVEL",
        help="corrupt an observation during evaluation, e.g. pixels:gaussian:1.0, grid:salt:0.3, "
        "grid:dropout:0.5, grid:dropout_episode:0.5, direction:stale:4, pixels:noisy_tv:0.25, or "
        "embed.state:gaussian:4 (noise on a Layer-1 embedding, Table 13); repeatable; replaces the recipe's "
        "env.corrupt entries for evaluation (--corrupt none: a clean evaluation)",
    )

    p_health = sub.add_parser(
        "health", help="wearable-health: anomaly report (and train, an alias of freamer-rl train)", add_help=False
    )
    p_health.add_argument("health_args", nargs=argparse.REMAINDER)

    p_params = sub.add_parser(
        "params", help="print the parameter table (trainable vs frozen per component); never downloads weights"
    )
    p_params.add_argument("recipe")
    p_params.add_argument("overrides", nargs="*")
    p_params.add_argument("--markdown", action="store_true")
    return parser


def _run(args: argparse.Namespace) -> int:
    if args.command == "train":
        name, cfg = load_recipe(args.recipe, args.overrides)  # the recipe is read once
        summary = get_trainer(name, args.recipe).train(cfg, args.run_dir, resume=not args.no_resume)
        logger.info("summary: %s", json.dumps(summary, default=str))
        return 0
    if args.command == "chain":
        rows = run_chain(args.chain, args.overrides)
        last, rate = rows[-1], rows[-1]["final_success_rate"]
        logger.info(
            "chain finished: %d stages, %d frames, last stage success %s | %s",
            len(rows),
            last["chain_frames"],
            "n/a" if rate is None else f"{rate:.3f}",
            Path(last["run_dir"]).parent / "chain_summary.md",
        )
        return 0
    if args.command == "suite":
        return _suite(args)
    if args.command == "eval":
        options = {} if args.corrupt is None else {"corrupt": parse_corruptions(args.corrupt)}
        result = evaluate_any(
            args.checkpoint,
            episodes=args.episodes,
            deterministic=args.deterministic,
            num_envs=args.num_envs,
            seed=args.seed,
            **options,
        )
        sys.stdout.write(_result_json(result) + "\n")
        return 0
    if args.command == "health":
        if args.health_args[:1] == ["corruption"]:  # the sweep aggregates with experiments.stats (a higher tier)
            return health_corruption_main(args.health_args[1:])
        return health_main(args.health_args, prog="freamer-rl health")
    if args.command == "params":
        name, cfg = load_recipe(args.recipe, args.overrides)
        table = get_trainer(name, args.recipe).params(cfg)
        sys.stdout.write(format_parameter_table(table, markdown=args.markdown) + "\n" + OFFLINE_NOTE + "\n")
        return 0
    raise AssertionError(args.command)


def _suite(args: argparse.Namespace) -> int:
    """``freamer-rl suite``: the dry-run listing, or train + report; 1 when runs failed (the others still ran)."""
    if args.dry_run:
        sys.stdout.write(dry_run_listing(args.suite, args.output))
        return 0
    result = run_suite(args.suite, jobs=args.jobs, output=args.output, report_only=args.report_only, only=args.only)
    sys.stdout.write(f"{Path(result['output']) / 'summary.md'}\n")
    if result["failed"]:
        sys.stderr.write(
            f"{len(result['failed'])} of {len(result['runs'])} runs failed (see runs.csv): "
            f"{', '.join(result['failed'])}\n"
        )
        return 0 if args.report_only else 1
    if result["eval_failed"]:
        sys.stderr.write(
            f"{len(result['eval_failed'])} evaluations failed (see robustness.md): {', '.join(result['eval_failed'])}\n"
        )
        return 1
    return 0


#: how torch reports a failed allocation (CPU: "[enforce fail at alloc_cpu.cpp] ... DefaultCPUAllocator: not enough
#: memory"; CUDA: "CUDA out of memory")
_ALLOCATION_FAILURES = (
    "not enough memory",
    "[enforce fail",
    "out of memory",
    "defaultcpuallocator",
    "cannot allocate memory",
)


def allocation_failure(err: BaseException) -> str | None:
    """The one ``error:`` line for an allocation that failed (a size in the recipe too large for the machine), or
    None when ``err`` is something else."""
    text = " ".join(str(err).split())
    if not isinstance(err, MemoryError) and not (
        isinstance(err, RuntimeError) and any(p in text.lower() for p in _ALLOCATION_FAILURES)
    ):
        return None
    shown = text if len(text) <= 160 else text[:157] + "..."
    return (
        f"out of memory ({type(err).__name__}: {shown or 'no details'}): a size in the recipe is too large for "
        "this machine (e.g. model.embed_dim, model.head_hidden, network.hidden, a batch, sequence or buffer "
        "size); lower it (--debug shows where it was allocated)"
    )


def parse_corruptions(specs: list[str]) -> list[CorruptionConfig]:
    """``--corrupt KEY:KIND:LEVEL`` values as ``env.corrupt`` entries for evaluation (``none``: no corruption)."""
    if specs == ["none"]:
        return []
    entries = []
    for spec in specs:
        parts = spec.rsplit(":", 2)
        try:
            key, kind, level = parts[0], parts[1], float(parts[2])
        except (IndexError, ValueError):
            raise ConfigError(f"--corrupt {spec!r}: expected KEY:KIND:LEVEL, e.g. pixels:gaussian:1.0") from None
        entries.append(CorruptionConfig(key=key, kind=kind, level=level, when="eval"))
    check_corruption(entries)
    return entries


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args, unknown = parser.parse_known_args(argv)
    if args.command == "health":  # its own parser takes everything after "health", options included
        args.health_args = unknown + args.health_args
    elif (
        args.command in ("train", "params", "chain")
        and unknown
        and all("=" in a and not a.startswith("-") for a in unknown)
    ):
        # overrides after an option (train recipe.yaml --run-dir D optim.lr=1e-3): argparse leaves them unparsed
        args.overrides = list(args.overrides) + unknown
    elif unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    logging.basicConfig(
        level=getattr(logging, args.log_level), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        return _run(args)
    except FreamerError as err:
        if args.debug:
            raise
        sys.stderr.write(f"error: {err}\n")
        return 2
    except (MemoryError, RuntimeError) as err:
        line = allocation_failure(err)
        if line is None or args.debug:
            raise
        sys.stderr.write(f"error: {line}\n")
        return 2
    except KeyboardInterrupt as err:
        if isinstance(err, Terminated):  # SIGTERM: the trainer checkpointed like on Ctrl-C; 128 + 15 as a shell would
            sys.stderr.write("terminated (SIGTERM): rerun the same command to resume from the latest checkpoint\n")
            return 143
        sys.stderr.write("interrupted: rerun the same command to resume from the latest checkpoint\n")
        return 130


if __name__ == "__main__":
    sys.exit(main())
