"""Table 15: MLP, CNN, SlotAttn+CrossAttn and Foundation encoders on the same RSSM core, 3 seeds each, plus the
imagination throughput of the world-model env vs TorchRL's DreamerEnv at equal sizes.

    python benchmarks/health_benchmark.py                       # full: 4 encoders x 3 seeds (the recipes' sizes)
    python benchmarks/health_benchmark.py --quick               # smoke: tiny sizes, 2 seeds, ~1-2 minutes
    python benchmarks/health_benchmark.py --encoders mlp foundation --seeds 0 1 2 collect.iterations=40
    python benchmarks/health_benchmark.py --reuse               # finish an interrupted table; redo only the report

Each (encoder, seed) is one :func:`freamer_rl.health.trainer.run_health` with ``recipes/health/health_<encoder>.yaml``
(plus the overrides given on the command line), in its own process, ``--workers`` at a time (one thread each).
Writes to ``--out`` (default ``benchmarks/results/health``):

* ``results.md`` -- the Table 15 layout: per encoder, mean +- std across seeds (sample std, ddof = 1) of the
  real-env evaluation return, violations per episode (steps with HR > 160 bpm), reconstruction MSE (raw units, per
  feature) and imagination horizon (steps; definition in :mod:`freamer_rl.world_model.metrics`), plus the
  Foundation / MLP reward ratio and std ratio (the issue's targets), and the imagination throughput table;
* ``results.csv`` -- one row per run; ``summary.csv`` -- one row per encoder; ``imagination_throughput.json``;
* ``runs/<encoder>_s<seed>/`` -- each run's directory (progress.csv, summary.json, checkpoint.pt).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENCODERS = ("mlp", "cnn", "slotattn", "foundation")
LABELS = {
    "mlp": "MLP (vanilla)", "cnn": "CNN", "slotattn": "SlotAttn+CrossAttn", "foundation": "Foundation (FreamerV1)",
}
METRICS = (
    ("eval_return_mean", "Reward", "{:.1f}"),
    ("eval_violations_mean", "Violations", "{:.2f}"),
    ("recon_mse", "MSE", "{:.3f}"),
    ("imagination_horizon", "Horizon", "{:.1f}"),
)
#: sizes of the smoke run (--quick): seconds per run
QUICK = [
    "env.num_envs=4", "env.episode_length=64", "collect.iterations=3", "collect.prefill_frames=256",
    "collect.frames_per_iter=128", "world_model.seq_len=16", "world_model.batch_size=4", "world_model.train_steps=4",
    "world_model.prefill_train_steps=4", "world_model.deter_dim=32", "world_model.stoch_dim=8",
    "world_model.hidden=32", "encoder.embed_dim=16", "encoder.dim=16", "encoder.hidden=32", "encoder.fm_hidden=16",
    "encoder.memory_slots=4", "encoder.memory_width=8", "imagination.num_seeds=32", "imagination.updates=2",
    "imagination.policy_hidden=32", "eval.num_envs=4", "eval.horizon_context=4", "eval.horizon_max=16",
    "eval.mse_windows=8", "eval.horizon_windows=16",
]  # fmt: skip


def _run_job(job: dict) -> dict:
    import torch
    import yaml

    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING)
    import shutil

    from freamer_rl.trainers.registry import load_config
    from freamer_rl.health.config import HealthConfig, health_config_to_dict
    from freamer_rl.health.trainer import run_health

    cfg = load_config(
        ROOT / "recipes" / "health" / f"health_{job['encoder']}.yaml",
        [*job["overrides"], f"run.seed={job['seed']}", "run.progress_bar=false", "run.threads=1"],
        schema=HealthConfig,
    )
    run_dir = Path(job["out"]) / "runs" / f"{job['encoder']}_s{job['seed']}"
    wanted = yaml.safe_load(yaml.safe_dump(health_config_to_dict(cfg), sort_keys=False))
    same = (run_dir / "config.yaml").is_file() and yaml.safe_load((run_dir / "config.yaml").read_text()) == wanted
    if job.get("reuse") and same and (run_dir / "summary.json").is_file():
        logging.getLogger("health_benchmark").warning("reusing the finished run %s (same resolved config)", run_dir)
        return json.loads((run_dir / "summary.json").read_text())
    if run_dir.exists() and not (job.get("reuse") and same):
        # the benchmark owns its run folders: without --reuse, or with another config, a run is trained afresh
        shutil.rmtree(run_dir)
    t0 = time.perf_counter()  # with --reuse and the same config, an interrupted run resumes from its checkpoint
    summary = run_health(cfg, run_dir)
    summary["job_wall_s"] = time.perf_counter() - t0
    return summary


def _mean_std(values: list[float]) -> tuple[float, float]:
    vals = [v for v in values if v is not None and v == v]
    if not vals:
        return float("nan"), float("nan")
    return statistics.fmean(vals), (statistics.stdev(vals) if len(vals) > 1 else 0.0)


def aggregate(results: list[dict]) -> list[dict]:
    rows = []
    for enc in ENCODERS:
        runs = [r for r in results if r["encoder"] == enc]
        if not runs:
            continue
        row = {"encoder": enc, "seeds": len(runs)}
        for key, _, _ in METRICS:
            row[f"{key}_mean"], row[f"{key}_std"] = _mean_std([r.get(key) for r in runs])
        row["wall_time_s_mean"] = statistics.fmean(r["wall_time_s"] for r in runs)
        row["params_encoder"] = runs[0]["params_encoder"]
        row["params_world_model"] = runs[0]["params_world_model"]
        rows.append(row)
    return rows


def write_report(results: list[dict], table: list[dict], throughput: dict | None, out: Path, args) -> str:
    out.mkdir(parents=True, exist_ok=True)
    run_keys = ["encoder", "seed", "eval_return_mean", "eval_return_std", "eval_violations_mean", "eval_length_mean",
                "recon_mse", "recon_mse_imu", "recon_mse_hr_features", "imagination_horizon",
                "imagination_horizon_std", "frames", "wall_time_s", "params_encoder", "params_world_model"]  # fmt: skip
    with (out / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=run_keys, extrasaction="ignore")
        w.writeheader()
        for r in sorted(results, key=lambda r: (ENCODERS.index(r["encoder"]), r["seed"])):
            w.writerow(r)
    if table:
        with (out / "summary.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(table[0]))
            w.writeheader()
            w.writerows(table)
    lines = [
        "# Health encoder comparison (paper Table 15)",
        "",
        f"Seeds {args.seeds}; recipes `recipes/health/health_<encoder>.yaml`"
        + (f" with overrides `{' '.join(args.overrides)}`" if args.overrides else "")
        + (" (--quick smoke sizes)" if args.quick else "") + ". Same RSSM core, reward, PPO and data; only the "
        "encoder differs. Mean +- std across seeds (sample std). Reward: real-env evaluation return per episode; "
        "Violations: steps with HR > 160 bpm per episode; MSE: reconstruction MSE per feature in raw units on "
        "held-out evaluation episodes; Horizon: open-loop imagined steps before the reward prediction error exceeds "
        "the tolerance (see freamer_rl.world_model.metrics).",
        "",
        "| Encoder | " + " | ".join(label for _, label, _ in METRICS) + " | params (encoder) | wall s / run |",
        "|---|" + "---|" * (len(METRICS) + 2),
    ]
    for row in table:
        cells = [f"{fmt.format(row[f'{k}_mean'])} +- {fmt.format(row[f'{k}_std'])}" for k, _, fmt in METRICS]
        lines.append(f"| {LABELS[row['encoder']]} | " + " | ".join(cells)
                     + f" | {row['params_encoder']:,} | {row['wall_time_s_mean']:.0f} |")  # fmt: skip
    by = {r["encoder"]: r for r in table}
    if "mlp" in by and "foundation" in by:
        f, m = by["foundation"], by["mlp"]
        ratio = f["eval_return_mean_mean"] / m["eval_return_mean_mean"] if m["eval_return_mean_mean"] else float("nan")
        std_ratio = m["eval_return_mean_std"] / f["eval_return_mean_std"] if f["eval_return_mean_std"] else float("inf")
        lines += [
            "",
            f"Foundation / MLP reward: {ratio:.2f}x (target >= 2x; paper 2.4x; a ratio of returns is only "
            f"meaningful when both are positive). MLP std / Foundation std: {std_ratio:.2f}x (target > 1; paper 16x). "
            f"Reward difference: {f['eval_return_mean_mean'] - m['eval_return_mean_mean']:+.1f}.",
        ]
    if throughput:
        med = throughput["median_steps_per_s"]
        lines += [
            "",
            "## Imagination throughput (imagined steps/s, median over rounds)",
            "",
            f"batch {throughput['batch']}, horizon {throughput['horizon']}, sizes {throughput['sizes']}, "
            f"{throughput['threads']} thread(s), {throughput['rounds']} interleaved rounds "
            "(freamer_rl.world_model.bench_imagination).",
            "",
            "| env | steps/s | ratio vs DreamerEnv | ratio vs the DreamerEnv doing the same work |",
            "|---|---|---|---|",
        ]
        ratios = throughput["median_ratio_vs_dreamer_env"]
        equal = throughput["equal_work_ratio"]
        for k, v in med.items():
            same = (f"{equal[k]:.2f} (vs {throughput['equal_work_pairs'][k]}, median of per-round ratios)"
                    if k in equal else "")
            lines.append(f"| {k} | {v:,.0f} | {ratios.get(k, 1.0):.2f} | {same} |")
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Table 15: health encoders on the same RSSM core")
    ap.add_argument("--encoders", nargs="+", default=list(ENCODERS), choices=ENCODERS)
    ap.add_argument("--seeds", type=int, nargs="+", default=None, help="default 0 1 2 (--quick: 0 1)")
    ap.add_argument("--workers", type=int, default=2, help="runs in parallel (one CPU thread each)")
    ap.add_argument("--out", default=None, help="default benchmarks/results/health (--quick: .../health_quick)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes and 2 seeds: a smoke test of the whole table")
    ap.add_argument("--skip-throughput", action="store_true", help="do not run the imagination throughput bench")
    ap.add_argument("--reuse", action="store_true",
                    help="take a finished run (summary.json) whose saved config equals the resolved one instead of "
                         "training it again (code changes are not detected: drop --reuse after changing the pipeline)")
    ap.add_argument("overrides", nargs="*", help="dotted overrides applied to every recipe")
    args = ap.parse_args(argv)
    if args.seeds is None:
        args.seeds = [0, 1] if args.quick else [0, 1, 2]
    out = Path(args.out or ROOT / "benchmarks" / "results" / ("health_quick" if args.quick else "health"))
    overrides = [*(QUICK if args.quick else []), *args.overrides]
    jobs = [{"encoder": e, "seed": s, "overrides": overrides, "out": str(out), "reuse": args.reuse}
            for e in args.encoders for s in args.seeds]  # fmt: skip
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    log = logging.getLogger("health_benchmark")
    log.info("%d runs, %d at a time -> %s", len(jobs), args.workers, out)
    t0 = time.perf_counter()
    if args.workers > 1:
        with mp.get_context("spawn").Pool(args.workers) as pool:
            results = pool.map(_run_job, jobs, chunksize=1)
    else:
        results = [_run_job(j) for j in jobs]
    log.info("runs done in %.0f s", time.perf_counter() - t0)
    throughput = None
    if not args.skip_throughput:
        from freamer_rl.world_model.bench_imagination import run as bench_run

        throughput = bench_run(batch=64, horizon=15, rounds=3 if args.quick else 20, rollouts_per_round=2, threads=1)
        out.mkdir(parents=True, exist_ok=True)
        (out / "imagination_throughput.json").write_text(json.dumps(throughput, indent=2))
    table = aggregate(results)
    text = write_report(results, table, throughput, out, args)
    print(text)  # noqa: T201 -- CLI output
    return 0


if __name__ == "__main__":
    sys.exit(main())
