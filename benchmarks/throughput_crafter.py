"""Crafter suite of the throughput benchmark (``python benchmarks/throughput_benchmark.py --suite crafter``).

    python benchmarks/throughput_benchmark.py --suite crafter --rounds 2 --batches 2 --threads 1 2 --out /tmp/tpc

Per round, at each ``--threads`` value t (and each ``--num-envs`` n, default the recipe's ``env.num_envs``), six
measurements, each in its own subprocess through the main script's job runner, one at a time (the recipes generate
the next worlds in a worker process, ``env.reset_workers: 1``; the ``_inline`` twins of the adapter env and of
FreamerV1 run the same recipe with ``env.reset_workers=0``, crafter's reset in the env's process, so the report
shows what the prefetching buys, round by round):

* ``raw_env``: one ``crafter.Env(seed=...)`` (crafter's defaults: the benchmark's 64x64 world, 9x9 view, 64x64
  frames, reward on) with uniform random actions from numpy. The first reset (a whole world) is untimed, like the
  training measurements' warm-up batch; then ``batches * ppo.frames_per_batch`` steps are timed, the resets at
  episode ends included. steps/s = steps / (step time + reset time); both parts are reported apart too.
* ``adapter_env``: the env a trainer builds from the FreamerV1 recipe's ``env`` section
  (:func:`freamer_rl.run.envs.make_batched_env`: ``env.num_envs`` ``CrafterEnv`` in a ``SerialEnv`` + InitTracker,
  StepCounter, RewardSum), collected by :func:`freamer_rl.run.collection.make_collector` with no policy (TorchRL's
  ``RandomPolicy``: uniform random actions) in batches of ``ppo.frames_per_batch``: one warm-up batch, then
  ``batches`` timed. steps/s = frames / collection time.
* ``freamer``: ``recipes/crafter_cpu.yaml`` timed as the N2-S4 suite times FreamerV1 (collection = ``next()`` on
  ``trainer.make_collector``'s iterator; update = ``trainer.compute_advantage`` + ``trainer.update``).
* ``ppo_cnn``: ``recipes/baselines/ppo_cnn_crafter.yaml`` (``trainer: ppo_baseline``) with FreamerV1's
  ``ppo.frames_per_batch`` and ``env.num_envs``, timed as the N2-S4 baseline (collection; update = ``trainer.learn``).

Ratios are taken round by round, then averaged: every rate / the raw env's steps/s of the same round and thread
count (the issue's target: FreamerV1 overall >= 0.8x), and collection fps / the adapter env's steps/s, the share of a
collection batch's time that stepping the batched env takes (the rest is the policy forward with its primers and the
collector's bookkeeping of the policy outputs). Random actions end episodes after ~150-200 steps; a policy that
lives longer resets less often, so the env rates are those of an early, near-random agent.
"""

from __future__ import annotations

