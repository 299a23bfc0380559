"""What a trained health policy does by heart rate: its deterministic actions on the held-out subject, counted per
heart-rate bucket, beside the heart-rate rule's on the same observations.

    python benchmarks/health_action_profile.py RUN_DIR [RUN_DIR ...] [--episodes 8] [--seed 12345]

``RUN_DIR``: a ``ppo_baseline`` run on the ``health`` adapter (e.g. ``benchmarks/results/health_mf_loso/runs/
mlp_prior_fold108/pamap2-health-varied/seed0`` with its checkpoints). Episodes run in the run's evaluation env
(``env.eval_options`` over ``env.options``: the held-out subject), one unbatched env seeded with ``--seed``. Prints a
table per run and writes ``action_profile.json`` in each run folder: per bucket (``<130``, ``130-150``, ``150-170``,
``>170`` bpm) the count of each action, the rule's on the same observations (``rule_counts``), and the mean episode
return. The README's health section reads it for its claims on the rule-prior, jitter and shield arms (who rests
above 150 bpm on the most active subject, and what the policies do below it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from tensordict.nn import InteractionType, set_interaction_type

from freamer_rl.health.config import ACTION_NAMES
from freamer_rl.health.reference import make_reference_policy
from freamer_rl.run import env_registry
from freamer_rl.run.envs import env_options, eval_config
from freamer_rl.run.evaluation import read_checkpoint_config
from freamer_rl.trainers.baselines.common import build_network
from freamer_rl.trainers.baselines.config import PPOBaselineConfig

BUCKETS = ("<130", "130-150", "150-170", ">170")
EDGES = torch.tensor([130.0, 150.0, 170.0])


def profile(run: Path, episodes: int, seed: int) -> dict:
    """Action counts per heart-rate bucket and the mean return of ``episodes`` deterministic episodes."""
    summary = json.loads((run / "summary.json").read_text())
    if summary.get("trainer") != "ppo_baseline":
        raise SystemExit(f"error: {run}: trainer {summary.get('trainer')!r}; this script reads ppo_baseline runs")
    checkpoints = sorted((run / "checkpoints").glob("*.pt"))
    if not checkpoints:
        raise SystemExit(f"error: {run}/checkpoints: no checkpoint (the published folders keep none: retrain it)")
    ckpt, cfg = read_checkpoint_config(checkpoints[-1], PPOBaselineConfig)
    net = build_network(cfg)
    net.load_state_dict(ckpt["model"])
    net.eval()
    policy = net.get_policy_operator()
    ecfg = eval_config(cfg)
    env = env_registry.make_env(ecfg.env.adapter, ecfg.env.id, seed=seed, **env_options(ecfg))
    rule = make_reference_policy("hr_threshold")
    counts = torch.zeros(len(BUCKETS), len(ACTION_NAMES), dtype=torch.long)
    rule_counts = torch.zeros_like(counts)
    total = 0.0
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        for _ in range(episodes):
            td = env.rollout(100_000, policy, break_when_any_done=True)  # ends at the env's truncation
            bucket = torch.bucketize(td["heart_rate"].reshape(-1), EDGES)
            ruled = rule(td.exclude("action").clone())["action"].reshape(-1)
            for i in range(len(BUCKETS)):
                counts[i] += torch.bincount(td["action"].reshape(-1)[bucket == i], minlength=len(ACTION_NAMES))
                rule_counts[i] += torch.bincount(ruled[bucket == i], minlength=len(ACTION_NAMES))
            total += float(td["next", "reward"].sum())
    return {
        "run": str(run),
        "episodes": episodes,
        "seed": seed,
        "return_mean": total / episodes,
        "actions": list(ACTION_NAMES),
        "counts": {b: counts[i].tolist() for i, b in enumerate(BUCKETS)},
        "rule_counts": {b: rule_counts[i].tolist() for i, b in enumerate(BUCKETS)},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=12345)
    args = parser.parse_args(argv)
    for run in args.runs:
        result = profile(run, args.episodes, args.seed)
        (run / "action_profile.json").write_text(json.dumps(result, indent=1))
        print(f"{run}: return {result['return_mean']:.1f} per episode ({args.episodes} episodes)")
        print(f"  {'HR bpm':<9}" + "".join(f"{a:>10}" for a in ACTION_NAMES))
        for b, row in result["counts"].items():
            rule_row = result["rule_counts"][b]
            print(f"  {b:<9}" + "".join(f"{c:>10}" for c in row) + "   rule: " + " ".join(str(c) for c in rule_row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
