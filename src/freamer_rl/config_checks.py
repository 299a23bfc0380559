"""Value checks of :func:`freamer_rl.config.validate` and the recipe-file checks of ``read_recipe``.

Every check raises one :class:`~freamer_rl.config.ConfigError` line naming the dotted field, the value and what is
allowed, e.g. ``ppo.gamma: got 5.0, expected a finite number in (0, 1]``. Numbers are checked generically: every int
and float a config holds (dataclasses and dict values walked) against :data:`RANGES`, where ints default to >= 1 and
floats to any finite value.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from freamer_rl.config import ConfigError, FreamerConfig

if TYPE_CHECKING:
    import torch

__all__ = ["RANGES", "check_recipe_file", "check_device_name", "resolve_device", "config_numbers", "check_numbers",
           "check_model_shapes", "check_names", "check_ray_backend"]  # fmt: skip


class _DuplicateKey(Exception):
    def __init__(self, key: Any, line: int, first_line: int) -> None:
        super().__init__(key)
        self.key, self.line, self.first_line = key, line, first_line


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.safe_load`` that refuses a key given twice in one mapping (PyYAML silently keeps the last one)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *base' merges; overriding a merged key is fine
                continue
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, Hashable):  # a complex key (a list): safe_load itself refuses it
                continue
            line = key_node.start_mark.line + 1
            if key in seen:
                raise _DuplicateKey(key, line, seen[key])
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


def check_recipe_file(path: Path) -> None:
    """ConfigError for what ``safe_load`` accepts silently: a key given twice, a file without any setting.

    Invalid YAML is left to the caller (``read_recipe``), which reports it with its line.
    """
    try:
        data = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
    except _DuplicateKey as dup:
        raise ConfigError(
            f"{path}:{dup.line}: duplicate key '{dup.key}' (first given at line {dup.first_line}); "
            f"give each key once"
        ) from None
    except yaml.YAMLError:
        return
    if data is None:
        raise ConfigError(f"{path}: the recipe file is empty (no settings); give at least one key, e.g. env.id")


#: ``run.device`` values: the CPU or a CUDA device (checked for visibility when a run starts, see resolve_device).
_DEVICE_PATTERN = r"cpu|cuda(:[0-9]+)?"


def check_device_name(name: str) -> None:
    """``run.device`` spelled cpu, cuda or cuda:N (whether such a device exists is :func:`resolve_device`'s job)."""
    if not re.fullmatch(_DEVICE_PATTERN, name):
        raise ConfigError(f"run.device: got {name!r}, expected cpu, cuda or cuda:N")


def resolve_device(name: str) -> torch.device:
    """``run.device`` -> ``torch.device``; ConfigError when it names no visible device.

    Checked when a run starts rather than while loading, so that a config trained on a GPU still loads (evaluation,
    parameter tables) on a CPU-only machine.
    """
    import torch

    check_device_name(name)
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            build = "" if torch.version.cuda else "; this torch is a CPU-only build"
            raise ConfigError(
                f"run.device: got {name!r}, but no CUDA device is visible (torch.cuda.is_available() is False"
                f"{build}); use run.device=cpu"
            )
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise ConfigError(f"run.device: got {name!r}, but only {count} CUDA device(s) are visible "
                              f"(cuda:0 to cuda:{count - 1})")  # fmt: skip
    return device


def config_numbers(obj: Any, prefix: str = "") -> Iterator[tuple[str, int | float]]:
    """``(dotted name, value)`` of every int and float a config holds, dataclasses and dict values walked."""
    items = (
        ((f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj))
        if dataclasses.is_dataclass(obj)
        else obj.items()
    )
    for key, value in items:
        name = f"{prefix}{key}"
        if dataclasses.is_dataclass(value) or isinstance(value, dict):
            yield from config_numbers(value, name + ".")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            yield name, value


def _positive(v):
    return v > 0


def _non_negative(v):
    return v >= 0


def _unit_interval(v):  # (0, 1]
    return 0 < v <= 1


#: Allowed range per number field: (predicate, range text). Every other int must be >= 1 and every other float
#: finite; a float must be finite everywhere.
RANGES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "env.reward_history": (_non_negative, ">= 0 (0: no reward history)"),
    "run.seed": (lambda v: 0 <= v < 2**32, "in [0, 2**32 - 1]"),
    "run.stop_at_success": (_unit_interval, "in (0, 1]"),
    "ppo.lr": (_positive, "> 0"),
    "ppo.adam_eps": (_positive, "> 0"),
    "ppo.max_grad_norm": (_positive, "> 0"),
    "ppo.clip_epsilon": (_positive, "> 0"),
    "ppo.gamma": (_unit_interval, "in (0, 1]"),
    "ppo.gae_lambda": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "ppo.entropy_coeff": (_non_negative, ">= 0"),
    "ppo.critic_coeff": (_non_negative, ">= 0"),
    "ppo.lambda_fm": (_non_negative, ">= 0"),
    "ppo.lambda_cl": (_non_negative, ">= 0"),
    "ppo.lambda_smooth": (_non_negative, ">= 0"),
    "model.flow.noise_std": (_non_negative, ">= 0"),
    "model.flow.adaptive_tau": (_positive, "> 0"),
    "shaping.language.weight": (_non_negative, ">= 0"),
    "shaping.language.r_scale": (_non_negative, ">= 0"),
    "shaping.language.goal_bonus": (_non_negative, ">= 0"),
    "shaping.language.proximity_bonus": (_non_negative, ">= 0"),
    "shaping.vision_language": (_non_negative, ">= 0"),
    "shaping.curiosity": (_non_negative, ">= 0"),
    "shaping.novelty.weight": (_non_negative, ">= 0"),
    "shaping.novelty.alpha": (_non_negative, ">= 0"),
    "shaping.time_penalty": (_non_negative, ">= 0"),
    "success_buffer.mix": (lambda v: 0 < v < 1, "in (0, 1)"),
    "success_buffer.rho_clip": (_positive, "> 0"),
    "ogm.alpha": (_positive, "> 0"),
    "ogm.lr_scale": (_positive, "> 0"),
    "ogm.ema": (lambda v: 0 <= v < 1, "in [0, 1)"),
    "collector.ray_collector_cpus": (_positive, "> 0"),
}
_INT_DEFAULT_RANGE = (lambda v: v >= 1, ">= 1")
_FLOAT_DEFAULT_RANGE = (lambda v: True, "")


