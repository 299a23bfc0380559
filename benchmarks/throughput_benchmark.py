"""Throughput of FreamerV1's N2-S4 recipe (this checkout and an older commit) and the TorchRL PPO-MLP, in one run.

    python benchmarks/throughput_benchmark.py        # 3 rounds x 4 batches, 1 and 2 threads, 8/16/32 envs, vs 411f9a7
    python benchmarks/throughput_benchmark.py --rounds 2 --batches 3 --threads 1 2 --num-envs 16 32 --out /tmp/tp
    python benchmarks/throughput_benchmark.py --skip-old --rounds 1 --threads 1 --num-envs 16   # no older commit

Every measurement is one subprocess with ``torch.set_num_threads(t)``, run one at a time and interleaved round by
round: for each round, for each (threads, env.num_envs) configuration, the current code, then the older commit
(``--old-commit``, default 411f9a7, extracted with ``git archive`` into a temporary folder and imported through
``PYTHONPATH=<tree>/src:<tree>``) with its own copy of the recipe when it has one (a recipe that gained keys
since would not load in its config schema), then the baseline. So all three see the same machine load, and the ratios are
taken round by round between measurements a few seconds apart.

What is timed, per batch of ``ppo.frames_per_batch`` frames (one warm-up batch first, then ``--batches`` K):

* FreamerV1: ``Trainer(cfg, tmp_dir, resume=False)`` with the recipe + ``run.threads``, ``env.num_envs`` (+ any
  positional overrides); collection = the time ``next()`` on ``trainer.make_collector(...)``'s iterator takes to
  return the batch; update = ``trainer.compute_advantage`` (the step-mode value pass on root and next states, then
  GAE) + ``trainer.update`` (the PPO epochs). These public seams are newer than 411f9a7: for an older tree the
  benchmark calls the private methods they wrap (``_make_collector``, ``_compute_advantage``, ``_update``). ``collector.update_policy_weights_()`` and the episode statistics are
  outside both. Trees before be0f9cc (a flat top level) have the config loader and the trainer at
  ``freamer_rl.config`` and ``freamer_rl.train``. For commits whose adapters are the top-level package ``envs``,
  ``envs/`` is linked as ``freamer_rl_envs`` in the extracted tree (the name the installed entry points import, so
  they load that tree's adapters), and ``env_registry.get_env_factory`` is patched to return that tree's
  ``envs.minigrid`` factory (411f9a7's adapter module declares no ``ADAPTER``). The first warm-up batch's seconds (compiling included) are reported as "first batch".
* PPO-MLP: ``PPOBaselineTrainer`` of ``recipes/baselines/ppo_mlp_n2s4.yaml`` (``trainer: ppo_baseline``) with the
  FreamerV1 recipe's ``env.id`` and ``ppo.frames_per_batch``, timed the same way: collection = ``next()`` on its
  collector, update = ``trainer.learn`` (GAE with the value network, then the PPO epochs). It always uses one env
  (that is the baseline), so ``env.num_envs`` does not change it; it is rerun for every configuration only so that
  every row has a same-load baseline.

fps = frames / time; overall = frames / (collection + update). Per round, a method's fps is over its K batches
together; the tables give the mean and min-max over rounds, and the ratios are the mean (min-max) of the per-round
ratios. Writes ``results.md``, ``results.csv`` (one row per configuration and method) and ``rounds.csv`` (every
round) into ``--out`` (default benchmarks/results/throughput/).

``--suite crafter`` measures Crafter instead, with the same job runner, summary and CSV code: the raw ``crafter.Env``,
the adapter's batched env, FreamerV1 (``recipes/crafter_cpu.yaml``) and PPO-CNN training, every rate also as a ratio
to the raw env's steps/s of the same round (no older commit). What it times: ``throughput_crafter.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import old_trees  # benchmarks/ is on sys.path: this script's own folder
import throughput_crafter as tc

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_RECIPE = ROOT / "recipes" / "minigrid_multiroom_n2s4.yaml"
BASELINE_RECIPE = ROOT / "recipes" / "baselines" / "ppo_mlp_n2s4.yaml"
RESULT_TAG = "THROUGHPUT_RESULT "
METHODS = ("current", "old", "baseline")
METRICS = ("collect_fps", "update_fps", "overall_fps")
CSV_FIELDS = [
    "threads",
    "num_envs",
    "method",
    "code",
    "rounds",
    "batches",
    "frames_per_batch",
    *[f"{m}_{s}" for m in METRICS for s in ("mean", "min", "max")],
    *[f"{m.removesuffix('_fps')}_vs_{o}" for o in ("old", "baseline") for m in METRICS],
]
ROUND_FIELDS = (
    "round threads num_envs method frames collect_s advantage_s update_s collect_fps update_fps overall_fps wall_s "
    "first_batch_s num_threads source error"
).split()


# ---------------------------------------------------------------------------------------------------------------
# worker side (one subprocess per measurement)
# ---------------------------------------------------------------------------------------------------------------
def _fps_summary(frames: int, collect: list[float], advantage: list[float], update: list[float]) -> dict:
    c, u = sum(collect), sum(update)
    return {
        "frames": frames,
        "collect_s": c,
        "advantage_s": sum(advantage),
        "update_s": u,
        "collect_fps": frames / c,
        "update_fps": frames / u,
        "overall_fps": frames / (c + u),
        "per_batch": [{"collect_s": a, "update_s": b} for a, b in zip(collect, update)],
    }


def _time_freamer(spec: dict) -> dict:
    import torch

    torch.set_num_threads(spec["threads"])
    import freamer_rl

    load_config = old_trees.from_tree("freamer_rl.trainers.registry", "freamer_rl.config", "load_config")
    src = Path(freamer_rl.__file__).resolve()
    tree = Path(spec["tree"]).resolve()
    if tree not in src.parents:
        raise RuntimeError(f"imported freamer_rl from {src}, expected it under {tree}")
    patched = old_trees.patch_legacy_adapters(tree) if spec.get("patch_envs") else False
    Trainer = old_trees.from_tree("freamer_rl.trainers.minigrid_ppo", "freamer_rl.train", "Trainer")  # noqa: N806
    k, warmup = spec["batches"], spec["warmup"]
    cfg = load_config(spec["recipe"], spec["overrides"])
    fpb = cfg.ppo.frames_per_batch
    run_dir = Path(tempfile.mkdtemp(prefix="throughput_run_"))
    try:
        trainer = Trainer(cfg, run_dir / "run", resume=False)
        torch.set_num_threads(spec["threads"])
        collector = old_trees.seam(trainer, "make_collector", "_make_collector")((warmup + k) * fpb)
        compute_advantage = old_trees.seam(trainer, "compute_advantage", "_compute_advantage")
        update_step = old_trees.seam(trainer, "update", "_update")
        # run.update_threads as train() applies it (trees older than the option learn at run.threads)
        learning_threads = getattr(trainer, "learning_threads", contextlib.nullcontext)
        it = iter(collector)
        collect, advantage, update, frames = [], [], [], 0
        for i in range(warmup + k):
            t0 = time.perf_counter()
            data = next(it)
            t1 = time.perf_counter()
            with learning_threads():
                data = compute_advantage(data)
                t2 = time.perf_counter()
                update_step(data)
            t3 = time.perf_counter()
            if i == 0:  # compiling (model.compile) happens here
                first_s = t3 - t0
            trainer.frames += data.numel()
            collector.update_policy_weights_()
            if i >= warmup:
                collect.append(t1 - t0)
                advantage.append(t2 - t1)
                update.append(t3 - t1)
                frames += data.numel()
        collector.shutdown()
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)
    out = _fps_summary(frames, collect, advantage, update)
    out.update(
        source=str(src.parent) + (" (+ envs.minigrid patch)" if patched else ""),
        num_threads=torch.get_num_threads(),
        first_batch_s=first_s,
    )
    return out


def _time_baseline(spec: dict) -> dict:
    """A ``trainer: ppo_baseline`` recipe (``spec["recipe"]``, default the PPO-MLP of :data:`BASELINE_RECIPE`) timed
    like FreamerV1: collection = ``next()`` on its collector, update = ``learn`` (GAE with the value network, then
    the PPO epochs)."""
    import torch

    torch.set_num_threads(spec["threads"])
    from freamer_rl.trainers.baselines.ppo_baseline import PPOBaselineTrainer
    from freamer_rl.trainers.registry import load_config

    k, warmup = spec["batches"], spec["warmup"]
    recipe = Path(spec.get("recipe", BASELINE_RECIPE))
    cfg = load_config(recipe, spec["overrides"])
    run_dir = Path(tempfile.mkdtemp(prefix="throughput_baseline_"))
    try:
        trainer = PPOBaselineTrainer(cfg, run_dir / "run", resume=False)
        torch.set_num_threads(spec["threads"])
        collector = trainer.make_collector((warmup + k) * cfg.ppo.frames_per_batch)
        it = iter(collector)
        collect, update, frames = [], [], 0
        for i in range(warmup + k):
            t0 = time.perf_counter()
            data = next(it)
            t1 = time.perf_counter()
            trainer.learn(data)
            t2 = time.perf_counter()
            if i == 0:
                first_s = t2 - t0
            trainer.frames += data.numel()
            collector.update_policy_weights_()
            if i >= warmup:
                collect.append(t1 - t0)
                update.append(t2 - t1)
                frames += data.numel()
        collector.shutdown()
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)
    out = _fps_summary(frames, collect, [0.0] * len(collect), update)
    source = recipe.relative_to(ROOT) if recipe.is_relative_to(ROOT) else recipe
    out.update(source=str(source), num_threads=torch.get_num_threads(), first_batch_s=first_s)
    return out


def measure(spec: dict) -> dict:
    """One measurement (what a worker subprocess runs), by ``spec["method"]``, with its wall time."""
    timers = {"baseline": _time_baseline, "ppo_cnn": _time_baseline, **tc.TIMERS}  # tc: raw_env, adapter_env
    t0 = time.perf_counter()
    result = timers.get(spec["method"], _time_freamer)(spec)  # current, old, freamer: FreamerV1
    result["wall_s"] = time.perf_counter() - t0
    return result


def _worker(spec: dict) -> None:
    import logging

    logging.basicConfig(level=logging.WARNING)
    print(RESULT_TAG + json.dumps(measure(spec)), flush=True)


# ---------------------------------------------------------------------------------------------------------------
# driver side
# ---------------------------------------------------------------------------------------------------------------
def _git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True, text=True).stdout.strip()


def _current_code() -> str:
    try:
        dirty = bool(_git("status", "--porcelain", "--untracked-files=no"))
        return _git("rev-parse", "--short", "HEAD") + (" + uncommitted changes" if dirty else "")
    except (subprocess.CalledProcessError, FileNotFoundError):
        return "unknown (not a git checkout)"


def extract_commit(commit: str, dest: Path) -> str:
    """``git archive`` the commit's ``src``, ``envs`` and ``recipes`` into ``dest`` (no worktree, nothing in .git
    changes)."""
    sha = _git("rev-parse", "--short", f"{commit}^{{commit}}")
    paths = [p for p in ("src", "envs", "recipes") if _git("ls-tree", "--name-only", sha, p)]
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "--format=tar", sha, *paths], check=True, capture_output=True
    ).stdout
    dest.mkdir(parents=True, exist_ok=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    if (dest / "envs").is_dir() and not (dest / "src" / "freamer_rl_envs").is_dir():
        # trees that installed envs/ as ``freamer_rl_envs`` import it under that name: the tree root is on PYTHONPATH
        (dest / "freamer_rl_envs").symlink_to("envs", target_is_directory=True)
    return sha


def run_job(spec: dict, tree: Path | None, timeout: float) -> dict:
    """One measurement in its own interpreter; returns the worker's result or ``{"error": ...}``."""
    env = dict(os.environ)
    if tree is not None:  # FreamerV1 code from this tree, ahead of the editable install (old trees: envs/ too)
        paths = [str(tree / "src")] + ([str(tree)] if spec.get("patch_envs") else [])
        env["PYTHONPATH"] = os.pathsep.join([*paths, env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.update(OMP_NUM_THREADS=str(spec["threads"]), MKL_NUM_THREADS=str(spec["threads"]))
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
            cwd=tempfile.gettempdir(),
        )
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s", "wall_s": time.perf_counter() - t0}
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG) :])
    tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
    return {"error": f"exit {proc.returncode}: {tail[:300]}", "wall_s": time.perf_counter() - t0}


