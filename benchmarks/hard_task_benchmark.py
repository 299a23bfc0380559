"""A hard MiniGrid task, three methods, three seeds: FreamerV1 (curriculum chain with its machinery), TorchRL's
PPO-MLP, and PPO-MLP with the same novelty bonus (``freamer_rl.machinery.exploration.NoveltyBonus``).

    python benchmarks/hard_task_benchmark.py --task doorkey8x8            # all methods, seeds 0 1 2
    python benchmarks/hard_task_benchmark.py --task n4s5 --methods ppo_mlp ppo_mlp_novelty
    python benchmarks/hard_task_benchmark.py --task doorkey8x8 --frames 4096 --seeds 0 --out /tmp/smoke   # smoke

Per method and seed: frames and episodes to 80% and 95% success (the windowed rate over the last 100 episodes,
counted from the 100th episode; a chain counts the frames and episodes of its earlier stages too), final success,
frames/s. Writes ``results.md``, ``results.csv`` and ``learning_curve.png`` (mean across seeds with a min-max band)
into ``--out`` (default ``benchmarks/results/hard_<task>/``). Resumable: finished runs are read back from
``<out>/jobs/``, chains resume from their last checkpoints; runs go two at a time, one thread each.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from harness import _run_cached, finished_results, first_reaching, mean_std, plot_bands  # noqa: E402

#: task -> env id, frame budget (the issue's targets), the FreamerV1 chain, the success target.
TASKS = {
    "n4s5": {"env": "MiniGrid-MultiRoom-N4-S5-v0", "frames": 1_000_000, "target": 0.80,
             "chain": "recipes/minigrid_multiroom_curriculum.chain.yaml"},
    "doorkey8x8": {"env": "MiniGrid-DoorKey-8x8-v0", "frames": 500_000, "target": 0.95,
                   "chain": "recipes/minigrid_doorkey_curriculum.chain.yaml"},
    "n6": {"env": "MiniGrid-MultiRoom-N6-v0", "frames": 1_500_000, "target": 0.80,
           "chain": "recipes/minigrid_multiroom_n6_curriculum.chain.yaml"},
}  # fmt: skip
METHODS = ("freamer", "ppo_mlp", "ppo_mlp_novelty")
WINDOW = 100
NOVELTY_WEIGHT = 0.1  # the weight of recipes/minigrid_*_novelty (shaping.novelty.weight)


def run_ppo_mlp(job: dict) -> dict:
    """TorchRL's PPO-MLP baseline (``benchmarks/ppo_mlp_baseline.py``), with the novelty bonus when the job says so."""
    import torch

    torch.set_num_threads(1)
    from ppo_mlp_baseline import train_ppo_mlp

    bonus = {"novelty_weight": job["novelty"]} if job.get("novelty") else {}
    result = train_ppo_mlp(job["env"], job["seed"], job["frames"], **bonus)
    result["method"] = job["method"]
    return result


def run_freamer_chain(job: dict) -> dict:
    """One seed of the task's chain (resumable); rows of its last stage with the earlier stages' frames and episodes
    added, so every row counts from the start of the chain."""
    import torch

    from freamer_rl.experiments.chain import run_chain
    from freamer_rl.run.metrics import quiet_library_logs

    torch.set_num_threads(1)
    stage_overrides = ["run.threads=1", "logging.progress_bar=false", *job.get("stage_overrides", [])]
    with quiet_library_logs():
        stages = run_chain(job["chain"], [f"seed={job['seed']}", f"output_dir={job['out']}/runs"],
                           stage_overrides=stage_overrides)  # fmt: skip
    frames_before = sum(int(s["frames"]) for s in stages[:-1])
    episodes_before = sum(int(s["episodes"]) for s in stages[:-1])
    with open(Path(stages[-1]["run_dir"]) / "progress.csv", newline="") as f:
        rows = [{"frames": frames_before + int(r["frames"]), "episodes": episodes_before + int(r["episodes"]),
                 "stage_episodes": int(r["episodes"]), "success_rate": float(r["success_rate"]),
                 "fps": float(r["fps"])} for r in csv.DictReader(f)]  # fmt: skip
    last = stages[-1]
    return {"method": job["method"], "seed": job["seed"], "frames": frames_before + int(last["frames"]),
            "episodes": episodes_before + int(last["episodes"]), "final_success_rate": last["final_success_rate"],
            "fps": last.get("fps") or (sum(r["fps"] for r in rows) / len(rows) if rows else None), "rows": rows,
            "stages": " / ".join(f"{s['stage']} {int(s['frames']):,}" for s in stages)}  # fmt: skip


