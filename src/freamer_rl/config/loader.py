"""The one config loader: YAML recipes, dotted command-line overrides, typed dataclass schemas.

A recipe is a YAML mapping whose keys mirror a schema dataclass (a subclass of
:class:`freamer_rl.config.sections.BaseConfig`). Loading validates every key and type and raises
:class:`~freamer_rl.errors.ConfigError` naming the dotted field, e.g. ``optim.lr: expected float, got str 'fast'``;
then every number against the schema's ``RANGES`` table and the schema's cross-field validator (:data:`VALIDATORS`).
A key an earlier release used is refused with the key that replaced it (the schema's ``RENAMED`` table).

    from freamer_rl.trainers.minigrid_ppo import FreamerConfig
    cfg = load_config("recipes/minigrid_multiroom_n2s4.yaml", ["optim.lr=3e-4", "run.seed=1"], schema=FreamerConfig)

This module knows no trainer: which schema a recipe's ``trainer:`` key names is the trainer registry's business
(:func:`freamer_rl.trainers.registry.load_recipe`).
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from freamer_rl.config.checks import check_recipe_file, load_yaml
from freamer_rl.errors import ConfigError

# --------------------------------------------------------------------------------------------------------------
# Conversion and validation
# --------------------------------------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, path: str) -> Any:
    """Convert a YAML value to ``tp`` or raise ConfigError naming ``path``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, path)
            except ConfigError:
                continue
        raise ConfigError(f"{path}: expected {_type_name(tp)}, got {type(value).__name__} {value!r}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping of {tp.__name__} fields, got {type(value).__name__}")
        return _build(tp, value, path)
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {type(value).__name__} {value!r}")
        return [_coerce(v, item_tp, f"{path}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        key_tp, val_tp = typing.get_args(tp)
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping, got {type(value).__name__} {value!r}")
        return {_coerce(k, key_tp, path): _coerce(v, val_tp, f"{path}.{k}") for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{path}: expected bool (true/false), got {type(value).__name__} {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{path}: expected int, got {type(value).__name__} {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # YAML 1.1 reads "1e-4" as a string
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(f"{path}: expected float, got {type(value).__name__} {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{path}: expected str, got {type(value).__name__} {value!r}")
    if tp is typing.Any:  # plain YAML data, checked by whoever reads it (e.g. an env adapter's options)
        return _plain_data(value, path)
    raise ConfigError(f"{path}: unsupported field type {tp}")


def _plain_data(value: Any, path: str) -> Any:
    """``value`` when it is YAML data (None, bool, number, str, and lists / string-keyed mappings of them)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_plain_data(v, f"{path}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return {k: _plain_data(v, f"{path}.{k}") for k, v in value.items()}
    raise ConfigError(f"{path}: expected YAML data (numbers, strings, lists, mappings), got {type(value).__name__}")


def _build(cls: type, data: dict, prefix: str = "") -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in names:
            where = f"{prefix}.{key}" if prefix else key
            raise ConfigError(f"unknown key '{where}' (known keys here: {', '.join(sorted(names))})")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in data:
            kwargs[f.name] = _coerce(data[f.name], hints[f.name], f"{prefix}.{f.name}" if prefix else f.name)
    return cls(**kwargs)


def merge_dicts(base: dict, update: dict) -> dict:
    """``update`` merged into ``base`` section by section (``gate_init``, a per-modality table, is replaced whole)."""
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict) and key != "gate_init":
            out[key] = merge_dicts(out[key], value)
        else:
            out[key] = value
    return out


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"optim.lr=3e-4"`` -> (["ppo", "lr"], 3e-4). The value is parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"override '{text}' must look like dotted.key=value")
    key, raw = text.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"override '{text}' has an empty key")
    try:
        value = load_yaml(raw) if raw.strip() else None
    except yaml.YAMLError as err:
        raise ConfigError(f"override '{text}': value is not valid YAML ({err.problem})") from None
    return parts, value


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    data = dict(data)
    for text in overrides:
        parts, value = parse_override(text)
        node = data
        for part in parts[:-1]:
            child = node.get(part)
            if child is None:
                child = {}
            elif not isinstance(child, dict):
                raise ConfigError(f"override '{text}': '{part}' is not a section")
            node[part] = dict(child)
            node = node[part]
        node[parts[-1]] = value
    return data


#: The recipe's top-level key naming its trainer (an entry of :data:`freamer_rl.trainers.registry.TRAINERS`).
TRAINER_KEY = "trainer"
#: The trainer of a recipe without a ``trainer:`` key (every MiniGrid / gym recipe written before the key existed).
DEFAULT_TRAINER = "minigrid_ppo"
#: Cross-field validator per schema dataclass, run after the typed build; a domain's config module registers its own
#: (the health one: ``VALIDATORS[HealthConfig] = validate_health_config``).
VALIDATORS: dict[type, Callable[[Any], None]] = {}


def config_from_dict(data: dict | None, schema: type, *, migrate: bool = False) -> Any:
    """Build and validate a ``schema`` instance from a plain mapping.

    ``migrate=True`` is for configs the library wrote itself (a checkpoint's ``config`` entry): keys an earlier release
    used are moved to their new names (the schema's ``RENAMED`` table) and top-level sections the schema no longer has
    are dropped (the baselines' schemas once carried FreamerV1's), instead of being refused as in a recipe.

    Unknown keys and wrong types raise :class:`ConfigError` naming the dotted field; then the schema's registered
    validator (:data:`VALIDATORS`) runs its cross-field checks. A top-level ``trainer:`` entry is not a field of
    any schema and is dropped here (:func:`split_trainer` reads it).
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"a recipe must be a YAML mapping, got {type(data).__name__}")
    data = {k: v for k, v in data.items() if k != TRAINER_KEY}
    if migrate:
        data = migrate_config(data, schema)
    _refuse_renamed(data, getattr(schema, "RENAMED", {}))
    cfg = _build(schema, data)
    if schema not in VALIDATORS:
        raise ConfigError(f"no validator registered for config schema {schema.__name__} (config.VALIDATORS)")
    VALIDATORS[schema](cfg)
    return cfg


def read_recipe(path: str | Path | None, overrides: list[str] | None = None) -> dict:
    """The raw mapping of a YAML recipe (empty when ``path`` is None) with dotted ``overrides`` applied."""
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"recipe file not found: {path}")
        check_recipe_file(path)  # duplicate keys, an empty file
        try:
            data = load_yaml(path.read_text()) or {}
        except yaml.YAMLError as err:
            mark = getattr(err, "problem_mark", None)
            where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
            raise ConfigError(f"{where}: invalid YAML ({getattr(err, 'problem', err)})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: a recipe must be a YAML mapping")
    return apply_overrides(data, overrides or [])


def split_trainer(data: dict, source: str = "recipe") -> tuple[str, dict]:
    """``(trainer name, the rest of the mapping)``; the name defaults to :data:`DEFAULT_TRAINER`."""
    trainer = data.get(TRAINER_KEY, DEFAULT_TRAINER)
    if not isinstance(trainer, str):
        raise ConfigError(f"{source}: {TRAINER_KEY}: expected a trainer name (str), got {type(trainer).__name__}")
    return trainer, {k: v for k, v in data.items() if k != TRAINER_KEY}


def load_config(path: str | Path | None, overrides: list[str] | None = None, *, schema: type) -> Any:
    """Load a YAML recipe (or the schema's defaults when ``path`` is None), apply dotted overrides, build and
    validate as ``schema``. A recipe naming another trainer's schema is refused by the registry's
    :func:`~freamer_rl.trainers.registry.load_recipe`, which picks the schema from the recipe."""
    source = str(path) if path is not None else "defaults"
    _, data = split_trainer(read_recipe(path, overrides), source)
    return config_from_dict(data, schema)


def migrate_config(data: dict, schema: type) -> dict:
    """A saved config mapping in the current layout of ``schema``: every old dotted key of ``schema.RENAMED`` moved
    to its new key (unless that is set already), then sections ``schema`` does not have dropped."""
    data = copy.deepcopy(data)
    for old, new in getattr(schema, "RENAMED", {}).items():
        *path, last = old.split(".")
        node = data
        for part in path:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or last not in node:
            continue
        value = node.pop(last)
        *new_path, new_last = new.split(".")
        target = data
        for part in new_path:
            target = target.setdefault(part, {})
        target.setdefault(new_last, value)
    fields = {f.name for f in dataclasses.fields(schema)}
    return {k: v for k, v in data.items() if k in fields}


def _refuse_renamed(data: dict, renamed: dict[str, str]) -> None:
    """ConfigError naming the new key for every old dotted key of ``renamed`` that ``data`` still uses."""
    for old, new in renamed.items():
        node: Any = data
        for part in old.split("."):
            if not isinstance(node, dict) or part not in node:
                break
            node = node[part]
        else:
            raise ConfigError(f"{old}: this key was renamed; use {new} (e.g. {new}={node})")


def config_to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)
