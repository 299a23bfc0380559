"""Recipe chains: a curriculum of runs, each stage starting from the previous stage's final weights.

A chain file is YAML::

    name: multiroom_curriculum
    seed: 0
    output_dir: runs
    overrides: [run.threads=1]               # every stage
    stages:
      - {name: n2s4, recipe: minigrid_multiroom_n2s4.yaml, overrides: [run.stop_at_success=0.9]}
      - {name: n3s4, recipe: minigrid_multiroom_n2s4.yaml, overrides: [env.id=MiniGrid-MultiRoom-N3-S4-v0]}

A chain may instead name one ``recipe`` for every stage (then no stage names its own), so that the same curriculum
trains another agent with one override: ``freamer-rl chain FILE recipe=baselines/ppo_mlp_n2s4.yaml`` (or a suite
entry's ``overrides: [recipe=...]``), every stage keeping its env id, frame cap and stop rule.

Stage recipes are paths relative to the chain file's folder and must stay inside it; transfer (``run.init_from``) is a
setting of the MiniGrid / gymnasium trainer, so chains of health recipes stop at stage 2 with one error line. Stage
``k`` trains in ``<output_dir>/<name>-s<seed>/<stage name>`` with ``run.init_from`` set to stage ``k-1``'s run
directory (transfer: weights only). ``freamer-rl chain <file>`` is resumable: a finished stage (its ``summary.json``
written after its last checkpoint, with the weights' sections this chain asks for: else a ConfigError) is read back,
an interrupted one resumes from its checkpoint. ``chain_summary.json`` / ``chain_summary.md`` list every stage with
the frames counted across the chain (a curriculum's earlier stages count towards its budget).

Overrides on the command line follow one rule: a key that is a chain-file field (``name``, ``seed``, ``output_dir``,
``overrides``, ``recipe``, ``stages``) edits the chain file (``freamer-rl chain FILE seed=1``); any other key goes to
every stage, after the chain's and the stage's own overrides, so it wins (``freamer-rl chain FILE
run.total_frames=2048`` shrinks every stage for a smoke test). ``run.seed`` is always the chain's ``seed``. The output
folder is checked writable before the first stage; one overall progress bar (a log line per stage off a terminal)
gives the ETA.

A benchmark suite (:mod:`freamer_rl.experiments.suite`) runs a chain as one of its entries: a recipe path ending in
``.chain.yaml`` (:func:`is_chain`) is a chain, trained by :func:`run_chain` with ``root=`` the suite's run folder and
planned by :func:`plan_chain`.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from freamer_rl.config.checks import run_name_problem
from freamer_rl.config.loader import VALIDATORS, config_from_dict, config_to_dict, read_recipe
from freamer_rl.errors import ConfigError, FreamerError
from freamer_rl.experiments.folders import prepare_output_folder
from freamer_rl.experiments.progress import OverallProgress
from freamer_rl.run.checkpoint import structural_differences
from freamer_rl.run.metrics import SUCCESS_LEVELS
from freamer_rl.trainers.registry import get_trainer, load_recipe

logger = logging.getLogger(__name__)

__all__ = [
    "CHAIN_KEYS",
    "CHAIN_SUFFIX",
    "ChainConfig",
    "ChainPlan",
    "StageConfig",
    "is_chain",
    "load_chain",
    "plan_chain",
    "run_chain",
    "split_overrides",
]

CHAIN_SUFFIX = ".chain.yaml"


@dataclass
class StageConfig:
    name: str
    recipe: str | None = None  # relative to the chain file's folder; None: the chain's ``recipe``
    overrides: list[str] = field(default_factory=list)


@dataclass
class ChainConfig:
    name: str
    stages: list[StageConfig]
    seed: int = 0
    output_dir: str = "runs"
    overrides: list[str] = field(default_factory=list)
    recipe: str | None = None  # every stage's recipe, when no stage names its own


def _validate_chain(cfg: ChainConfig) -> None:
    if problem := run_name_problem(cfg.name):
        raise ConfigError(f"name: {problem}")
    if not cfg.stages:
        raise ConfigError("stages: a chain needs at least one stage")
    seen: set[str] = set()
    for i, stage in enumerate(cfg.stages):
        if problem := run_name_problem(stage.name):
            raise ConfigError(f"stages[{i}].name: {problem}")
        if stage.name in seen:
            raise ConfigError(f"stages[{i}].name: {stage.name!r} is used twice")
        seen.add(stage.name)
        if stage.recipe is None and cfg.recipe is None:
            raise ConfigError(f"stages[{i}].recipe: missing; name one here or one for every stage (recipe:)")
        if stage.recipe is not None and cfg.recipe is not None:
            raise ConfigError(
                f"stages[{i}].recipe: {stage.recipe!r} beside the chain's recipe {cfg.recipe!r}; a chain names one "
                "recipe for every stage or one per stage, not both"
            )


VALIDATORS[ChainConfig] = _validate_chain


def load_chain(path: str | Path, overrides: list[str] | None = None) -> ChainConfig:
    """Read and validate a chain file (dotted ``overrides`` apply to the chain file itself, e.g. ``seed=2``)."""
    path = Path(path)
    cfg = config_from_dict(read_recipe(path, overrides), ChainConfig)
    for i, stage in enumerate(cfg.stages):
        _stage_recipe(path, stage, i, cfg.recipe)  # every recipe exists and stays in the folder before anything trains
    return cfg


def _stage_recipe(chain_path: Path, stage: StageConfig, index: int, default: str | None) -> Path:
    folder = chain_path.resolve().parent
    name, where = (stage.recipe, f"stages[{index}].recipe") if stage.recipe is not None else (default, "recipe")
    recipe = (folder / name).resolve()
    if not recipe.is_relative_to(folder):
        raise ConfigError(f"{where}: {name!r} leaves the chain file's folder {folder}")
    if not recipe.is_file():
        raise ConfigError(f"{where}: no such recipe file: {recipe}")
    return recipe


def _finished(run_dir: Path) -> dict | None:
    """The stage's summary when it finished (summary.json written after its newest checkpoint), else None."""
    summary = run_dir / "summary.json"
    latest = run_dir / "checkpoints" / "latest"
    if not summary.is_file() or not latest.is_file() or summary.stat().st_mtime < latest.stat().st_mtime:
        return None
    return json.loads(summary.read_text())