import functools
import importlib.metadata
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FREAMER_RECIPE = ROOT / "recipes" / "crafter_cpu.yaml"
PPO_CNN_RECIPE = ROOT / "recipes" / "baselines" / "ppo_cnn_crafter.yaml"
METHODS = ("raw_env", "adapter_env_inline", "adapter_env", "freamer_inline", "freamer", "ppo_cnn")
ENV_METHODS = ("raw_env", "adapter_env_inline", "adapter_env")
#: the ``_inline`` measurements: the recipe with crafter's own reset in the env's process (env.reset_workers=0)
INLINE = {"adapter_env_inline": "adapter_env", "freamer_inline": "freamer"}
NAMES = {
    "raw_env": "raw crafter.Env (1 env)",
    "adapter_env_inline": "adapter env (random actions), resets inline",
    "adapter_env": "adapter env (random actions)",
    "freamer_inline": "FreamerV1 (crafter_cpu), resets inline",
    "freamer": "FreamerV1 (crafter_cpu)",
    "ppo_cnn": "PPO-CNN (ppo_cnn_crafter)",
}
#: ratio pairs for ``summarise``: method -> the methods whose ``REFERENCE`` metric of the same round divides it
PAIRS = {
    "adapter_env_inline": ("raw_env",),
    "adapter_env": ("raw_env",),
    "freamer_inline": ("raw_env", "adapter_env_inline"),
    "freamer": ("raw_env", "adapter_env"),
    "ppo_cnn": ("raw_env", "adapter_env"),
}
REFERENCE = "collect_fps"  # an env measurement's steps/s
RATIO_FIELDS = [f"{m}_vs_raw_env" for m in ("collect", "update", "overall")]
RATIO_FIELDS += ["collect_vs_adapter_env", "collect_vs_adapter_env_inline"]
ROUND_EXTRA = ("step_s", "reset_s", "resets")  # the raw env's split of its time, in rounds.csv
CSV_FIELDS = [
    "threads",
    "num_envs",
    "method",
    "code",
    "rounds",
    "batches",
    "frames_per_batch",
    *[f"{m}_{s}" for m in ("collect_fps", "update_fps", "overall_fps") for s in ("mean", "min", "max")],
    *RATIO_FIELDS,
]


# ---------------------------------------------------------------------------------------------------------------
# worker side
# ---------------------------------------------------------------------------------------------------------------
def _env_rates(steps: int, seconds: float) -> dict:
    """An env measurement in the result layout of the training ones: collection only (no update, no overall)."""
    return {"frames": steps, "collect_s": seconds, "collect_fps": steps / seconds}


def _crafter_version() -> str:
    return importlib.metadata.version("crafter")  # the package has no __version__


def time_raw_env(spec: dict) -> dict:
    """``spec["steps"]`` random-action steps of one ``crafter.Env`` after an untimed first reset; episode-end resets
    are timed (``reset_s``, ``resets``) and included in the rate."""
    import crafter
    import numpy as np

    env = crafter.Env(seed=spec["seed"])
    rng = np.random.default_rng(spec["seed"])
    n_actions = env.action_space.n
    env.reset()
    step_s = reset_s = 0.0
    resets = 0
    for _ in range(spec["steps"]):
        t0 = time.perf_counter()
        _, _, done, _ = env.step(int(rng.integers(n_actions)))
        t1 = time.perf_counter()
        step_s += t1 - t0
        if done:
            env.reset()
            reset_s += time.perf_counter() - t1
            resets += 1
    out = _env_rates(spec["steps"], step_s + reset_s)
    out.update(step_s=step_s, reset_s=reset_s, resets=resets, source=f"crafter {_crafter_version()}")
    return out


def time_adapter_env(spec: dict) -> dict:
    """The trainer's batched env of ``spec["recipe"]`` collected with random actions (warm-up batch untimed)."""
    import torch

    torch.set_num_threads(spec["threads"])
    from freamer_rl.run.collection import make_collector
    from freamer_rl.run.envs import make_batched_env
    from freamer_rl.trainers.registry import load_config

    cfg = load_config(spec["recipe"], spec["overrides"])
    fpb, k, warmup = cfg.ppo.frames_per_batch, spec["batches"], spec["warmup"]
    seed = spec["seed"] * 10_000  # the trainer's seed rule (RunLoop._make_collector / _env_fns)
    env_fns = [
        functools.partial(make_batched_env, cfg, [], seed + 1000 * i) for i in range(cfg.collector.num_collectors)
    ]
    collector = make_collector(
        cfg.collector,
        env_fns,
        None,
        frames_per_batch=fpb,
        total_frames=(warmup + k) * fpb,
        devices={"policy_device": "cpu", "env_device": "cpu", "storing_device": "cpu"},
    )
    it = iter(collector)
    seconds, frames = 0.0, 0
    for i in range(warmup + k):
        t0 = time.perf_counter()
        data = next(it)
        if i >= warmup:
            seconds += time.perf_counter() - t0
            frames += data.numel()
    collector.shutdown()
    out = _env_rates(frames, seconds)
    out.update(source=f"make_batched_env({cfg.env.adapter}, {cfg.env.id}, num_envs={cfg.env.num_envs})")
    out["num_threads"] = torch.get_num_threads()
    return out


