"""Benchmark suites: one command over recipes x envs x seeds, resumable, with tables and plots in one folder.

A suite file is YAML::

    name: n2s4_baselines
    output: results/n2s4_baselines        # default results/<name>, relative to the current directory
    seeds: [0, 1, 2]
    envs: [MiniGrid-MultiRoom-N2-S4-v0]    # optional: env.id of every entry without its own envs
    total_frames: 80000                    # optional: run.total_frames of every run
    overrides: [logging.checkpoint_every_frames=10000]   # every run
    entries:
      - {label: freamer, recipe: ../minigrid_multiroom_n2s4.yaml}
      - {label: freamer_lr3e-4, recipe: ../minigrid_multiroom_n2s4.yaml, overrides: [optim.lr=3e-4]}
      - {label: ppo_mlp, recipe: ../baselines/ppo_mlp_n2s4.yaml, seeds: [0, 1, 2, 3, 4]}   # its own seeds

Recipes are paths relative to the suite file and may name any trainer of :data:`freamer_rl.trainers.registry.TRAINERS`.
Each run trains in ``<output>/runs/<label>/<env folder>/seed<k>`` (env ids such as ``ALE/Pong-v5`` become one folder
name, ``ALE_Pong-v5``) with the overrides: env.id, run.total_frames, the suite's, the entry's, ``run.seed=<k>`` and
the schema's ``progress_bar=false``. ``freamer-rl suite`` runs them ``--jobs`` at a time in spawned worker processes
(one torch thread each). Rerunning the same command resumes: a run whose ``done.json`` covers the budget is skipped,
an interrupted one resumes from its latest checkpoint (the trainer's own resume and run-directory lock). A failing
run is recorded (``failed.txt``, a ``failed`` row) and the others go on. The report is
:func:`freamer_rl.experiments.report.write_report`.

The results folder is created and checked writable before anything trains and stays locked for the whole suite (a
second suite on the same folder is refused, naming the holder's pid). Workers die with the suite process, ``kill
-9`` included (they checkpoint on the SIGTERM they get), so a rerun finds no run still locked. One overall progress
bar with an ETA (frames-weighted when every run's budget is known; a log line per finished run when not on a
terminal) replaces the per-run lines.

An entry whose recipe ends in ``.chain.yaml`` is a chain (:mod:`freamer_rl.experiments.chain`, a curriculum): each
seed runs the whole chain (``run_chain(..., seed=<k>)``) in ``<output>/runs/<label>/<env folder of its last
stage>/seed<k>`` (stage ``s`` in ``.../seed<k>/<s>``), resumably like a recipe run (``done.json`` once the last stage
finished). The suite's and the entry's overrides are the chain-level overrides (after each stage's own, so
``run.total_frames=2048`` shrinks every stage); the suite's ``envs`` and ``total_frames`` do not apply (the stages
carry their env ids and frame caps; the run's budget is the sum of the caps). ``envs`` on a chain entry, a ``seed=``
or ``output_dir=`` override, and ``evaluate`` conditions in a suite with a chain entry are refused. The report
counts a chain run's frames, episodes and frames / episodes to 95% across its stages and shows its last stage's
curve, shifted by the earlier stages' frames and episodes.

An optional ``evaluate:`` section (:class:`~freamer_rl.experiments.robustness.EvaluateConfig`: episodes, seed,
metric, conditions of evaluation-time corruption, ``compare`` pairs of entry labels) has every finished run
evaluated under every condition in the same workers, each run as soon as it is done
(:mod:`~freamer_rl.experiments.suite_evals`; ``<run_dir>/eval/<condition>.json``; one already written for the run's
final checkpoint is skipped, a failed one is retried), and adds the robustness report
(:func:`~freamer_rl.experiments.robustness.write_robustness`). ``--report-only`` rebuilds everything from the folders.
"""

from __future__ import annotations

