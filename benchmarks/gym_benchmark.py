"""FreamerV1 (full trunk: vector encoder, FM refiner, FNO fuser, DNC) vs TorchRL PPO-MLP on a gymnasium env, same
recipe PPO settings and frame budget, 3 seeds each, two runs at a time, one thread each.

    python benchmarks/gym_benchmark.py recipes/gym/cartpole.yaml --frames 100000 --target 475
    python benchmarks/gym_benchmark.py recipes/gym/pendulum.yaml --frames 200000
    python benchmarks/gym_benchmark.py recipes/gym/cartpole.yaml --frames 2048 --seeds 0   # smoke

Resumable: rerunning the same command skips finished runs and resumes FreamerV1 runs from their last checkpoint
(``--fresh`` starts over). Writes ``results.md``, ``results.csv`` and ``learning_curves.png`` (mean return over the
last 100 episodes vs frames, mean across seeds with a min-max band) into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import logging
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from harness import first_reaching, mean_std, plot_bands, run_freamer, run_jobs  # noqa: E402
from ppo_mlp_gym import train_ppo_mlp_gym  # noqa: E402

NAMES = {"freamer": "FreamerV1 (recipe)", "ppo_mlp": "TorchRL PPO-MLP 64x64"}


def run_ppo_mlp(job: dict) -> dict:
    return train_ppo_mlp_gym(job["recipe"], job["seed"], job["frames"], overrides=job.get("overrides", []))


def write_report(results: list[dict], out: Path, args) -> str:
    out.mkdir(parents=True, exist_ok=True)
    target = args.target
    rows = []
    for r in sorted(results, key=lambda r: (r["method"], r["seed"])):
        frames_t, eps_t = first_reaching(r["rows"], "return_mean", target) if target is not None else (None, None)
        rows.append({"method": r["method"], "seed": r["seed"], "final_return_mean": r["final_return_mean"],
                     "frames_to_target": frames_t, "episodes_to_target": eps_t, "frames": r["frames"],
                     "episodes": r["episodes"], "fps": r["fps"]})
    with (out / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    env_id = results[0].get("env", args.recipe)
    tgt = f"{target:g}" if target is not None else "-"
    lines = [
        f"# {env_id}: FreamerV1 vs TorchRL PPO-MLP", "",
        f"Recipe `{Path(args.recipe).relative_to(ROOT) if Path(args.recipe).is_absolute() else args.recipe}`"
        f" {' '.join(args.overrides)}; {args.frames:,} frames per run; seeds {args.seeds}; generated "
        f"{time.strftime('%Y-%m-%d %H:%M')}. Return = mean over the last 100 episodes.", "",
        f"| method | seed | return at the end | frames to return >= {tgt} | episodes to it | frames/s |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        ft = "-" if target is None else f"{r['frames_to_target']:,}" if r["frames_to_target"] else "not reached"
        et = f"{r['episodes_to_target']:,}" if r["episodes_to_target"] else "-"
        lines.append(f"| {NAMES[r['method']]} | {r['seed']} | {r['final_return_mean']:.1f} | {ft} | {et} | "
                     f"{r['fps']:.0f} |")
    lines += ["", "| method | return at the end (mean ± std) | seeds reaching the target | frames/s (mean) |",
              "|---|---:|---:|---:|"]
    for m in NAMES:
        rs = [r for r in rows if r["method"] == m]
        if rs:
            reached = sum(r["frames_to_target"] is not None for r in rs)
            lines.append(f"| {NAMES[m]} | {mean_std([r['final_return_mean'] for r in rs])} | "
                         f"{reached}/{len(rs) if target is not None else '-'} | "
                         f"{statistics.mean(r['fps'] for r in rs):.0f} |")
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    plot_bands(results, out / "learning_curves.png", "return_mean", env_id, target=target,
               ylabel="mean return (last 100 episodes)")
    return text


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="FreamerV1 vs TorchRL PPO-MLP on a gymnasium env")
    ap.add_argument("recipe")
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--target", type=float, default=None, help="return threshold to report frames-to-target for")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=None, help="default: benchmarks/results/gym_<recipe name>")
    ap.add_argument("--methods", nargs="+", default=list(NAMES), choices=list(NAMES))
    ap.add_argument("--fresh", action="store_true", help="discard finished runs of this benchmark and start over")
    ap.add_argument("overrides", nargs="*", help="dotted recipe overrides, applied to both methods")
    args = ap.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    out = Path(args.out or ROOT / "benchmarks" / "results" / f"gym_{Path(args.recipe).stem}")
    fns = {"freamer": run_freamer, "ppo_mlp": run_ppo_mlp}
    jobs = [(fns[m], {"method": m, "seed": s, "recipe": str(Path(args.recipe).resolve()), "frames": args.frames,
                      "overrides": args.overrides, "out": str(out)})
            for s in args.seeds for m in args.methods]
    results = run_jobs(jobs, workers=args.workers, fresh=args.fresh)
    sys.stdout.write(write_report(results, out, args))


if __name__ == "__main__":
    main()
