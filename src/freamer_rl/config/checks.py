"""Value checks of :func:`freamer_rl.config.loader.validate` and the recipe-file checks of ``read_recipe``.

Every check raises one :class:`~freamer_rl.config.loader.ConfigError` line naming the dotted field, the value and what is
allowed, e.g. ``ppo.gamma: got 5.0, expected a finite number in (0, 1]``. Numbers are checked generically: every int
and float a config holds (dataclasses and dict values walked) against :data:`RANGES`, where ints default to >= 1 and
floats to any finite value.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import os
import re
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import Any

import torch
import yaml

from freamer_rl.errors import ConfigError

__all__ = [
    "Range",
    "POSITIVE",
    "NON_NEGATIVE",
    "UNIT_INTERVAL",
    "check_recipe_file",
    "check_device_name",
    "resolve_device",
    "config_numbers",
    "check_numbers",
    "check_collector",
    "check_ray_backend",
    "check_logging",
    "run_name_problem",
]


class RecipeLoader(yaml.SafeLoader):
    """``yaml.safe_load`` with YAML 1.2 booleans: only ``true`` / ``false`` are bools, so ``placement: off`` or
    ``yes`` stay the strings the recipe wrote (YAML 1.1, PyYAML's default, reads on/off/yes/no as bools)."""


RecipeLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
RecipeLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


def load_yaml(text: str) -> Any:
    """A recipe's or an override's YAML with :class:`RecipeLoader` (safe; YAML 1.2 booleans)."""
    return yaml.load(text, Loader=RecipeLoader)  # noqa: S506 (a SafeLoader subclass)


class _DuplicateKey(Exception):
    def __init__(self, key: Any, line: int, first_line: int) -> None:
        super().__init__(key)
        self.key, self.line, self.first_line = key, line, first_line


class _UniqueKeyLoader(RecipeLoader):
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
            f"{path}:{dup.line}: duplicate key '{dup.key}' (first given at line {dup.first_line}); give each key once"
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
            raise ConfigError(
                f"run.device: got {name!r}, but only {count} CUDA device(s) are visible (cuda:0 to cuda:{count - 1})"
            )
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


Range = tuple[Callable[[Any], bool], str]


def POSITIVE(v):  # noqa: N802 (a predicate used as a constant in range tables)
    return v > 0


def NON_NEGATIVE(v):  # noqa: N802
    return v >= 0


def UNIT_INTERVAL(v):  # noqa: N802 ((0, 1])
    return 0 < v <= 1


def size_range(limit: int) -> Range:
    """A size bound: an integer in [1, limit]; far larger sizes only end in an allocation failure."""
    return (lambda v: 1 <= v <= limit, f"in [1, {limit:,}]")


#: widths, layer counts, batch and sequence sizes: generous for a workstation, refused before anything is allocated
WIDTH_LIMIT, LAYERS_LIMIT, BATCH_LIMIT = 16_384, 64, 65_536

_INT_DEFAULT_RANGE: Range = (lambda v: v >= 1, ">= 1")
_FLOAT_DEFAULT_RANGE: Range = (lambda v: True, "")


def check_numbers(cfg: Any, ranges: dict[str, Range] | None = None) -> None:
    """Every number field of a config dataclass against ``ranges`` (default: the schema's ``RANGES`` table); where
    the table says nothing, ints must be >= 1 and floats finite. The one range mechanism of every schema."""
    ranges = getattr(type(cfg), "RANGES", {}) if ranges is None else ranges
    for name, value in config_numbers(cfg):
        is_float = isinstance(value, float)
        ok, allowed = ranges.get(name, _FLOAT_DEFAULT_RANGE if is_float else _INT_DEFAULT_RANGE)
        if is_float and (not math.isfinite(value) or not ok(value)):
            raise ConfigError(f"{name}: got {value!r}, expected a finite number {allowed}".rstrip())
        if not is_float and not ok(value):
            raise ConfigError(f"{name}: got {value!r}, expected an integer {allowed}")


def check_collector(c: Any) -> None:
    """``collector.backend`` and the Ray fields (whether ray is installed is checked when a run starts)."""
    if c.backend not in ("local", "ray"):
        raise ConfigError(f"collector.backend: expected local or ray, got {c.backend!r}")
    if c.ray_address is not None and c.ray_num_cpus is not None:
        raise ConfigError(
            f"collector.ray_num_cpus: got {c.ray_num_cpus}, but collector.ray_address="
            f"{c.ray_address!r} joins a running Ray cluster, whose CPUs are set by `ray start "
            "--num-cpus`; leave ray_num_cpus unset"
        )
    if c.ray_address is not None and not c.ray_address.strip():
        raise ConfigError(
            "collector.ray_address: got an empty string; give auto or host:6379, "
            "or leave it unset to start a local Ray instance"
        )


def check_ray_backend(section: Any, policy: Any) -> None:
    """``collector.backend: ray`` when a run starts: ray installed, the policy on the CPU (the actors run it there).

    Checked here rather than while loading, so that a run trained through Ray still loads and evaluates where ray
    is not installed.
    """
    if importlib.util.find_spec("ray") is None:
        raise ConfigError(
            "collector.backend: got 'ray', but ray is not installed; pip install -c constraints.txt "
            '-e ".[ray]" (or collector.backend=local)'
        )
    devices = {p.device.type for p in policy.parameters()}
    if devices - {"cpu"}:
        raise ConfigError(
            f"collector.backend: 'ray' runs the policy in CPU actors, but it is on {sorted(devices)}; "
            "use run.device=cpu with the ray backend"
        )


def check_logging(section: Any) -> None:
    """``logging.backend``: one of TorchRL's loggers the project sets up."""
    if section.backend not in ("csv", "wandb", "tensorboard"):
        raise ConfigError(f"logging.backend: expected csv, wandb or tensorboard, got {section.backend!r}")


def run_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a run directory name directly under the output folder; None when it can.

    Refused: path separators (``/``, ``\\``), ``..`` anywhere, absolute paths, ``.``, control characters (a newline
    in a folder name would break the one-line messages and CSV files that mention it).
    """
    if name in ("", "."):
        return "must name a folder, got an empty name or '.'"
    if any(sep in name for sep in ("/", "\\", os.sep, os.altsep or "/")) or Path(name).is_absolute():
        return f"must be a plain folder name without path separators, got {name!r}"
    if ".." in name:
        return f"must not contain '..', got {name!r}"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return f"must not contain control characters, got {name!r}"
    return None