import json
import logging
import re
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from freamer_rl.config.checks import run_name_problem
from freamer_rl.config.loader import VALIDATORS, config_from_dict, read_recipe
from freamer_rl.errors import ConfigError, FreamerError
from freamer_rl.experiments.chain import is_chain, plan_chain, run_chain, split_overrides
from freamer_rl.experiments.folders import prepare_output_folder
from freamer_rl.experiments.report import DONE_NAME, FAILED_NAME, RunRecord, failed_line, run_status, write_report
from freamer_rl.experiments.robustness import (
    EvaluateConfig,
    check_evaluate,
    write_robustness,
)
from freamer_rl.experiments.robustness_compare import check_pairs
from freamer_rl.experiments.suite_evals import EvaluationQueue, describe_evaluations
from freamer_rl.experiments.workers import collect_jobs, error_line, submit_jobs, worker_pool
from freamer_rl.run.checkpoint import atomic_write_text
from freamer_rl.run.rundir import RunDirLock
from freamer_rl.trainers.registry import get_trainer, load_recipe

logger = logging.getLogger(__name__)

__all__ = [
    "SuiteConfig",
    "SuiteEntry",
    "SuiteRun",
    "describe_evaluations",
    "dry_run_listing",
    "env_folder",
    "load_suite",
    "plan_suite",
    "run_suite",
]


@dataclass
class SuiteEntry:
    label: str
    recipe: str  # relative to the suite file's folder
    overrides: list[str] = field(default_factory=list)
    envs: list[str] | None = None  # None: the suite's envs (or, without those, the recipe's env)
    # None: the suite's seeds; e.g. more seeds for the arms a comparison turns on, without rerunning every arm
    seeds: list[int] | None = None


@dataclass
class SuiteConfig:
    name: str
    entries: list[SuiteEntry]
    output: str | None = None  # default results/<name>
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    envs: list[str] = field(default_factory=list)
    overrides: list[str] = field(default_factory=list)
    total_frames: int | None = None
    # pairs of entry labels [A, B]: P(A reaches 95% sooner) and P(A ends higher) in summary.md
    # (freamer_rl.experiments.learning_compare)
    compare: list[list[str]] = field(default_factory=list)
    # robustness evaluation (freamer_rl.experiments.robustness); no conditions: none. Not Optional: the loader's
    # union coercion would hide the nested field an error names
    evaluate: EvaluateConfig = field(default_factory=EvaluateConfig)