TIMERS = {"raw_env": time_raw_env, "adapter_env": time_adapter_env, "adapter_env_inline": time_adapter_env}


# ---------------------------------------------------------------------------------------------------------------
# driver side
# ---------------------------------------------------------------------------------------------------------------
def plan(args, fixed: list[str], valid_configs: Callable, current_code: str) -> dict:
    """Configurations, methods, codes and one round's jobs ``((threads, num_envs, method), spec, tree)``
    (``valid_configs``: the main script's check of (threads, env.num_envs) pairs against the recipe)."""
    recipe = Path(args.recipe).resolve() if args.recipe else FREAMER_RECIPE
    configs, notes, cfg = valid_configs(recipe, args.threads, args.num_envs, [*fixed, *args.overrides])
    fpb, total = cfg.ppo.frames_per_batch, (args.warmup + args.batches) * cfg.ppo.frames_per_batch
    jobs = []
    for t, n in configs:
        common = {"threads": t, "num_envs": n, "batches": args.batches, "warmup": args.warmup, "seed": args.seed}
        sized = [f"run.threads={t}", f"env.num_envs={n}", f"run.total_frames={total}"]
        freamer = {**common, "recipe": str(recipe), "overrides": [*fixed, *args.overrides, *sized]}
        ppo_overrides = [*fixed, f"ppo.frames_per_batch={fpb}", *args.baseline_override, *sized]
        specs = {
            "raw_env": {**common, "steps": args.batches * fpb},
            "adapter_env": freamer,
            "freamer": {**freamer, "tree": str(ROOT), "patch_envs": False},
            "ppo_cnn": {**common, "recipe": str(PPO_CNN_RECIPE), "overrides": ppo_overrides},
        }
        for inline, base in INLINE.items():  # the same measurement with world generation on the critical path
            specs[inline] = {**specs[base], "overrides": [*specs[base]["overrides"], "env.reset_workers=0"]}
        for m in METHODS:
            jobs.append(((t, n, m), {**specs[m], "method": m}, ROOT if m.startswith("freamer") else None))
    codes = {"raw_env": f"crafter {_crafter_version()}", "ppo_cnn": "ppo_baseline"}
    codes.update({m: current_code for m in (*INLINE, *INLINE.values())})
    return dict(
        configs=configs, methods=list(METHODS), codes=codes, notes=notes, jobs=jobs, frames_per_batch=fpb, recipe=recipe
    )


def _raw_env_notes(rounds: list[dict]) -> list[str]:
    """Where the raw env's time goes, per thread count: step and reset costs over every round."""
    notes = []
    for t in sorted({r["threads"] for r in rounds if r["method"] == "raw_env" and not r.get("error")}):
        rs = [r for r in rounds if r["method"] == "raw_env" and r["threads"] == t and not r.get("error")]
        steps, step_s = sum(r["frames"] for r in rs), sum(r["step_s"] for r in rs)
        resets, reset_s = sum(r["resets"] for r in rs), sum(r["reset_s"] for r in rs)
        per_reset = f"{reset_s / resets:.2f} s per reset" if resets else "no reset"
        notes.append(
            f"raw env, {t} thread(s): {1e3 * step_s / steps:.2f} ms per step, {per_reset}, {resets} resets in "
            f"{steps} steps; resets take {100 * reset_s / (step_s + reset_s):.0f}% of its time."
        )
    return notes