def check_numbers(cfg: Any, ranges: dict[str, tuple[Callable[[Any], bool], str]] | None = None) -> None:
    """Every number field of a config dataclass against ``ranges`` (default :data:`RANGES`); where the table says
    nothing, ints must be >= 1 and floats finite. Another schema (e.g. the health config) passes its own table."""
    ranges = RANGES if ranges is None else ranges
    for name, value in config_numbers(cfg):
        is_float = isinstance(value, float)
        ok, allowed = ranges.get(name, _FLOAT_DEFAULT_RANGE if is_float else _INT_DEFAULT_RANGE)
        if is_float and (not math.isfinite(value) or not ok(value)):
            raise ConfigError(f"{name}: got {value!r}, expected a finite number {allowed}".rstrip())
        if not is_float and not ok(value):
            raise ConfigError(f"{name}: got {value!r}, expected an integer {allowed}")


#: Cells of the MiniGrid symbolic view (7 x 7) the state encoder's FNO runs along.
_MINIGRID_VIEW_CELLS = 49


def check_model_shapes(cfg: FreamerConfig) -> None:
    """Sizes that must fit each other: attention heads divide the embedding, Fourier modes fit the signal."""
    m = cfg.model
    mods, d = set(m.modalities), m.embed_dim
    heads = [("model.language.heads", m.language.heads)] if "language" in mods else []
    if {"vision", "language"} <= mods:  # cross-modal attention between vision and language slots
        heads.append(("model.cross_modal_heads", m.cross_modal_heads))
    for name, h in heads:
        if d % h:
            raise ConfigError(f"model.embed_dim: got {d}, must be divisible by {name} ({h})")
    if m.fno.modes > d // 2 + 1:
        raise ConfigError(f"model.fno.modes: got {m.fno.modes}, must be <= model.embed_dim // 2 + 1 = {d // 2 + 1} "
                          f"(the fuser's rfft runs along the {d} embedding entries)")  # fmt: skip
    cells = _MINIGRID_VIEW_CELLS
    if "state" in mods and "state" not in m.observation_keys and m.state.modes > cells // 2 + 1:
        raise ConfigError(f"model.state.modes: got {m.state.modes}, must be <= {cells // 2 + 1} (the rfft modes "
                          f"of the {cells} cells of the 7x7 view)")  # fmt: skip
    if "reward" in mods and "reward" not in m.observation_keys and cfg.env.reward_history == 0:
        raise ConfigError("env.reward_history: got 0 (no reward history), but model.modalities includes reward; "
                          "use env.reward_history >= 1")  # fmt: skip


def check_names(cfg: FreamerConfig) -> None:
    """Names and choices: run name and device, modalities and their keys, backbone, logging backend."""
    from freamer_rl.modalities import MODALITIES
    from freamer_rl.rundir import run_name_problem

    # the run directory is run.output_dir/run.name: a name with separators or '..' would write elsewhere
    if cfg.run.name and (problem := run_name_problem(cfg.run.name)):
        raise ConfigError(f"run.name: {problem}")
    check_device_name(cfg.run.device)
    mods = cfg.model.modalities
    if not mods:
        raise ConfigError("model.modalities: at least one modality is required")
    for m in mods:
        if m not in MODALITIES:
            raise ConfigError(f"model.modalities: unknown modality '{m}' (known: {', '.join(MODALITIES)})")
    for m, keys in cfg.model.observation_keys.items():
        if m not in mods:
            raise ConfigError(f"model.observation_keys: '{m}' is not one of model.modalities {mods}")
        if not keys:
            raise ConfigError(f"model.observation_keys.{m}: give at least one observation key")
    if len(set(mods)) != len(mods):
        raise ConfigError(f"model.modalities: duplicates in {mods}")
    for m in cfg.model.freeze_encoders:
        if m not in mods:
            raise ConfigError(f"model.freeze_encoders: '{m}' is not one of model.modalities {mods}")
    if cfg.model.vision.backbone not in ("cnn", "clip"):
        raise ConfigError(f"model.vision.backbone: expected 'cnn' or 'clip', got {cfg.model.vision.backbone!r}")
    for m in cfg.model.flow.gate_init:
        if m not in MODALITIES:
            raise ConfigError(f"model.flow.gate_init: unknown modality '{m}'")
    _check_machinery_names(cfg)
    _check_collector(cfg.collector)
    if cfg.logging.backend not in ("csv", "wandb", "tensorboard"):
        raise ConfigError(f"logging.backend: expected csv, wandb or tensorboard, got {cfg.logging.backend!r}")