def env_folder(env_id: str) -> str:
    """One safe folder name for an env id: every run of characters other than letters, digits, ``.``, ``_``, ``-``
    becomes ``_`` (``ALE/Pong-v5`` -> ``ALE_Pong-v5``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", env_id)


def _check_envs(envs: list[str], where: str) -> None:
    folders: dict[str, str] = {}
    for i, env in enumerate(envs):
        folder = env_folder(env)
        if problem := run_name_problem(folder):
            raise ConfigError(f"{where}[{i}]: env id {env!r} gives no safe folder name ({problem})")
        if folder in folders:
            raise ConfigError(f"{where}[{i}]: {env!r} and {folders[folder]!r} share the folder name {folder!r}")
        folders[folder] = env


def _validate_suite(cfg: SuiteConfig) -> None:
    if problem := run_name_problem(cfg.name):
        raise ConfigError(f"name: {problem}")
    _check_seeds(cfg.seeds, "seeds")
    if cfg.total_frames is not None and cfg.total_frames <= 0:
        raise ConfigError(f"total_frames: expected a positive number of frames, got {cfg.total_frames}")
    if cfg.output is not None and not cfg.output.strip():
        raise ConfigError("output: expected a folder, got an empty string")
    _check_envs(cfg.envs, "envs")
    if not cfg.entries:
        raise ConfigError("entries: a suite needs at least one entry")
    seen: set[str] = set()
    for i, entry in enumerate(cfg.entries):
        if problem := run_name_problem(entry.label):
            raise ConfigError(f"entries[{i}].label: {problem}")
        if entry.label in seen:
            raise ConfigError(f"entries[{i}].label: {entry.label!r} is used twice")
        seen.add(entry.label)
        if entry.seeds is not None:
            _check_seeds(entry.seeds, f"entries[{i}].seeds")
        if is_chain(entry.recipe):
            _check_chain_entry(cfg, i, entry)
        elif entry.envs is not None:
            if not entry.envs:
                raise ConfigError(f"entries[{i}].envs: an empty list (leave it out to use the suite's envs)")
            _check_envs(entry.envs, f"entries[{i}].envs")
    check_pairs(cfg.compare, [e.label for e in cfg.entries], "compare")
    if cfg.evaluate != EvaluateConfig():
        check_evaluate(cfg.evaluate, [e.label for e in cfg.entries])


def _check_seeds(seeds: list[int], where: str) -> None:
    if not seeds:
        raise ConfigError(f"{where}: expected at least one seed (an empty list trains nothing)")
    for i, seed in enumerate(seeds):
        if seed < 0 or seeds.index(seed) != i:
            raise ConfigError(f"{where}[{i}]: expected distinct seeds >= 0, got {seed}")


def _check_chain_entry(cfg: SuiteConfig, i: int, entry: SuiteEntry) -> None:
    if entry.envs is not None:
        raise ConfigError(
            f"entries[{i}].envs: {entry.recipe!r} is a chain, whose stages name their own env ids; leave envs out"
        )
    for where, items in ((f"entries[{i}].overrides", entry.overrides), ("overrides", cfg.overrides)):
        for item in split_overrides(items)[0]:
            if item.split("=", 1)[0].strip() in ("seed", "output_dir"):
                raise ConfigError(f"{where}: {item!r}: a chain entry's seed and folder are the suite's")
    if cfg.evaluate.conditions:
        raise ConfigError(
            f"entries[{i}].recipe: {entry.recipe!r} is a chain, which the evaluate section cannot evaluate; "
            "drop the entry or evaluate its last stage's recipe"
        )


VALIDATORS[SuiteConfig] = _validate_suite


def load_suite(path: str | Path) -> SuiteConfig:
    """Read and validate a suite file; ConfigError naming the file and the field otherwise."""
    path = Path(path)
    try:
        cfg = config_from_dict(read_recipe(path), SuiteConfig)
        for i, entry in enumerate(cfg.entries):
            recipe = path.parent / entry.recipe
            if not recipe.is_file():
                raise ConfigError(f"entries[{i}].recipe: no such recipe file: {recipe}")
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}" if str(path) not in str(err) else str(err)) from None
    return cfg


@dataclass
class SuiteRun(RunRecord):
    """One run of the plan: its report identity plus what the worker trains."""

    recipe: Path = Path()
    overrides: list[str] = field(default_factory=list)


def _quiet_override(cfg: Any) -> list[str]:
    """``<section>.progress_bar=false`` for the schema's section that has it (logging, or run), else nothing."""
    for section in ("logging", "run"):
        if hasattr(getattr(cfg, section, None), "progress_bar"):
            return [f"{section}.progress_bar=false"]
    return []


def _plan_run(suite: SuiteConfig, entry: SuiteEntry, recipe: Path, env: str | None, seed: int, root: Path) -> SuiteRun:
    given = [f"env.id={env}"] if env else []
    given += [f"run.total_frames={suite.total_frames}"] if suite.total_frames else []
    given += [*suite.overrides, *entry.overrides, f"run.seed={seed}"]
    error, cfg = None, None
    try:
        _, cfg = load_recipe(recipe, given)
    except FreamerError as err:
        error = f"{recipe}: {err}" if str(recipe) not in str(err) else str(err)
    if env is None:  # the recipe's own env (from the loaded config, else the raw recipe)
        env = getattr(getattr(cfg, "env", None), "id", None)
        if env is None:
            try:
                raw_env = read_recipe(recipe, given).get("env")
            except FreamerError:
                raw_env = None
            env = raw_env.get("id") if isinstance(raw_env, dict) else None
        env = env if isinstance(env, str) and not run_name_problem(env_folder(env)) else "default"
    run_dir = root / "runs" / entry.label / env_folder(env) / f"seed{seed}"
    target = getattr(getattr(cfg, "run", None), "total_frames", None)
    return SuiteRun(
        label=entry.label,
        env=env,
        env_dir=env_folder(env),
        seed=seed,
        run_dir=run_dir,
        target_frames=target,
        error=error,
        recipe=recipe,
        overrides=given + _quiet_override(cfg),
    )