def _old_recipe(recipe: Path, tree: Path) -> str:
    """The older commit's copy of ``recipe`` (same path in its tree) when it has one, else ``recipe`` itself: a
    recipe that gained keys since (e.g. ``model.dnc.compile``) would not load in the older config schema."""
    try:
        candidate = tree / recipe.relative_to(ROOT)
    except ValueError:  # a recipe outside this checkout
        return str(recipe)
    return str(candidate) if candidate.is_file() else str(recipe)


def _check_config(recipe: str, overrides: list[str]):
    """``(config, None)`` for a valid configuration, else ``(None, the ConfigError line)``."""
    from freamer_rl.errors import ConfigError
    from freamer_rl.trainers.registry import load_config

    try:
        return load_config(recipe, overrides), None
    except ConfigError as err:
        return None, str(err)


def valid_configs(recipe: Path, threads: list[int], num_envs: list[int] | None, overrides: list[str]):
    """``(configs, notes, config)``: the (threads, env.num_envs) pairs the recipe accepts (``num_envs`` None: the
    recipe's own), a note for each env count it refuses, and the last valid config; SystemExit when none is."""
    if num_envs is None:
        cfg, err = _check_config(str(recipe), overrides)
        if err is not None:
            raise SystemExit(f"{recipe}: {err}")
        num_envs = [cfg.env.num_envs]
    configs, notes, cfg = [], [], None
    for t in threads:
        for n in num_envs:
            got, err = _check_config(str(recipe), [*overrides, f"run.threads={t}", f"env.num_envs={n}"])
            if err is not None:
                if t == threads[0]:
                    notes.append(f"env.num_envs={n} skipped: {err}")
                continue
            configs.append((t, n))
            cfg = got
    if not configs:
        raise SystemExit("no valid configuration: " + "; ".join(notes))
    return configs, notes, cfg