CHAIN_KEYS = frozenset(f.name for f in fields(ChainConfig))


def split_overrides(overrides: list[str] | None) -> tuple[list[str], list[str]]:
    """``(chain's, stages')``: an override whose first key is a chain-file field (``seed=1``, ``output_dir=...``)
    edits the chain file; any other (``run.total_frames=2048``) goes to every stage, after the stage's own."""
    chain, stages = [], []
    for item in overrides or []:
        (chain if item.split("=", 1)[0].split(".", 1)[0].strip() in CHAIN_KEYS else stages).append(item)
    return chain, stages


def is_chain(path: str | Path) -> bool:
    """Whether a recipe path names a chain file: its name ends in :data:`CHAIN_SUFFIX` (``.chain.yaml``)."""
    return Path(path).name.endswith(CHAIN_SUFFIX)


def _stage_plans(path: Path, cfg: ChainConfig, root: Path, stage_overrides: list[str]) -> list[tuple]:
    """Per stage: (stage, recipe, run dir, overrides without run.init_from)."""
    plans = []
    for i, stage in enumerate(cfg.stages):
        given = [*cfg.overrides, *stage.overrides, *stage_overrides, f"run.seed={cfg.seed}"]
        plans.append((stage, _stage_recipe(path, stage, i, cfg.recipe), root / stage.name, given))
    return plans