def _plan_chain_run(suite: SuiteConfig, entry: SuiteEntry, chain: Path, seed: int, root: Path) -> SuiteRun:
    """A chain entry's run: the suite's and entry's overrides go to every stage; ``seed=<k>`` edits the chain."""
    given = [*suite.overrides, *entry.overrides, f"seed={seed}"]
    error, plan = None, None
    try:
        plan = plan_chain(chain, given)
    except FreamerError as err:
        error = f"{chain}: {err}" if str(chain) not in str(err) else str(err)
    env = plan.env if plan is not None and plan.env else "default"
    env = env if not run_name_problem(env_folder(env)) else "default"
    return SuiteRun(
        label=entry.label,
        env=env,
        env_dir=env_folder(env),
        seed=seed,
        run_dir=root / "runs" / entry.label / env_folder(env) / f"seed{seed}",
        target_frames=plan.total_frames if plan is not None else None,
        error=error,
        stages=plan.stages if plan is not None else [],
        recipe=chain,
        overrides=given + (_quiet_override(plan.last_config) if plan is not None else []),
    )


def plan_suite(path: str | Path, output: str | Path | None = None) -> tuple[SuiteConfig, Path, list[SuiteRun]]:
    """The suite, its results folder and every run (entry x env x seed, in that order); a run whose config does not
    load carries the error (it fails without training)."""
    path = Path(path)
    suite = load_suite(path)
    root = Path(output if output is not None else suite.output or Path("results") / suite.name)
    runs = []
    for entry in suite.entries:
        recipe = path.parent / entry.recipe
        seeds = entry.seeds if entry.seeds is not None else suite.seeds
        if is_chain(recipe):
            runs += [_plan_chain_run(suite, entry, recipe, seed, root) for seed in seeds]
            continue
        envs: list[str | None] = list(entry.envs if entry.envs is not None else suite.envs) or [None]
        runs += [_plan_run(suite, entry, recipe, env, seed, root) for env in envs for seed in seeds]
    return suite, root, runs


def describe(runs: list[SuiteRun]) -> list[dict[str, Any]]:
    """Per run: label, env, seed, status (done / partial / new / failed) and frames so far (for ``--dry-run``)."""
    rows = []
    for run in runs:
        status, frames = ("failed", 0) if run.error else run_status(run.run_dir, run.target_frames, run.stages)
        error = run.error or (failed_line(run.run_dir) if status == "failed" else None)
        rows.append(
            {
                "label": run.label,
                "env": run.env,
                "seed": run.seed,
                "status": status,
                "frames": frames,
                "target_frames": run.target_frames,
                "run_dir": str(run.run_dir),
                "error": error,
            }
        )
    return rows