def _csv_value(v):
    return f"{v:.4g}" if isinstance(v, float) and abs(v) < 100 else f"{v:.1f}" if isinstance(v, float) else v


def _stats(values: list[float]) -> tuple[float, float, float]:
    return statistics.mean(values), min(values), max(values)


def _fmt(values: list[float], nd: int = 0) -> str:
    if not values:
        return "n/a"
    m, lo, hi = _stats(values)
    return f"{m:,.{nd}f} ({lo:,.{nd}f}-{hi:,.{nd}f})" if len(values) > 1 else f"{m:,.{nd}f}"


def summarise(
    rounds: list[dict],
    configs: list[tuple[int, int]],
    methods: list[str],
    codes: dict,
    pairs: dict[str, tuple[str, ...]] | None = None,
    reference: str | None = None,
) -> list[dict]:
    """One row per (threads, num_envs, method): mean/min/max over rounds of each metric a method reports (an env
    measurement has no update), and for each method of ``pairs`` (default ``current`` against ``old`` and
    ``baseline``) the per-round ratios ``metric / other's metric`` (``other's reference metric`` when ``reference``
    is given): the mean over rounds, plus the lists for the Markdown."""
    pairs = {"current": ("old", "baseline")} if pairs is None else pairs
    ok = [r for r in rounds if not r.get("error")]
    rows = []
    for t, n in configs:
        by = {
            m: {r["round"]: r for r in ok if (r["threads"], r["num_envs"], r["method"]) == (t, n, m)} for m in methods
        }
        for m in methods:
            rs = list(by[m].values())
            if not rs:
                continue
            row = {"threads": t, "num_envs": n, "method": m, "code": codes[m], "rounds": len(rs)}
            for metric in METRICS:
                values = [r[metric] for r in rs if r.get(metric) is not None]
                stats = _stats(values) if values else (None, None, None)
                row[f"{metric}_mean"], row[f"{metric}_min"], row[f"{metric}_max"] = stats
                row[f"_{metric}"] = values
            for other in pairs.get(m, ()):
                for metric in METRICS:
                    ref = reference or metric
                    ratios = [
                        r[metric] / by[other][i][ref]
                        for i, r in by[m].items()
                        if r.get(metric) is not None and i in by.get(other, {})
                    ]
                    key = f"{metric.removesuffix('_fps')}_vs_{other}"
                    row[key] = statistics.mean(ratios) if ratios else None
                    row[f"_{key}"] = ratios
            rows.append(row)
    return rows


