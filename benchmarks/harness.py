"""Shared benchmark machinery: resumable jobs run two at a time, FreamerV1 runs through the library's Trainer, and
learning curves with min-max bands across seeds (``plot_bands``, ``first_reaching`` and ``mean_std`` live in
:mod:`freamer_rl.experiments.report`, which ``freamer-rl suite`` uses too).

A job is a dict with at least ``method``, ``seed`` and ``out``. Its result is stored as
``<out>/jobs/<method>_s<seed>.json`` when it finishes, and a rerun of the same benchmark command skips finished jobs
(``--fresh`` in the scripts deletes them). FreamerV1 jobs also resume mid-run from their run directory's last
checkpoint (``<out>/runs/<method>_s<seed>``), so a killed benchmark loses at most one checkpoint interval.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import shutil
import time
from pathlib import Path
from typing import Callable

# one copy, in the library (freamer_rl.experiments.report); re-exported for the benchmark scripts
from freamer_rl.experiments.report import first_reaching, mean_std, plot_bands  # noqa: F401

ROW_KEYS = ("frames", "episodes", "success_rate", "return_mean")


def job_path(job: dict) -> Path:
    return Path(job["out"]) / "jobs" / f"{job['method']}_s{job['seed']}.json"


def run_freamer(job: dict) -> dict:
    """Train FreamerV1 from ``job["recipe"]`` + overrides (seed, frames) with the library's Trainer; resumable."""
    import torch

    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING)
    from freamer_rl.trainers.registry import load_config
    from freamer_rl.trainers.minigrid_ppo import Trainer

    overrides = [
        f"run.seed={job['seed']}",
        f"run.total_frames={job['frames']}",
        "logging.progress_bar=false",
        f"logging.checkpoint_every_frames={job.get('checkpoint_every', 20_000)}",
        *job.get("overrides", []),
    ]
    cfg = load_config(job["recipe"], overrides)
    trainer = Trainer(cfg, Path(job["out"]) / "runs" / f"{job['method']}_s{job['seed']}", resume=True)
    summary = trainer.train()
    summary["method"] = job["method"]
    summary["rows"] = [{k: r[k] for k in ROW_KEYS} for r in trainer.rows]
    return summary


def _run_cached(args: tuple[Callable[[dict], dict], dict]) -> dict:
    fn, job = args
    path = job_path(job)
    if path.is_file():
        return json.loads(path.read_text())
    result = fn(job)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, default=str))
    tmp.replace(path)
    return result


def finished_results(jobs: list[tuple[Callable[[dict], dict], dict]]) -> list[dict]:
    """The results of the jobs that have finished (their result files), without running anything."""
    return [json.loads(job_path(job).read_text()) for _, job in jobs if job_path(job).is_file()]


def run_jobs(jobs: list[tuple[Callable[[dict], dict], dict]], workers: int = 2, fresh: bool = False) -> list[dict]:
    """Run ``(fn, job)`` pairs, ``workers`` at a time in spawned processes (one thread each); finished jobs are
    read back from their result files unless ``fresh``."""
    if fresh:
        for _, job in jobs:
            job_path(job).unlink(missing_ok=True)
            shutil.rmtree(Path(job["out"]) / "runs" / f"{job['method']}_s{job['seed']}", ignore_errors=True)
    t0 = time.perf_counter()
    results = []

    def report(r: dict) -> None:
        results.append(r)
        ret = r.get("final_return_mean", float("nan"))
        logging.getLogger("benchmark").warning(
            "[%6.0fs] %s seed %s: return %.2f, success %.3f, %.0f frames/s", time.perf_counter() - t0,
            r["method"], r["seed"], ret if ret is not None else float("nan"),
            r.get("final_success_rate") or float("nan"), r.get("fps") or float("nan"),
        )

    if workers > 1:
        with mp.get_context("spawn").Pool(workers) as pool:
            for r in pool.imap_unordered(_run_cached, jobs):
                report(r)
    else:
        for j in jobs:
            report(_run_cached(j))
    return results
