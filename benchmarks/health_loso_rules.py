"""Held-out-subject returns of model-free health policies beside the heart-rate rule and the oracle planner.

    python benchmarks/health_loso_rules.py results/health_mf_loso [--episodes 16] [--seed 12345]

Reads a suite folder of ``recipes/suites/health_mf_loso.yaml`` (runs of collector-based trainers on the ``health``
adapter, each evaluated by the suite's ``evaluate:`` section on the subjects of its ``env.eval_options``: its
``eval/clean.json``), scores the heart-rate rule, always-Continue and the oracle planner on the same episodes of each
fold (the rule, the heart-rate controller -- the rule plus Increase back to plan below 145 bpm -- and Continue through
the collector-based evaluator, the oracle through the health trainer's; the rule is scored both ways and must agree,
or the script stops), and writes, in the suite folder:

* ``loso_references.json``: the references per fold (cached: a rerun scores only new folds and references);
* ``loso_vs_rules.json``: one row per run (arm, seed, held-out subject, return, the references);
* ``loso_vs_rules.md``: the health suites' leave-one-subject-out table (reward, rule, oracle, paired differences to
  the rule and to the controller, fraction of the oracle, each a mean over folds with a two-level bootstrap interval).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

from freamer_rl.experiments.health_table import loso_markdown
from freamer_rl.health.config import load_health_config
from freamer_rl.health.reference import evaluate_reference, make_reference_policy
from freamer_rl.run.evaluation import run_episodes
from freamer_rl.trainers.registry import get_trainer, load_config

RULE_TOLERANCE = 1e-3  # the rule's return through both evaluators (float32 sums of 120 steps)
COLLECTOR_REFERENCES = ("hr_threshold", "hr_controller", "continue")  # scored by the collector-based evaluator


def _runs(suite_dir: Path) -> list[tuple[str, int, Path]]:
    """``(label, seed, run dir)`` of every run with a clean evaluation."""
    out = []
    for path in sorted(suite_dir.glob("runs/*/*/seed*/eval/clean.json")):
        run = path.parents[1]
        out.append((run.parents[1].name, int(run.name.removeprefix("seed")), run))
    return out


def _health_config(cfg, episodes: int, seed: int):
    """The health trainer's config of the same env, training subjects and held-out subjects."""
    opts, held = cfg.env.options, cfg.env.eval_options
    overrides = [f"env.id={cfg.env.id}", f"eval.num_envs={episodes}", f"eval.seed={seed}"]
    # the references read none of the world-model or horizon-probe fields: smallest values, valid for short episodes
    overrides += ["world_model.seq_len=1", "eval.horizon_context=1", "eval.horizon_max=1"]
    overrides += [f"env.subjects={list(opts['subjects'])}", f"eval.subjects={list(held['subjects'])}"]
    # every option the two configs share (HEALTH_OPTION_NAMES less the subjects, set above, and gain_jitter, which the
    # health trainer does not take: evaluate with eval_options.gain_jitter 0); the rule check catches any difference
    shared = ("episode_length", "rate_hz", "synthetic_duration_s", "data_seed", "reward_weights", "data_dir")
    overrides += [f"env.{k}={opts[k]}" for k in shared if opts.get(k) is not None]
    return load_health_config(None, overrides)


def run_config(run: Path):
    """A finished run's config (``config.yaml``), built with the schema of the trainer its ``summary.json`` names."""
    trainer = json.loads((run / "summary.json").read_text())["trainer"]
    return load_config(run / "config.yaml", schema=get_trainer(trainer).schema)


def references(run: Path, episodes: int, seed: int, known: dict[str, float] | None = None) -> dict[str, float]:
    """The rule, the controller, Continue and the oracle on the evaluation episodes of ``run``'s held-out subjects;
    ``known``: a cached fold's references, of which only the missing ones are scored."""
    known = dict(known or {})
    cfg = run_config(run)
    if not cfg.env.eval_options.get("subjects"):
        raise SystemExit(f"error: {run / 'config.yaml'}: env.eval_options.subjects is not set (no held-out subject)")
    options = {"episodes": episodes, "deterministic": True, "num_envs": episodes, "seed": seed}
    out = known | {
        f"eval_ref_{name}_return": run_episodes(cfg, make_reference_policy(name), [], **options)["return_mean"]
        for name in COLLECTOR_REFERENCES
        if f"eval_ref_{name}_return" not in known
    }
    if "eval_ref_oracle_return" in known:  # checked against the health trainer when it was scored
        return out
    health = _health_config(cfg, episodes, seed)
    rule = evaluate_reference(health, "hr_threshold")["return_mean"]
    if not math.isclose(rule, out["eval_ref_hr_threshold_return"], abs_tol=RULE_TOLERANCE):
        raise SystemExit(
            f"error: {run}: the heart-rate rule scores {out['eval_ref_hr_threshold_return']:.4f} through the "
            f"collector-based evaluator and {rule:.4f} through the health trainer's: not the same episodes"
        )
    out["eval_ref_oracle_return"] = evaluate_reference(health, "oracle")["return_mean"]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("suite_dir", type=Path)
    parser.add_argument("--episodes", type=int, default=16, help="the suite's evaluate.episodes")
    parser.add_argument("--seed", type=int, default=12345, help="the suite's evaluate.seed")
    args = parser.parse_args(argv)
    runs = _runs(args.suite_dir)
    if not runs:
        print(f"error: no runs with eval/clean.json under {args.suite_dir}/runs", file=sys.stderr)
        return 1
    cache_path = args.suite_dir / "loso_references.json"
    cache = json.loads(cache_path.read_text()) if cache_path.is_file() else {}
    rows = []
    for label, seed, run in runs:
        evaluation = json.loads((run / "eval" / "clean.json").read_text())
        if evaluation.get("episodes") != args.episodes or not evaluation.get("deterministic"):
            print(f"error: {run}/eval/clean.json: expected {args.episodes} deterministic episodes", file=sys.stderr)
            return 1
        fold = ", ".join(str(s) for s in evaluation["env_options"]["subjects"])
        scored = cache.get(fold, {})
        if fold not in cache or any(f"eval_ref_{name}_return" not in scored for name in COLLECTOR_REFERENCES):
            cache[fold] = references(run, args.episodes, args.seed, scored)
            cache_path.write_text(json.dumps(cache, indent=1))
        arm = re.sub(r"_fold\d+$", "", label)
        rows.append(
            {"label": label, "encoder": arm, "seed": seed, "status": "done", "eval_subjects": fold}
            | {"eval_return_mean": evaluation["return_mean"]}
            | cache[fold]
        )
    (args.suite_dir / "loso_vs_rules.json").write_text(json.dumps(rows, indent=1))
    lines = [f"# {args.suite_dir.name}: held-out subjects against the heart-rate rules", *loso_markdown(rows)]
    (args.suite_dir / "loso_vs_rules.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
