"""When a suite evaluates (freamer_rl.experiments.suite_evals): each run as soon as it is done, lost jobs not failed."""

import json
import multiprocessing as mp
import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest

from freamer_rl.experiments.report import RunRecord
from freamer_rl.experiments.suite import load_suite, run_suite
from freamer_rl.experiments.suite_evals import EvaluationQueue, describe_evaluations

ROOT = Path(__file__).resolve().parents[2]
ENV = "MiniGrid-Empty-5x5-v0"
EVALUATE = "evaluate:\n  episodes: 2\n  num_envs: 2\n  conditions: [{label: clean}, {label: g, corrupt: [{key: grid, kind: salt, level: 0.5}]}]\n"


def _suite(tmp_path: Path, entries: str) -> Path:
    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    path = tmp_path / "early.yaml"
    path.write_text(f"name: early\nseeds: [0]\ntotal_frames: 128\noverrides: [ppo.epochs=1]\n{entries}{EVALUATE}")
    return path


def test_a_run_is_evaluated_while_a_longer_run_still_trains(tmp_path):
    # two workers: the long run starts first; the short one finishes, and its evaluations take the free worker
    # instead of waiting for the long run (before, every evaluation started after the last training)
    path = _suite(
        tmp_path,
        "entries: [{label: long, recipe: tiny.yaml, overrides: [run.total_frames=1536]}, {label: short, recipe: tiny.yaml}]\n",
    )
    out = run_suite(path, jobs=2, output=tmp_path / "out")
    tags = [f"{label}/{ENV}/seed0 eval {c}" for label in ("long", "short") for c in ("clean", "g")]
    assert sorted(out["trained"]) == [f"long/{ENV}/seed0", f"short/{ENV}/seed0"]
    assert sorted(out["evaluated"]) == tags and out["eval_failed"] == []
    runs = tmp_path / "out" / "runs"
    long_done = (runs / "long" / ENV / "seed0" / "done.json").stat().st_mtime
    short_evals = [(runs / "short" / ENV / "seed0" / "eval" / f"{c}.json").stat().st_mtime for c in ("clean", "g")]
    assert max(short_evals) < long_done
    for c in ("clean", "g"):  # the long run's own evaluations are of its final checkpoint
        data = json.loads((runs / "long" / ENV / "seed0" / "eval" / f"{c}.json").read_text())
        assert data["checkpoint_frames"] == 1536


def _done_run(root: Path, label: str) -> RunRecord:
    run_dir = root / "runs" / label / ENV / "seed0"
    run_dir.mkdir(parents=True)
    (run_dir / "done.json").write_text(json.dumps({"total_frames": 128, "frames": 128}))
    (run_dir / "summary.json").write_text(json.dumps({"frames": 128}))
    return RunRecord(label=label, env=ENV, env_dir=ENV, seed=0, run_dir=run_dir, target_frames=128)


def test_evaluations_lost_to_a_dead_worker(tmp_path):
    # a worker that dies breaks the pool: the first queue reports its evaluations lost (the suite evaluates them
    # again in fresh workers) without writing them as failed; the fresh workers' queue records such a loss
    cfg = load_suite(_suite(tmp_path, "entries: [{label: a, recipe: tiny.yaml}]\n")).evaluate
    runs = [_done_run(tmp_path, "a")]
    assert [e["status"] for e in describe_evaluations(cfg, runs)] == ["new", "new"]
    with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
        with pytest.raises(BrokenProcessPool):
            pool.submit(os._exit, 3).result()
        queue = EvaluationQueue(pool, cfg, "early")
        queue.add(runs)  # the broken pool refuses the jobs
        assert queue.finish(runs) == ([], [], True)
    assert [e["status"] for e in describe_evaluations(cfg, runs)] == ["new", "new"]  # nothing written as failed


@pytest.mark.parametrize("record_lost", [False, True])
def test_an_evaluation_whose_worker_dies(tmp_path, record_lost):
    # the worker is killed while it starts: the first queue reports the loss and writes nothing; the fresh
    # workers' queue (record_lost) writes the failures, which a rerun retries
    cfg = load_suite(_suite(tmp_path, "entries: [{label: a, recipe: tiny.yaml}]\n")).evaluate
    runs = [_done_run(tmp_path, "a")]
    with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
        queue = EvaluationQueue(pool, cfg, "early", record_lost=record_lost)
        queue.add(runs)
        for process in list(pool._processes.values()):  # started by the first submit, still importing
            process.kill()
        done, failed, lost = queue.finish(runs)
    assert done == [] and lost is not record_lost
    assert failed == ([f"a/{ENV}/seed0 eval clean", f"a/{ENV}/seed0 eval g"] if record_lost else [])
    rows = describe_evaluations(cfg, runs)
    assert [e["status"] for e in rows] == (["failed", "failed"] if record_lost else ["new", "new"])
    if record_lost:
        assert "BrokenProcessPool" in rows[0]["error"]


def test_a_committed_run_without_checkpoints_keeps_its_evaluations(tmp_path):
    # a results folder in git holds each run's done.json and eval/*.json but no checkpoints: a suite rerun into it
    # (say, with a new arm) must keep those evaluations, not re-evaluate, fail ("no checkpoint") and overwrite them
    suite = load_suite(_suite(tmp_path, "entries: [{label: a, recipe: tiny.yaml}]\n"))
    runs = [_done_run(tmp_path, "a")]
    evals = runs[0].run_dir / "eval"
    evals.mkdir()
    kept = {c: {"condition": c, "return_mean": 0.5, "checkpoint_frames": 128} for c in ("clean", "g")}
    for c, data in kept.items():
        (evals / f"{c}.json").write_text(json.dumps(data))
    assert [e["status"] for e in describe_evaluations(suite.evaluate, runs)] == ["done", "done"]
    # one of another checkpoint is stale, as with checkpoints present
    (evals / "g.json").write_text(json.dumps({**kept["g"], "checkpoint_frames": 64}))
    assert [e["status"] for e in describe_evaluations(suite.evaluate, runs)] == ["done", "stale"]
    (evals / "g.json").write_text(json.dumps(kept["g"]))
    out = run_suite(tmp_path / "early.yaml", jobs=1, output=tmp_path)
    assert out["trained"] == [] and out["evaluated"] == [] and out["eval_failed"] == []
    assert {c: json.loads((evals / f"{c}.json").read_text()) for c in kept} == kept