def _counted_rows(result: dict) -> list[dict]:
    """Rows from the (last stage's) 100th episode on: before that the windowed rate covers too few episodes."""
    key = "stage_episodes" if result["method"] == "freamer" else "episodes"
    return [r for r in result["rows"] if r[key] >= WINDOW]


def summarise(result: dict) -> dict:
    rows = _counted_rows(result)
    f80, e80 = first_reaching(rows, "success_rate", 0.80)
    f95, e95 = first_reaching(rows, "success_rate", 0.95)
    return {"method": result["method"], "seed": result["seed"], "frames_to_80": f80, "episodes_to_80": e80,
            "frames_to_95": f95, "episodes_to_95": e95, "final_success": result["final_success_rate"],
            "frames": result["frames"], "episodes": result["episodes"], "fps": result.get("fps")}  # fmt: skip


def make_jobs(task: str, methods: list[str], seeds: list[int], frames: int | None, out: Path) -> list:
    spec = TASKS[task]
    budget = frames or spec["frames"]
    jobs = []
    for method in methods:
        for seed in seeds:
            job = {"method": method, "seed": seed, "env": spec["env"], "frames": budget, "out": str(out)}
            if method == "freamer":
                job["chain"] = str(ROOT / spec["chain"])
                if frames:  # a smoke run: every stage gets the small budget
                    job["stage_overrides"] = [f"run.total_frames={frames}"]
                jobs.append((run_freamer_chain, job))
            else:
                job["novelty"] = NOVELTY_WEIGHT if method == "ppo_mlp_novelty" else 0.0
                jobs.append((run_ppo_mlp, job))
    return jobs


def _fmt(v, missing: str = "not reached") -> str:
    if v is None:
        return missing
    return f"{v:,.0f}" if isinstance(v, (int, float)) else str(v)


def write_report(task: str, results: list[dict], out: Path, command: str) -> str:
    spec = TASKS[task]
    rows = [summarise(r) for r in sorted(results, key=lambda r: (METHODS.index(r["method"]), r["seed"]))]
    fields = list(rows[0])
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    plot_bands([{"method": r["method"], "rows": _counted_rows(r)} for r in results], out / "learning_curve.png",
               "success_rate", f"{spec['env']}", target=spec["target"], ylabel="success (last 100 episodes)")
    lines = [f"# {spec['env']}: FreamerV1 vs PPO-MLP vs PPO-MLP + novelty", "",
             f"Generated {time.strftime('%Y-%m-%d %H:%M')}. At most {_fmt(max(r['frames'] for r in results))} "
             "frames per run; success over the last 100 episodes, "
             "counted from the 100th episode; FreamerV1's frames and episodes include its curriculum's earlier "
             "stages.", "",
             "| method | seed | frames to 80% | episodes to 80% | frames to 95% | episodes to 95% | final success | "
             "frames | frames/s |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        lines.append(f"| {r['method']} | {r['seed']} | {_fmt(r['frames_to_80'])} | {_fmt(r['episodes_to_80'])} | "
                     f"{_fmt(r['frames_to_95'])} | {_fmt(r['episodes_to_95'])} | {r['final_success']:.3f} | "
                     f"{_fmt(r['frames'])} | {_fmt(r['fps'], 'n/a')} |")
    lines += ["", f"Methods: freamer = FreamerV1 through `{spec['chain']}` (each stage from the previous stage's weights); "
              "ppo_mlp = `benchmarks/ppo_mlp_baseline.py` (FlatObs, MLP 256x2, TorchRL ClipPPOLoss/GAE); "
              f"ppo_mlp_novelty = the same with `NoveltyBonus` (weight {NOVELTY_WEIGHT}) on the flat observation.", ""]
    for m in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == m]
        lines.append(f"- {m}: frames to 80% {mean_std([r['frames_to_80'] for r in mine])}, to 95% "
                     f"{mean_std([r['frames_to_95'] for r in mine])}; final success "
                     f"{mean_std([r['final_success'] for r in mine])}")
    lines += ["", f"Command: `{command}`"]
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", choices=sorted(TASKS), required=True)
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=None, help="override every budget (smoke runs)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=None)
    ap.add_argument("--report-only", action="store_true", help="tables from the finished runs; start nothing")
    args = ap.parse_args(argv)
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"hard_{args.task}"
    out.mkdir(parents=True, exist_ok=True)
    jobs = make_jobs(args.task, args.methods, args.seeds, args.frames, out)
    if args.report_only:
        results = finished_results(jobs)
    else:
        with ProcessPoolExecutor(max_workers=args.workers) as pool:
            results = list(pool.map(_run_cached, jobs))
    command = " ".join(["python benchmarks/hard_task_benchmark.py", *(argv if argv is not None else sys.argv[1:])])
    text = write_report(args.task, results, out, command)
    print(text)
    return text


if __name__ == "__main__":
    main()
