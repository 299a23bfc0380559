"""A recipe chain (curriculum) over seeds: frames counted across the whole chain to 80% / 95% success on its last stage.

    python benchmarks/curriculum_benchmark.py recipes/minigrid_multiroom_curriculum.chain.yaml --seeds 0 1 2

A script, not a suite (``recipes/suites/``): a suite entry is one recipe, and what this measures is a chain of them
with the frames of the earlier stages counted (the FreamerV1 rows of the hard-task results files as well).

Each seed is one ``freamer-rl chain`` run (``freamer_rl.experiments.chain.run_chain``) in its own process, two at a time, one
thread each; rerunning the command resumes unfinished chains and reads finished ones back. Success rates are the
trainer's windowed rates (last 100 episodes). Writes ``results.md``, ``results.csv`` and ``learning_curve.png`` (the
last stage's success rate against the frames of the whole chain, mean across seeds with a min-max band) into ``--out``
(default ``benchmarks/results/<chain name>/``).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from freamer_rl.experiments.report import first_reaching, mean_std, plot_bands

ROOT = Path(__file__).resolve().parents[1]


def _run_seed(job: dict) -> list[dict]:
    import torch

    from freamer_rl.experiments.chain import run_chain
    from freamer_rl.run.metrics import quiet_library_logs

    torch.set_num_threads(1)
    with quiet_library_logs():
        return run_chain(
            job["chain"],
            [f"seed={job['seed']}", f"output_dir={job['out']}"],
            stage_overrides=["run.threads=1", "logging.progress_bar=false"],
        )


def _last_stage_curve(stages: list[dict], window: int = 100) -> list[dict]:
    """The last stage's progress rows with ``frames`` shifted by the frames of the stages before it, from its
    ``window``-th episode on (before that the windowed rate covers too few episodes to count)."""
    before = sum(int(s["frames"]) for s in stages[:-1])
    with open(Path(stages[-1]["run_dir"]) / "progress.csv", newline="") as f:
        return [
            {
                "frames": before + int(r["frames"]),
                "episodes": int(r["episodes"]),
                "success_rate": float(r["success_rate"]),
            }
            for r in csv.DictReader(f)
            if int(r["episodes"]) >= window
        ]


def summarise(seed: int, stages: list[dict]) -> dict:
    curve = _last_stage_curve(stages)
    f80, _ = first_reaching(curve, "success_rate", 0.80)
    f95, _ = first_reaching(curve, "success_rate", 0.95)
    return {
        "seed": seed,
        "stages": " / ".join(f"{s['stage']} {int(s['frames']):,}" for s in stages[:-1]),
        "chain_frames": stages[-1]["chain_frames"],
        "frames_to_80": f80,
        "frames_to_95": f95,
        "final_success": stages[-1]["final_success_rate"],
        "curve": curve,
    }


def write_report(name: str, env: str, rows: list[dict], out: Path, command: str) -> str:
    out.mkdir(parents=True, exist_ok=True)
    fields = ["seed", "stages", "chain_frames", "frames_to_80", "frames_to_95", "final_success"]
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows({k: r[k] for k in fields} for r in rows)
    plot_bands(
        [{"method": f"FreamerV1 chain {name}", "rows": r["curve"]} for r in rows],
        out / "learning_curve.png",
        "success_rate",
        f"{env}: last stage of {name}",
        target=0.8,
        ylabel="success (last 100 episodes)",
    )

    def fmt(v):
        return "not reached" if v is None else f"{v:,}"

    lines = [
        f"# Curriculum {name}: {env}",
        "",
        f"Generated {time.strftime('%Y-%m-%d %H:%M')}; frames are counted "
        "across the whole chain (earlier stages included); success over the last 100 episodes.",
        "",
        "| seed | earlier stages (frames) | frames to 80% | frames to 95% | final success | chain frames |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {r['stages']} | {fmt(r['frames_to_80'])} | {fmt(r['frames_to_95'])} | "
            f"{r['final_success']:.3f} | {r['chain_frames']:,} |"
        )
    lines += [
        "",
        f"Frames to 80%: {mean_std([r['frames_to_80'] for r in rows])}; to 95%: "
        f"{mean_std([r['frames_to_95'] for r in rows])}.",
        "",
        f"Command: `{command}`",
    ]
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("chain")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from freamer_rl.experiments.chain import load_chain

    chain = load_chain(args.chain)
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / chain.name
    jobs = [{"chain": str(Path(args.chain).resolve()), "seed": s, "out": str(out / "runs")} for s in args.seeds]
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        results = list(pool.map(_run_seed, jobs))
    rows = [summarise(job["seed"], stages) for job, stages in zip(jobs, results)]
    env = json.loads((Path(results[0][-1]["run_dir"]) / "summary.json").read_text())["env"]
    command = " ".join(["python benchmarks/curriculum_benchmark.py", *(argv if argv is not None else sys.argv[1:])])
    text = write_report(chain.name, env, rows, out, command)
    print(text)
    return text


if __name__ == "__main__":
    main()