#: Step counts a refiner may choose from (App. G.4 lists 1, 2, 3, 5, 7, 10).
_MAX_ADAPTIVE_STEPS = 32


def _check_machinery_names(cfg: FreamerConfig) -> None:
    """Choices of the training machinery: parser kind, OGM-GE mode, adaptive step counts, hashed novelty keys."""
    lang = cfg.shaping.language
    if lang.parser not in ("regex", "llm"):
        raise ConfigError(f"shaping.language.parser: expected 'regex' or 'llm', got {lang.parser!r}")
    if lang.weight and lang.parser == "llm" and not lang.llm_path:
        raise ConfigError("shaping.language.llm_path: parser 'llm' needs the local directory of the model weights "
                          "(e.g. Qwen2.5-1.5B-Instruct), or use shaping.language.parser=regex")  # fmt: skip
    if cfg.ogm.mode not in ("none", "A", "B"):
        raise ConfigError(f"ogm.mode: expected none, A or B, got {cfg.ogm.mode!r}")
    steps = cfg.model.flow.adaptive_steps
    if any(not 1 <= s <= _MAX_ADAPTIVE_STEPS for s in steps) or len(set(steps)) != len(steps):
        raise ConfigError(f"model.flow.adaptive_steps: got {steps}, expected distinct step counts in "
                          f"[1, {_MAX_ADAPTIVE_STEPS}] (paper: [1, 2, 3, 5, 7, 10]; [] = fixed model.flow.steps)")
    if len(steps) == 1:
        raise ConfigError(f"model.flow.adaptive_steps: got {steps}: give two or more choices, or set "
                          "model.flow.steps and leave adaptive_steps empty")  # fmt: skip
    if cfg.ogm.mode != "none" and not cfg.ppo.lambda_fm:
        raise ConfigError(f"ogm.mode: got {cfg.ogm.mode!r}, but OGM-GE is driven by the FM losses and ppo.lambda_fm "
                          "is 0; set ppo.lambda_fm > 0 or ogm.mode=none")  # fmt: skip
    mods = set(cfg.model.modalities)
    if cfg.shaping.vision_language and not ("language" in mods and mods & {"vision", "state"}):
        raise ConfigError(f"shaping.vision_language: got {cfg.shaping.vision_language}, but R_VL needs the language "
                          f"modality and vision or state in model.modalities {cfg.model.modalities}; set it to 0")
    if cfg.shaping.novelty.weight and not cfg.shaping.novelty.keys:
        raise ConfigError("shaping.novelty.keys: got [], give at least one observation entry to hash")


def _check_collector(c: Any) -> None:
    """``collector.backend`` and the Ray fields (whether ray is installed is checked when a run starts)."""
    if c.backend not in ("local", "ray"):
        raise ConfigError(f"collector.backend: expected local or ray, got {c.backend!r}")
    if c.ray_address is not None and c.ray_num_cpus is not None:
        raise ConfigError(f"collector.ray_num_cpus: got {c.ray_num_cpus}, but collector.ray_address="
                          f"{c.ray_address!r} joins a running Ray cluster, whose CPUs are set by `ray start "
                          "--num-cpus`; leave ray_num_cpus unset")  # fmt: skip
    if c.ray_address is not None and not c.ray_address.strip():
        raise ConfigError("collector.ray_address: got an empty string; give auto or host:6379, "
                          "or leave it unset to start a local Ray instance")  # fmt: skip


def check_ray_backend(section: Any, policy: Any) -> None:
    """``collector.backend: ray`` when a run starts: ray installed, the policy on the CPU (the actors run it there).

    Checked here rather than while loading, so that a run trained through Ray still loads and evaluates where ray
    is not installed.
    """
    import importlib.util

    if importlib.util.find_spec("ray") is None:
        raise ConfigError('collector.backend: got \'ray\', but ray is not installed; pip install -c constraints.txt '
                          '-e ".[ray]" (or collector.backend=local)')  # fmt: skip
    devices = {p.device.type for p in policy.parameters()}
    if devices - {"cpu"}:
        raise ConfigError(f"collector.backend: 'ray' runs the policy in CPU actors, but it is on {sorted(devices)}; "
                          "use run.device=cpu with the ray backend")  # fmt: skip
