"""FreamerV1 (default offline recipe) vs TorchRL PPO-MLP on MiniGrid MultiRoom-N2-S4, 3 seeds each, in one run.

    python benchmarks/minigrid_benchmark.py                      # full benchmark (~30-60 min on 2 cores)
    python benchmarks/minigrid_benchmark.py --frames 4096 --seeds 0   # smoke

Resumable: rerunning the same command skips finished runs and resumes FreamerV1 runs from their last checkpoint
(``--fresh`` starts over). Writes to ``--out`` (default benchmarks/results/minigrid_n2s4/): ``results.md`` and ``results.csv`` (frames and
episodes to reach 95% success over the last 100 episodes, final success, frames/s, the FreamerV1/baseline
throughput ratio), ``curves.csv`` and ``learning_curves.png``. Runs go two at a time (one per core, one thread
each), FreamerV1 and the baseline side by side, so both see the same machine load.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from harness import mean_std, run_freamer, run_jobs  # noqa: E402

DEFAULT_RECIPE = ROOT / "recipes" / "minigrid_multiroom_n2s4.yaml"


def _run_ppo_mlp(job: dict) -> dict:
    import torch

    torch.set_num_threads(1)
    from ppo_mlp_baseline import train_ppo_mlp

    return train_ppo_mlp(job["env"], job["seed"], job["frames"])


def _run_freamer(job: dict) -> dict:
    """FreamerV1 through the library's Trainer; resumes from the run's last checkpoint (see harness)."""
    return run_freamer(job)


def _fmt(v, nd=0):
    if v is None:
        return "not reached"
    if isinstance(v, float):
        return f"{v:.{nd}f}" if nd else f"{v:,.0f}"
    return f"{v:,}"


def write_report(results: list[dict], out: Path, args) -> str:
    out.mkdir(parents=True, exist_ok=True)
    fields = ["method", "seed", "frames_to_95", "episodes_to_95", "final_success_rate", "frames", "episodes", "fps"]
    with (out / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in results:
            w.writerow({k: r.get(k) for k in fields})
    with (out / "curves.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "seed", "frames", "episodes", "success_rate", "return_mean"])
        for r in results:
            for row in r["rows"]:
                w.writerow([r["method"], r["seed"], row["frames"], row["episodes"], row["success_rate"], row["return_mean"]])
    names = {"freamer": "FreamerV1 (default offline recipe)", "ppo_mlp": "TorchRL PPO-MLP (FlatObs, 256x2)"}
    lines = [
        f"# MiniGrid benchmark: {args.env}",
        "",
        f"{args.frames:,} frames per run; seeds {args.seeds}; generated {time.strftime('%Y-%m-%d %H:%M')}.",
        "Success = terminated with positive reward; rates over the last 100 episodes.",
        "",
        "| method | seed | frames to 95% | episodes to 95% | final success | frames | episodes | frames/s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {names[r['method']]} | {r['seed']} | {_fmt(r.get('frames_to_95'))} | {_fmt(r.get('episodes_to_95'))} | "
            f"{r['final_success_rate']:.3f} | {r['frames']:,} | {r['episodes']:,} | {r['fps']:.0f} |"
        )
    lines += ["", "| method | episodes to 95% (mean ± std) | final success (mean ± std) | frames/s (mean) |", "|---|---:|---:|---:|"]
    fps = {}
    for m in ("freamer", "ppo_mlp"):
        rs = [r for r in results if r["method"] == m]
        if not rs:
            continue
        fps[m] = statistics.mean(r["fps"] for r in rs)
        reached = sum(r.get("episodes_to_95") is not None for r in rs)
        lines.append(
            f"| {names[m]} | {mean_std([r.get('episodes_to_95') for r in rs], 'not reached')} ({reached}/{len(rs)} seeds reached) | "
            f"{mean_std([r['final_success_rate'] for r in rs], 'not reached')} | {fps[m]:.0f} |"
        )
    if len(fps) == 2:
        lines += ["", f"Throughput ratio FreamerV1 / PPO-MLP: **{fps['freamer'] / fps['ppo_mlp']:.2f}x** (same run)."]
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    _plot(results, out / "learning_curves.png", args.env)
    return text


def _plot(results: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    colors = {"freamer": "tab:purple", "ppo_mlp": "tab:gray"}
    for r in results:
        xs_f = [row["frames"] for row in r["rows"]]
        xs_e = [row["episodes"] for row in r["rows"]]
        ys = [row["success_rate"] for row in r["rows"]]
        label = f"{r['method']} s{r['seed']}"
        axes[0].plot(xs_f, ys, color=colors[r["method"]], alpha=0.8, label=label)
        axes[1].plot(xs_e, ys, color=colors[r["method"]], alpha=0.8, label=label)
    for ax, xl in zip(axes, ("frames", "episodes")):
        ax.axhline(0.95, color="k", ls=":", lw=0.8)
        ax.set_xlabel(xl)
        ax.set_ylabel("success rate (last 100 episodes)")
        ax.set_ylim(-0.02, 1.02)
    axes[1].axvline(2000, color="tab:red", ls="--", lw=0.8)
    axes[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="FreamerV1 vs TorchRL PPO-MLP on MiniGrid")
    ap.add_argument("--env", default="MiniGrid-MultiRoom-N2-S4-v0")
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--recipe", default=str(DEFAULT_RECIPE))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "minigrid_n2s4"))
    ap.add_argument("--methods", nargs="+", default=["freamer", "ppo_mlp"], choices=["freamer", "ppo_mlp"])
    ap.add_argument("--fresh", action="store_true", help="discard finished runs of this benchmark and start over")
    ap.add_argument("overrides", nargs="*", help="dotted overrides for the FreamerV1 recipe")
    args = ap.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    out = Path(args.out)
    fns = {"freamer": _run_freamer, "ppo_mlp": _run_ppo_mlp}
    jobs = [
        (fns[m], {"method": m, "seed": s, "env": args.env, "frames": args.frames, "recipe": args.recipe,
                  "overrides": [f"env.id={args.env}", *args.overrides], "out": str(out)})
        for s in args.seeds for m in args.methods
    ]
    results = run_jobs(jobs, workers=args.workers, fresh=args.fresh)
    results.sort(key=lambda r: (r["method"] != "freamer", r["seed"]))
    print(write_report(results, out, args))
    (out / "results.json").write_text(json.dumps([{k: v for k, v in r.items() if k != "rows"} for r in results],
                                                 indent=2, default=str))


if __name__ == "__main__":
    main()
