"""Each training component of issue 12 switched on alone (and all together) against the plain recipe, 3 seeds each,
with TorchRL's PPO-MLP in the same run: what every piece does to the learning curve.

    python benchmarks/ablation_benchmark.py                                 # N2-S4, 80k frames, seeds 0 1 2
    python benchmarks/ablation_benchmark.py --arms base language ogm_a --seeds 0
    python benchmarks/ablation_benchmark.py --frames 4096 --seeds 0 --out /tmp/smoke      # smoke

Arms are recipe overrides (:data:`ARMS`) on ``--recipe``; ``ppo_mlp`` is the baseline. Per arm and seed: episodes
and frames to 80% / 95% success (last 100 episodes, from the 100th episode on), final success, frames/s; a table
with each arm's mean and its difference to ``base``, and learning curves (mean and min-max band over seeds) against
episodes. Resumable like every benchmark here (``harness``): finished runs are read back from ``<out>/jobs/``.
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

from harness import finished_results, first_reaching, mean_std, plot_bands, run_freamer, run_jobs  # noqa: E402

#: arm -> overrides of the recipe. Weights are Table A20's where the paper gives one.
ARMS: dict[str, list[str]] = {
    "base": [],
    "language": ["shaping.language.weight=0.2", "shaping.time_penalty=0.02"],
    "language_strong": ["shaping.language.weight=1.0", "shaping.time_penalty=0.02", "shaping.adaptive=true"],
    "language_adaptive": ["shaping.language.weight=0.2", "shaping.time_penalty=0.02", "shaping.adaptive=true"],
    "vision_language": ["shaping.vision_language=0.1"],
    "curiosity": ["shaping.curiosity=0.2"],
    "curiosity_low": ["shaping.curiosity=0.02"],
    "novelty": ["shaping.novelty.weight=0.1"],
    "success_buffer": ["success_buffer.enabled=true"],
    "ogm_a": ["ogm.mode=A"],
    "ogm_b": ["ogm.mode=B"],
    "adaptive_steps": ["model.flow.adaptive_steps=[1,2,3,5,7,10]"],
    "success_language": ["success_buffer.enabled=true", "shaping.language.weight=0.2", "shaping.time_penalty=0.02",
                         "shaping.adaptive=true"],
    # every component but curiosity (0% success alone at Table A20's weight in the first run)
    "all": ["shaping.language.weight=0.2", "shaping.time_penalty=0.02", "shaping.adaptive=true",
            "shaping.vision_language=0.1", "shaping.novelty.weight=0.1", "success_buffer.enabled=true", "ogm.mode=A",
            "model.flow.adaptive_steps=[1,2,3,5,7,10]"],
}  # fmt: skip
WINDOW = 100


def _run_ppo_mlp(job: dict) -> dict:
    import torch

    torch.set_num_threads(1)
    from ppo_mlp_baseline import train_ppo_mlp

    return train_ppo_mlp(job["env"], job["seed"], job["frames"])


def summarise(result: dict) -> dict:
    rows = [r for r in result["rows"] if r["episodes"] >= WINDOW]
    f80, e80 = first_reaching(rows, "success_rate", 0.80)
    f95, e95 = first_reaching(rows, "success_rate", 0.95)
    return {"arm": result["method"], "seed": result["seed"], "episodes_to_80": e80, "frames_to_80": f80,
            "episodes_to_95": e95, "frames_to_95": f95, "final_success": result["final_success_rate"],
            "episodes": result["episodes"], "fps": result.get("fps")}  # fmt: skip


def _mean(values: list) -> float | None:
    vals = [v for v in values if v is not None]
    return statistics.mean(vals) if vals else None


def write_report(results: list[dict], out: Path, env: str, frames: int, command: str) -> str:
    rows = [summarise(r) for r in results]
    arms = list(dict.fromkeys(r["arm"] for r in rows))
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot_bands([{"method": r["method"], "rows": [x for x in r["rows"] if x["episodes"] >= WINDOW]} for r in results],
               out / "learning_curves.png", "success_rate", f"{env}: components", x_key="episodes", target=0.95,
               ylabel="success (last 100 episodes)")  # fmt: skip
    base = [r for r in rows if r["arm"] == "base"]
    base_e95 = _mean([r["episodes_to_95"] for r in base])
    lines = [f"# Component ablation on {env}", "",
             f"{frames:,} frames per run; generated {time.strftime('%Y-%m-%d %H:%M')}. Episodes counted from the "
             "100th; 'not reached' seeds are left out of the means and counted in 'reached'.", "",
             "| arm | overrides | episodes to 80% | episodes to 95% | reached 95% | vs base (episodes to 95%) | "
             "final success | frames/s |", "|---|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for arm in arms:
        mine = [r for r in rows if r["arm"] == arm]
        e95 = _mean([r["episodes_to_95"] for r in mine])
        delta = f"{e95 - base_e95:+,.0f}" if e95 is not None and base_e95 is not None and arm != "base" else ""
        reached = sum(r["episodes_to_95"] is not None for r in mine)
        lines.append(f"| {arm} | {' '.join(ARMS.get(arm, ['(baseline)']))} | "
                     f"{mean_std([r['episodes_to_80'] for r in mine])} | {mean_std([r['episodes_to_95'] for r in mine])}"
                     f" | {reached}/{len(mine)} | {delta} | {mean_std([r['final_success'] for r in mine])} | "
                     f"{mean_std([r['fps'] for r in mine])} |")  # fmt: skip
    lines += ["", "Per seed (episodes to 95%): " + "; ".join(
        f"{a} " + "/".join("-" if r["episodes_to_95"] is None else f"{r['episodes_to_95']:,}"
                          for r in rows if r["arm"] == a) for a in arms), "", f"Command: `{command}`"]  # fmt: skip
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recipe", default=str(ROOT / "recipes" / "minigrid_multiroom_n2s4.yaml"))
    ap.add_argument("--env", default="MiniGrid-MultiRoom-N2-S4-v0")
    ap.add_argument("--frames", type=int, default=80_000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--arms", nargs="+", choices=[*ARMS, "ppo_mlp"], default=[*ARMS, "ppo_mlp"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "ablation_n2s4"))
    ap.add_argument("--report-only", action="store_true", help="tables from the finished runs; start nothing")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = []
    for seed in args.seeds:
        for arm in args.arms:
            job = {"method": arm, "seed": seed, "env": args.env, "frames": args.frames, "recipe": args.recipe,
                   "overrides": [f"env.id={args.env}", *ARMS.get(arm, [])], "out": str(out)}  # fmt: skip
            jobs.append((_run_ppo_mlp if arm == "ppo_mlp" else run_freamer, job))
    results = finished_results(jobs) if args.report_only else run_jobs(jobs, workers=args.workers)
    order = {a: i for i, a in enumerate([*ARMS, "ppo_mlp"])}
    results.sort(key=lambda r: (order[r["method"]], r["seed"]))
    command = " ".join(["python benchmarks/ablation_benchmark.py", *(argv if argv is not None else sys.argv[1:])])
    text = write_report(results, out, args.env, args.frames, command)
    print(text)
    return text


if __name__ == "__main__":
    main()