def _prefetch_notes(rounds: list[dict], fmt: Callable) -> list[str]:
    """What generating worlds ahead (``env.reset_workers``, the recipes' setting) buys: per round and thread count,
    each measurement's rate over its ``_inline`` twin's (collection for the env, overall for FreamerV1)."""
    notes = []
    ok = [r for r in rounds if not r.get("error")]
    for t in sorted({r["threads"] for r in ok}):
        by = {(r["round"], r["num_envs"], r["method"]): r for r in ok if r["threads"] == t}
        for inline, base in INLINE.items():
            metric, what = ("collect_fps", "collection") if base in ENV_METHODS else ("overall_fps", "overall")
            ratios = [
                by[(rnd, n, base)][metric] / r[metric]
                for (rnd, n, m), r in by.items()
                if m == inline and (rnd, n, base) in by
            ]
            if ratios:
                notes.append(
                    f"{NAMES[base]}, {t} thread(s): {what} fps {fmt(ratios, 2)}x that with "
                    "resets inline (env.reset_workers=0), per round."
                )
    return notes


def report_lines(rows: list[dict], rounds: list[dict], meta: dict, fmt: Callable) -> tuple[list[str], list[str]]:
    """The Markdown tables of the Crafter suite and its notes (``fmt(values, digits)`` formats a mean (min-max)
    cell)."""
    lines = [
        "# Throughput on Crafter: raw env, adapter env, FreamerV1 and PPO-CNN training",
        "",
        f"Generated {meta['date']} on {meta['machine']}; load average {meta['load_start']} at the start, "
        f"{meta['load_end']} at the end.",
        f"Code: {meta['codes']['freamer']}; {meta['codes']['raw_env']}. FreamerV1 = {meta['recipe']}, PPO-CNN = "
        f"{PPO_CNN_RECIPE.relative_to(ROOT)} with FreamerV1's ppo.frames_per_batch and env.num_envs.",
        f"{meta['rounds']} round(s), interleaved (each round: at each thread count, raw env / adapter env and "
        f"FreamerV1, each with resets inline and with the recipe's worlds generated ahead / PPO-CNN, each in its own "
        f"subprocess); per measurement {meta['warmup']} warm-up batch(es) + "
        f"{meta['batches']} timed batches of {meta['frames_per_batch']} frames (raw env: the same number of steps "
        f"after its first reset). Overrides: {meta['overrides'] or 'none'}.",
        "Cells: mean (min-max) over rounds. Env rows: env steps/s with random actions, resets included. Update = "
        "advantage (value pass + GAE) + PPO epochs; overall = frames / (collection + update).",
        "",
        "| threads | env.num_envs | measurement | collection fps (env: steps/s) | update fps | overall fps |",
        "|---:|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        n = 1 if r["method"] == "raw_env" else r["num_envs"]
        env = r["method"] in ENV_METHODS
        cells = [fmt(r["_collect_fps"])] + ["-" if env else fmt(r[f"_{m}"]) for m in ("update_fps", "overall_fps")]
        lines.append(f"| {r['threads']} | {n} | {NAMES[r['method']]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Ratios per round, then mean (min-max): rate / raw env steps/s of the same round (target for FreamerV1 "
        "overall: >= 0.8); env share of collection = collection fps / adapter env steps/s (the time a collection "
        "batch spends stepping the env; the rest is the policy).",
        "",
        "| threads | env.num_envs | measurement | collection / raw env | update / raw env | overall / raw env | "
        "env share of collection |",
        "|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        if r["method"] == "raw_env":
            continue
        env = r["method"] in ENV_METHODS
        cells = [fmt(r.get("_collect_vs_raw_env") or [], 2)]
        cells += ["-" if env else fmt(r.get(f"_{m}_vs_raw_env") or [], 2) for m in ("update", "overall")]
        cells.append("-" if env else fmt(r.get(f"_collect_vs_{PAIRS[r['method']][1]}") or [], 2))
        lines.append(f"| {r['threads']} | {r['num_envs']} | {NAMES[r['method']]} | " + " | ".join(cells) + " |")
    return lines, _raw_env_notes(rounds) + _prefetch_notes(rounds, fmt)