def write_csvs(rows: list[dict], rounds: list[dict], out: Path, meta: dict, fields: list[str], extra=()) -> None:
    """``rounds.csv`` (every measurement: :data:`ROUND_FIELDS` + ``extra``) and ``results.csv`` (one row per
    configuration and method: ``fields``)."""
    out.mkdir(parents=True, exist_ok=True)
    with (out / "rounds.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[*ROUND_FIELDS, *extra], extrasaction="ignore")
        w.writeheader()
        w.writerows({k: _csv_value(v) for k, v in r.items()} for r in rounds)
    with (out / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            r = {**r, "batches": meta["batches"], "frames_per_batch": meta["frames_per_batch"]}
            w.writerow({k: _csv_value(v) for k, v in r.items()})


def _finish_report(lines: list[str], rounds: list[dict], notes: list[str], out: Path, meta: dict) -> str:
    """Notes (and every failed measurement), the command; writes ``results.md``."""
    errors = [r for r in rounds if r.get("error")]
    if notes or errors:
        lines += ["", "Notes:", ""]
        lines += [f"- {n}" for n in notes]
        lines += [
            f"- round {r['round']}, {r['threads']} thread(s), {r['num_envs']} envs, {r['method']}: {r['error']}"
            for r in errors
        ]
    lines += ["", f"Command: `{meta['command']}`"]
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    return text


def write_report(rows: list[dict], rounds: list[dict], notes: list[str], out: Path, meta: dict) -> str:
    write_csvs(rows, rounds, out, meta, CSV_FIELDS)
    names = {"current": "FreamerV1 current", "old": "FreamerV1 old", "baseline": "TorchRL PPO-MLP"}
    lines = [
        "# Throughput: FreamerV1 N2-S4 recipe vs an older commit vs TorchRL PPO-MLP",
        "",
        f"Generated {meta['date']} on {meta['machine']}; load average {meta['load_start']} at the start, "
        f"{meta['load_end']} at the end.",
        f"Code: current = {meta['codes']['current']}, old = {meta['codes'].get('old', 'skipped')}, "
        f"baseline = recipes/baselines/ppo_mlp_n2s4.yaml (trainer: ppo_baseline, one env, MLP 256x2).",
        f"{meta['rounds']} round(s), interleaved (each round: every configuration, current / old / baseline, each in "
        f"its own subprocess); per measurement {meta['warmup']} warm-up batch(es) + {meta['batches']} timed batches of "
        f"{meta['frames_per_batch']} frames. Overrides: {meta['overrides'] or 'none'}.",
        "Cells: mean (min-max) over rounds, frames/s. Update = GAE value pass + GAE + PPO epochs "
        "(FreamerV1: `_compute_advantage` + `_update`); overall = frames / (collection + update). First batch: "
        "seconds of the first warm-up batch (collection + update, compiling included), mean over rounds.",
        "",
        "| threads | env.num_envs | code | collection fps | update fps | overall fps | first batch s |",
        "|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        n = "1 (own)" if r["method"] == "baseline" else r["num_envs"]
        lines.append(
            f"| {r['threads']} | {n} | {names[r['method']]} | {_fmt(r['_collect_fps'])} | "
            f"{_fmt(r['_update_fps'])} | {_fmt(r['_overall_fps'])} | {_first_batch(rounds, r)} |"
        )
    cur = [r for r in rows if r["method"] == "current"]
    if any(r.get("_overall_vs_old") or r.get("_overall_vs_baseline") for r in cur):
        lines += [
            "",
            "Ratios, current / other, per round then mean (min-max):",
            "",
            "| threads | env.num_envs | collection vs old | update vs old | overall vs old | "
            "collection vs baseline | update vs baseline | overall vs baseline |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in cur:
            cells = [
                _fmt(r.get(f"_{m.removesuffix('_fps')}_vs_{o}") or [], 2) for o in ("old", "baseline") for m in METRICS
            ]
            lines.append(f"| {r['threads']} | {r['num_envs']} | " + " | ".join(cells) + " |")
    return _finish_report(lines, rounds, notes, out, meta)


def _first_batch(rounds: list[dict], row: dict) -> str:
    """Mean seconds of the first warm-up batch over the rounds of ``row``'s configuration and method."""
    keys = ("threads", "num_envs", "method")
    seconds = [
        r["first_batch_s"] for r in rounds if r.get("first_batch_s") is not None and all(r[k] == row[k] for k in keys)
    ]
    return f"{statistics.mean(seconds):.1f}" if seconds else "n/a"


def _load() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def _machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{os.cpu_count()} CPU cores ({cpu})"


def write_crafter_report(rows: list[dict], rounds: list[dict], notes: list[str], out: Path, meta: dict) -> str:
    """The Crafter suite's ``results.md`` / ``results.csv`` / ``rounds.csv`` (tables: ``throughput_crafter``)."""
    write_csvs(rows, rounds, out, meta, tc.CSV_FIELDS, tc.ROUND_EXTRA)
    lines, raw_notes = tc.report_lines(rows, rounds, meta, _fmt)
    return _finish_report(lines, rounds, [*raw_notes, *notes], out, meta)


def _minigrid_plan(args, fixed: list[str]) -> dict:
    """The N2-S4 suite: configurations (threads x env.num_envs), methods and one round's jobs
    ``((threads, num_envs, method), spec, tree)``; ``tmp`` holds the older commit's tree."""
    methods = ["current"] + ([] if args.skip_old else ["old"]) + ([] if args.skip_baseline else ["baseline"])
    recipe = Path(args.recipe or DEFAULT_RECIPE).resolve()
    configs, notes, cfg = valid_configs(recipe, args.threads, args.num_envs or [8, 16, 32], [*fixed, *args.overrides])
    fpb, env_id = cfg.ppo.frames_per_batch, cfg.env.id  # the baseline gets the recipe's env and batch size
    total = f"run.total_frames={(args.warmup + args.batches) * fpb}"
    codes = {"current": _current_code(), "baseline": "ppo_baseline"}
    tmp = Path(tempfile.mkdtemp(prefix="throughput_old_"))
    trees, recipes = {"current": ROOT, "baseline": None}, {"current": str(recipe)}
    if "old" in methods:
        codes["old"], trees["old"] = extract_commit(args.old_commit, tmp), tmp
        recipes["old"] = _old_recipe(recipe, tmp)
        if recipes["old"] != str(recipe):
            notes.append(
                f"The older commit runs its own copy of the recipe ({recipe.relative_to(ROOT)} at "
                f"{codes['old']}): each commit's default recipe, which the old config loader can read."
            )
    jobs = []
    for t, n in configs:
        for m in methods:
            spec = {"method": m, "threads": t, "num_envs": n, "batches": args.batches, "warmup": args.warmup}
            spec["seed"] = args.seed
            if m == "baseline":
                base = [f"env.id={env_id}", f"ppo.frames_per_batch={fpb}", *args.baseline_override]
                spec.update(recipe=str(BASELINE_RECIPE), overrides=[*fixed, *base, f"run.threads={t}", total])
            else:
                sized = [f"run.threads={t}", f"env.num_envs={n}", total]
                spec.update(recipe=recipes[m], tree=str(trees[m]), patch_envs=m == "old")
                spec["overrides"] = [*fixed, *args.overrides, *sized]
            jobs.append(((t, n, m), spec, trees[m]))
    return dict(configs=configs, methods=methods, codes=codes, notes=notes, jobs=jobs, frames_per_batch=fpb, tmp=tmp)


def _run_rounds(jobs: list, rounds: int, timeout: float) -> list[dict]:
    """Every job of ``jobs`` once per round, one at a time, in order (so each round interleaves every method)."""
    results: list[dict] = []
    t_start = time.perf_counter()
    for rnd in range(rounds):
        for (t, n, m), spec, tree in jobs:
            res = run_job(spec, tree, timeout)
            results.append({"round": rnd, "threads": t, "num_envs": n, "method": m, **res})
            rates = [f"{k.removesuffix('_fps')} {res[k]:.0f}" for k in METRICS if res.get(k) is not None]
            msg = res.get("error") or ", ".join(rates) + " fps"
            print(f"[{time.perf_counter() - t_start:6.0f}s] round {rnd} | {t} thread(s) | {n} envs | {m}: {msg}")
            sys.stdout.flush()
    return results


def _parse(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", choices=("minigrid", "crafter"), default="minigrid", help="N2-S4 (default) or Crafter")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--batches", type=int, default=4, help="timed batches per measurement (after the warm-up)")
    ap.add_argument("--warmup", type=int, default=1, help="untimed batches first")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--num-envs", type=int, nargs="+", help="default: 8 16 32 (minigrid), the recipe's (crafter)")
    ap.add_argument("--old-commit", default="411f9a7")
    ap.add_argument("--skip-old", action="store_true", help="measure only the current code and the baseline")
    ap.add_argument("--skip-baseline", action="store_true")
    ap.add_argument("--recipe", help="FreamerV1 recipe (default: the suite's)")
    ap.add_argument(
        "--baseline-override", action="append", default=[], help="a dotted override for the baseline (repeatable)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--job-timeout", type=float, default=900.0, help="seconds per measurement subprocess")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "throughput"))
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("overrides", nargs="*", help="dotted overrides for the FreamerV1 recipe (both codes)")
    return ap.parse_intermixed_args(argv)


def main(argv: list[str] | None = None) -> str:
    args = _parse(argv)
    if args.worker:
        _worker(json.loads(args.worker))
        return ""
    fixed = ["logging.progress_bar=false", "logging.checkpoint_every_frames=1000000000", f"run.seed={args.seed}"]
    if args.suite == "crafter":
        plan = tc.plan(args, fixed, valid_configs, _current_code())
    else:
        plan = _minigrid_plan(args, fixed)
    meta = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": _machine(),
        "load_start": _load(),
        "codes": plan["codes"],
        "rounds": args.rounds,
        "batches": args.batches,
        "warmup": args.warmup,
        "frames_per_batch": plan["frames_per_batch"],
        "overrides": " ".join(args.overrides),
        "command": " ".join(["python benchmarks/throughput_benchmark.py", *(sys.argv[1:] if argv is None else argv)]),
    }
    try:
        rounds = _run_rounds(plan["jobs"], args.rounds, args.job_timeout)
    finally:
        if plan.get("tmp"):
            shutil.rmtree(plan["tmp"], ignore_errors=True)
    meta["load_end"] = _load()
    out = Path(args.out)
    if args.suite == "crafter":
        meta["recipe"] = str(
            plan["recipe"].relative_to(ROOT) if plan["recipe"].is_relative_to(ROOT) else plan["recipe"]
        )
        rows = summarise(rounds, plan["configs"], plan["methods"], plan["codes"], tc.PAIRS, tc.REFERENCE)
        text = write_crafter_report(rows, rounds, plan["notes"], out, meta)
    else:
        rows = summarise(rounds, plan["configs"], plan["methods"], plan["codes"])
        text = write_report(rows, rounds, plan["notes"], out, meta)
    print(text)
    return text


if __name__ == "__main__":
    main()