@dataclass
class ChainPlan:
    """What a suite needs of a chain before it trains: its stage names in order, the last stage's env id (None when
    its config has none), the sum of the stages' ``run.total_frames`` (None when one is unknown) and the last
    stage's config."""

    stages: list[str]
    env: str | None
    total_frames: int | None
    last_config: Any = None


def plan_chain(path: str | Path, overrides: list[str] | None = None) -> ChainPlan:
    """Load the chain and every stage's config with ``overrides`` as :func:`run_chain` splits them; a
    FreamerError (ConfigError naming the stage) when the chain or a stage does not load."""
    path = Path(path)
    chain_overrides, stage_overrides = split_overrides(overrides)
    cfg = load_chain(path, chain_overrides)
    budgets: list[int | None] = []
    env = None
    for i, (stage, recipe, _, given) in enumerate(_stage_plans(path, cfg, Path(), stage_overrides)):
        try:
            _, stage_cfg = load_recipe(recipe, given)
        except ConfigError as err:
            raise ConfigError(f"stages[{i}] ({stage.name}): {err}") from None
        budgets.append(getattr(getattr(stage_cfg, "run", None), "total_frames", None))
        env = getattr(getattr(stage_cfg, "env", None), "id", None)
    total = None if any(b is None for b in budgets) else sum(budgets)  # type: ignore[arg-type]
    return ChainPlan([s.name for s in cfg.stages], env if isinstance(env, str) else None, total, stage_cfg)


def run_chain(
    path: str | Path,
    overrides: list[str] | None = None,
    *,
    stage_overrides: list[str] | None = None,
    root: str | Path | None = None,
    progress_bar: bool = True,
) -> list[dict[str, Any]]:
    """Train every stage in order (resumable); returns one row per stage and writes the chain summary.

    ``overrides`` are split by :func:`split_overrides`: chain-file fields (``seed=1``) edit the chain file, the
    others (``run.total_frames=2048``) go to every stage after its own, as ``stage_overrides`` do. ``root``: the
    chain's folder (stage ``s`` in ``<root>/<s>``; default ``<output_dir>/<name>-s<seed>``). ``progress_bar=False``:
    log lines only, no bar even on a terminal (a suite's worker). The output folder is created and checked before
    the first stage trains."""
    path = Path(path)
    overrides, given_to_stages = split_overrides(overrides)
    stage_overrides = [*given_to_stages, *(stage_overrides or [])]
    cfg = load_chain(path, overrides)
    root = Path(root) if root is not None else Path(cfg.output_dir) / f"{cfg.name}-s{cfg.seed}"
    root = prepare_output_folder(root, "output_dir")
    # (stage, recipe, run dir, overrides without run.init_from, its summary when finished)
    plans = [(*plan, _finished(plan[2])) for plan in _stage_plans(path, cfg, root, stage_overrides)]
    todo = [i for i, plan in enumerate(plans) if plan[4] is None]
    weights = [_stage_frames(plans[i][1], plans[i][3]) for i in todo]
    progress = OverallProgress(f"chain {cfg.name}", weights, item="stages") if progress_bar else None
    rows: list[dict[str, Any]] = []
    total = 0
    try:
        for i, (stage, recipe, run_dir, given, summary) in enumerate(plans):
            if i:
                given = [*given, f"run.init_from={plans[i - 1][2]}"]
            if summary is None:
                name, stage_cfg = load_recipe(recipe, given)
                logger.info("chain %s: stage %d/%d %s (%s)", cfg.name, i + 1, len(plans), stage.name, recipe.name)
                summary = get_trainer(name).train(stage_cfg, run_dir, resume=True)
                if progress is not None:
                    progress.advance(todo.index(i), f"stage {stage.name} done: {int(summary['frames']):,} frames")
            else:
                _check_finished_stage(run_dir, recipe, given, f"stages[{i}] ({stage.name})")
                logger.info("chain %s: stage %s already finished, read back", cfg.name, stage.name)
            rows.append(_stage_row(stage.name, summary, total, run_dir))
            total += int(summary["frames"])
    finally:
        if progress is not None:
            progress.close()
    _write_summary(root, cfg, rows)
    return rows


