"""A suite's evaluations (its ``evaluate`` section): which are due, and the queue that runs them in the suite's workers.

Each run's evaluations are queued as soon as the run is done (those of runs done before the suite started, once every
training is queued), behind the trainings the pool already holds: a worker that the last trainings leave idle
evaluates the finished runs instead of waiting for every run to end, and nothing is evaluated twice. An evaluation is
due (``new``, ``stale``: written for an older checkpoint, or ``failed``) only for a run that is done.
"""

from __future__ import annotations

import json
import logging
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from freamer_rl.experiments.report import RunRecord, run_status
from freamer_rl.experiments.robustness import (
    EvaluateConfig,
    checkpoint_frames,
    eval_job,
    eval_path,
    eval_state,
    evaluate_condition,
)
from freamer_rl.experiments.workers import collect_jobs, error_line, submit_jobs
from freamer_rl.run.checkpoint import atomic_write_text

logger = logging.getLogger(__name__)

__all__ = ["EvaluationQueue", "describe_evaluations"]

DUE = ("new", "stale", "failed")


def describe_evaluations(cfg: EvaluateConfig, runs: list[RunRecord]) -> list[dict[str, Any]]:
    """Per run x condition of ``cfg``: label, env, seed, condition, status (``done`` for the run's final
    checkpoint, ``stale``, ``failed``, ``new``, or ``waiting`` while the run is not done), error, path, run, config.
    A finished run whose checkpoints are gone is judged by its final frame count (``done.json``)."""
    rows = []
    for run in runs:
        run_state, run_frames = run_status(run.run_dir, run.target_frames, run.stages)
        done = run.error is None and run_state == "done"
        frames = checkpoint_frames(run.run_dir) if done else None
        if done and frames is None:
            # a finished run without its checkpoints (a committed results folder keeps none): its evaluations of
            # the final checkpoint stand; evaluating again could only fail and overwrite them
            frames = run_frames
        for c in cfg.conditions:
            path = eval_path(run.run_dir, c.label)
            status = eval_state(path, frames) if done else "waiting"
            error = (json.loads(path.read_text()) or {}).get("error") if status == "failed" else None
            rows.append(
                {
                    "label": run.label,
                    "env": run.env,
                    "seed": run.seed,
                    "condition": c.label,
                    "status": status,
                    "error": error,
                    "path": str(path),
                    "run": run,
                    "config": c,
                }
            )
    return rows


class EvaluationQueue:
    """The due evaluations of done runs, queued to a suite's worker pool.

    ``add(runs)`` queues those of ``runs`` not queued yet (behind whatever the pool already holds); ``finish(runs)``
    adds the rest and waits for every queued one with one overall progress. ``record_lost=False``: an evaluation
    lost because a worker died (the pool is broken) is not written as failed; ``finish`` says so and the suite
    evaluates again in fresh workers (whose queue records such a loss as a failure).
    """

    def __init__(self, pool: ProcessPoolExecutor, cfg: EvaluateConfig, name: str, *, record_lost: bool = False):
        self.pool, self.cfg, self.name, self.record_lost = pool, cfg, name, record_lost
        self.rows: list[dict[str, Any]] = []
        self.payloads: list[dict[str, Any]] = []
        self.futures: dict[Future, int] = {}
        self.broken = False  # a worker died: what was queued is lost
        self._level = logging.getLogger("freamer_rl").getEffectiveLevel()

    def add(self, runs: list[RunRecord]) -> None:
        """Queue the due evaluations of ``runs`` (a run not done yet has none)."""
        queued = {e["path"] for e in self.rows}
        rows = [e for e in describe_evaluations(self.cfg, runs) if e["status"] in DUE and e["path"] not in queued]
        if self.broken or not rows:
            return
        payloads = [eval_job(self.cfg, e["config"], e["run"].run_dir, e["run"].tag, self._level) for e in rows]
        try:
            futures = submit_jobs(self.pool, evaluate_condition, payloads, start=len(self.rows))
        except BrokenProcessPool:  # a training worker died; finish() reports it, fresh workers evaluate
            self.broken = True
            return
        self.rows += rows
        self.payloads += payloads
        self.futures.update(futures)

    def finish(self, runs: list[RunRecord]) -> tuple[list[str], list[str], bool]:
        """Queue what is still due of ``runs``, wait for every queued evaluation; returns the tags written, the
        tags failed (both in queue order, whatever order the workers finished in), and whether evaluations were lost
        to a broken pool (evaluate them again in fresh workers)."""
        self.add(runs)
        waiting = sum(e["status"] == "waiting" for e in describe_evaluations(self.cfg, runs))
        logger.info("suite %s: %d evaluations to run (%d wait for unfinished runs)", self.name, len(self.rows), waiting)
        done: list[tuple[int, str]] = []
        failed: list[tuple[int, str]] = []

        def on_result(index: int, future: Future) -> tuple[bool, str]:
            tag = self.payloads[index]["tag"]
            try:
                out = future.result()
            except BrokenProcessPool as err:
                if not self.record_lost:
                    self.broken = True
                    return False, f"{tag} lost (a worker died); evaluated again in fresh workers"
                out = self._record_failure(index, err)
            except Exception as err:  # noqa: BLE001 -- recorded like a failure; the suite goes on
                out = self._record_failure(index, err)
            (done if out["ok"] else failed).append((index, tag))
            return out["ok"], tag if out["ok"] else f"{tag} FAILED: {out['error']}"

        collect_jobs(self.futures, f"suite {self.name} evaluation", [None] * len(self.rows), "evaluations", on_result)
        return [tag for _, tag in sorted(done)], [tag for _, tag in sorted(failed)], self.broken

    def _record_failure(self, index: int, err: BaseException) -> dict[str, Any]:
        out = {"ok": False, "error": error_line(err)}
        path = Path(self.rows[index]["path"])
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps({"condition": self.rows[index]["condition"], "error": out["error"]}) + "\n")
        return out