# -- jobs run in the workers (freamer_rl.experiments.workers) ------------------------------------------------------
def _train_run(job: dict[str, Any]) -> dict[str, Any]:
    """Worker: train one run through the trainer registry, or a chain entry's run through ``run_chain`` (resuming),
    then write ``done.json`` or ``failed.txt``."""
    logging.basicConfig(
        force=True, level=job["log_level"], format=f"%(asctime)s %(levelname)s [{job['tag']}] %(name)s: %(message)s"
    )
    run_dir = Path(job["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / FAILED_NAME).unlink(missing_ok=True)
    t0 = time.perf_counter()
    try:
        if is_chain(job["recipe"]):  # the chain's frames in all, the last stage's success
            stages = run_chain(job["recipe"], job["overrides"], root=run_dir, progress_bar=False)
            summary = {"frames": stages[-1]["chain_frames"], "final_success_rate": stages[-1]["final_success_rate"]}
        else:
            name, cfg = load_recipe(job["recipe"], job["overrides"])
            summary = get_trainer(name, job["recipe"]).train(cfg, run_dir, resume=True)
    except Exception as err:  # recorded; the suite goes on with the other runs
        if not isinstance(err, FreamerError):
            logger.exception("run %s failed", job["tag"])
        error = error_line(err)
        atomic_write_text(run_dir / FAILED_NAME, error + "\n")
        return {"ok": False, "error": error, "seconds": time.perf_counter() - t0}
    done = {
        "total_frames": job["target_frames"],
        "frames": summary.get("frames"),
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    atomic_write_text(run_dir / DONE_NAME, json.dumps(done) + "\n")
    return {"ok": True, "summary": json.loads(json.dumps(summary, default=str)), "seconds": time.perf_counter() - t0}


def _outcome(future: Any, run: SuiteRun) -> dict[str, Any]:
    try:
        return future.result()
    except Exception as err:  # noqa: BLE001 -- BrokenProcessPool: the worker died (killed, out of memory)
        error = error_line(err)
        run.run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(run.run_dir / FAILED_NAME, error + "\n")
        return {"ok": False, "error": error, "seconds": 0.0}


def _finished_note(run: SuiteRun, out: dict[str, Any]) -> str:
    if not out["ok"]:
        return f"{run.tag} FAILED: {out['error']}"
    s = out["summary"]
    success = s.get("final_success_rate")
    return f"{run.tag} done in {out['seconds']:.0f} s: {s.get('frames', 0):,} frames" + (
        "" if success is None else f", success {success:.3f}"
    )


def _execute(
    pool: ProcessPoolExecutor,
    suite: str,
    todo: list[SuiteRun],
    remaining: list[int | None],
    evaluations: EvaluationQueue | None = None,
    done_before: list[SuiteRun] | None = None,
) -> list[SuiteRun]:
    """Train ``todo`` in the suite's workers (``remaining[i]``: the frames run ``i`` has left to train,
    None when unknown, for the overall progress); returns the runs that finished without error. With
    ``evaluations``, the runs of ``done_before`` are queued for evaluation once every training is queued, and
    each run as soon as it finishes."""
    level = logging.getLogger("freamer_rl").getEffectiveLevel()
    finished: list[SuiteRun] = []

    def on_result(index: int, future: Any) -> tuple[bool, str]:
        run = todo[index]
        out = _outcome(future, run)
        if out["ok"]:
            finished.append(run)
            if evaluations is not None:
                evaluations.add([run])
        return out["ok"], _finished_note(run, out)

    payloads = [
        {
            "recipe": str(r.recipe),
            "overrides": r.overrides,
            "tag": r.tag,
            "run_dir": str(r.run_dir),
            "target_frames": r.target_frames,
            "log_level": level,
        }
        for r in todo
    ]
    futures = submit_jobs(pool, _train_run, payloads)
    if evaluations is not None:
        evaluations.add(done_before or [])
    collect_jobs(futures, f"suite {suite}", remaining, "runs", on_result)
    return finished


def _lock_results(root: Path, field: str) -> RunDirLock:
    """The results folder's lock, held for the whole suite: a second suite on the same folder is refused naming the
    holder (the lock file is :class:`~freamer_rl.run.rundir.RunDirLock`'s)."""
    lock = RunDirLock(root)
    try:
        return lock.acquire()
    except FreamerError as err:
        found = re.search(r"\((pid .*|holder unknown.*)\); wait", str(err))
        holder = found.group(1) if found else str(err)
        raise FreamerError(
            f"{field}: the results folder {root} is in use by another suite ({holder}); wait for it "
            "to finish or give another --output"
        ) from None


def _train_missing(
    pool: ProcessPoolExecutor,
    suite: SuiteConfig,
    root: Path,
    runs: list[SuiteRun],
    jobs: int,
    evaluations: EvaluationQueue | None = None,
) -> list[SuiteRun]:
    """Train every run not done yet; returns those trained to the end. With ``evaluations``, each done run's
    evaluations are queued behind the trainings (see :func:`_execute`)."""
    states = describe(runs)
    pending = [(r, s) for r, s in zip(runs, states) if s["status"] != "done" and not r.error]
    counts = {k: sum(s["status"] == k for s in states) for k in ("done", "partial", "new", "failed")}
    logger.info(
        "suite %s: %d runs (%s) -> %s; training %d, %d at a time",
        suite.name,
        len(runs),
        ", ".join(f"{v} {k}" for k, v in counts.items() if v),
        root,
        len(pending),
        jobs,
    )
    for run in runs:
        if run.error:
            logger.warning("suite %s: %s cannot start: %s", suite.name, run.tag, run.error)
    if not pending:
        return []
    remaining = [
        None if r.target_frames is None else max(r.target_frames - int(s["frames"] or 0), 1) for r, s in pending
    ]
    done_before = [r for r, state in zip(runs, states) if state["status"] == "done"]
    return _execute(pool, suite.name, [r for r, _ in pending], remaining, evaluations, done_before)


def dry_run_listing(path: str | Path, output: str | Path | None = None) -> str:
    """What ``freamer-rl suite --dry-run`` prints: every run with its status, then every evaluation with its."""
    suite, root, runs = plan_suite(path, output)
    lines = [f"suite {suite.name}: {len(runs)} runs -> {root}"]
    for r in describe(runs):
        state = {
            "new": "new",
            "done": f"done ({r['frames']:,} frames)",
            "partial": f"partial ({r['frames']:,} frames)",
        }.get(r["status"], f"failed: {r['error']}")
        lines.append(f"  {r['label']:<20} {r['env']:<32} seed {r['seed']:<3} {state}")
    evals = describe_evaluations(suite.evaluate, runs)
    if evals:
        lines.append(f"{len(evals)} evaluations ({len(suite.evaluate.conditions)} conditions per run):")
    for e in evals:
        state = {"waiting": "waiting for training", "stale": "stale (older checkpoint)"}.get(e["status"], e["status"])
        state = f"failed: {e['error']}" if e["status"] == "failed" else state
        lines.append(f"  {e['label']:<20} {e['env']:<32} seed {e['seed']:<3} {e['condition']:<24} {state}")
    return "\n".join(lines) + "\n"


def select_entries(runs: list[SuiteRun], only: list[str] | None, suite: SuiteConfig) -> list[SuiteRun]:
    """The runs of the entries labelled in ``only`` (``--only``; None: every run); an unknown label is one error
    naming it and the suite's labels."""
    if only is None:
        return runs
    labels = [e.label for e in suite.entries]
    unknown = [label for label in only if label not in labels]
    if unknown:
        raise ConfigError(
            f"--only: no entry labelled {', '.join(unknown)} in suite {suite.name}; its labels: {', '.join(labels)}"
        )
    return [r for r in runs if r.label in only]


def run_suite(
    path: str | Path,
    *,
    jobs: int = 1,
    output: str | Path | None = None,
    report_only: bool = False,
    only: list[str] | None = None,
) -> dict[str, Any]:
    """Train every run not yet done (``report_only``: none), then write the report. ``only``: train and evaluate
    just the entries with these labels (the report still covers every run).

    With an ``evaluate`` section, every done run is evaluated under its conditions (those not yet evaluated for
    the run's final checkpoint; each run as soon as it is done, in the same workers) and the robustness report is
    written too.

    Returns ``{"output", "runs"`` (runs.csv rows), ``"trained"`` (tags of the runs trained to the end by this
    call), ``"failed"`` (tags of failed runs), ``"evaluated"`` / ``"eval_failed"`` (tags of this call's
    evaluations that were written / that failed)``}``."""
    if jobs < 1:
        raise ConfigError(f"--jobs: expected at least 1, got {jobs}")
    suite, root, runs = plan_suite(path, output)
    selected = select_entries(runs, only, suite)
    field_name = "--output" if output is not None else "output"
    prepare_output_folder(root, field_name)  # before anything trains
    with _lock_results(root, field_name):
        trained, evaluated, eval_failed = [], [], []
        if not report_only:
            with worker_pool(jobs) as pool:  # workers start on demand: none when nothing is left to do
                queue = EvaluationQueue(pool, suite.evaluate, suite.name) if suite.evaluate.conditions else None
                trained = _train_missing(pool, suite, root, selected, jobs, queue)
                if queue is not None:
                    evaluated, eval_failed, lost = queue.finish(selected)
                    if lost:  # a worker died (killed, out of memory): fresh workers for what was lost
                        with worker_pool(jobs) as fresh:
                            again = EvaluationQueue(fresh, suite.evaluate, suite.name, record_lost=True)
                            more, eval_failed, lost = again.finish(selected)
                            evaluated += more
                        if lost:
                            logger.warning("suite %s: evaluations lost again (a worker died); rerun", suite.name)
        results = write_report(root, suite.name, list(runs), compare=suite.compare)
        if suite.evaluate.conditions:
            write_robustness(root, suite.name, results, suite.evaluate)
    rows = [{k: v for k, v in r.items() if k != "rows"} for r in results]
    return {
        "output": root,
        "runs": rows,
        "trained": [r.tag for r in trained],
        "failed": [f"{r['label']}/{r['env']}/seed{r['seed']}" for r in rows if r["status"] == "failed"],
        "evaluated": evaluated,
        "eval_failed": eval_failed,
    }