def _check_finished_stage(run_dir: Path, recipe: Path, given: list[str], where: str) -> None:
    """ConfigError when a finished stage was trained with other weights' sections than this chain asks for (e.g. the
    same chain rerun with ``recipe=`` another agent into the same folder), instead of reading its summary back."""
    name, stage_cfg = load_recipe(recipe, given)
    saved_file = run_dir / "config.yaml"
    saved = yaml.safe_load(saved_file.read_text()) if saved_file.is_file() else None
    if not isinstance(saved, dict):
        raise ConfigError(f"{where}: {saved_file} is missing or unreadable; cannot tell what {run_dir} trained")
    defaults = config_to_dict(type(stage_cfg)())  # fields a later release added were at their defaults then
    diffs = structural_differences(saved, config_to_dict(stage_cfg), get_trainer(name).structural, defaults)
    if diffs:
        raise ConfigError(
            f"{where}: {run_dir} finished with another config ({'; '.join(diffs[:3])}); "
            "give this chain another output_dir"
        )


def _stage_row(name: str, summary: dict[str, Any], frames_before: int, run_dir: Path) -> dict[str, Any]:
    """One stage of ``chain_summary.json``: its own frames to 80% / 95% (the exact-episode definition of
    :class:`~freamer_rl.run.metrics.EpisodeStats`) and the same counted across the chain (the earlier stages' frames
    added)."""
    row = {
        "stage": name,
        "env": summary.get("env"),
        "frames": summary["frames"],
        "chain_frames": frames_before + int(summary["frames"]),
        "episodes": summary.get("episodes"),
        "final_success_rate": summary.get("final_success_rate"),
    }
    for level in SUCCESS_LEVELS:
        key = f"frames_to_{round(100 * level)}"
        row[key] = summary.get(key)
        row[f"chain_{key}"] = None if row[key] is None else frames_before + int(row[key])
    row["run_dir"] = str(run_dir)
    return row


def _stage_frames(recipe: Path, given: list[str]) -> int | None:
    """The stage's frame budget for the overall progress; None when its config does not load (the stage's own load
    then names the error)."""
    try:
        _, stage_cfg = load_recipe(recipe, given)
    except FreamerError:
        return None
    return getattr(getattr(stage_cfg, "run", None), "total_frames", None)


def _write_summary(root: Path, cfg: ChainConfig, rows: list[dict[str, Any]]) -> None:
    root.mkdir(parents=True, exist_ok=True)
    payload = {"chain": cfg.name, "seed": cfg.seed, "stages": rows}
    (root / "chain_summary.json").write_text(json.dumps(payload, indent=2))
    lines = [
        f"# Chain {cfg.name} (seed {cfg.seed})",
        "",
        "Frames to X%: the exact episode (and its frame) at which the trailing 100-episode success rate first reached X,"
        " within the stage and (in the chain) counted from the chain's start.",
        "",
        "| stage | env | frames | frames in the chain | episodes | final success | frames to 80% | frames to 95% "
        "| frames to 80% in the chain | frames to 95% in the chain |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        success = "" if r["final_success_rate"] is None else f"{r['final_success_rate']:.3f}"
        to = [
            "" if r.get(k) is None else f"{r[k]:,}"
            for k in ("frames_to_80", "frames_to_95", "chain_frames_to_80", "chain_frames_to_95")
        ]
        lines.append(
            f"| {r['stage']} | {r['env']} | {r['frames']:,} | {r['chain_frames']:,} | {r['episodes']} | "
            f"{success} | " + " | ".join(to) + " |"
        )
    (root / "chain_summary.md").write_text("\n".join(lines) + "\n")
