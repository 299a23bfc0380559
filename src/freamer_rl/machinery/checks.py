"""Checks of the training machinery's sections; one ConfigError line naming the dotted field."""

from __future__ import annotations

from typing import Any

from freamer_rl.errors import ConfigError
from freamer_rl.machinery.config import LANGUAGE_DISTANCES

__all__ = ["check_machinery", "check_shaping", "privileged_information"]


def check_shaping(cfg: Any) -> None:
    """The ``shaping`` choices every trainer with that section shares: parser kind, its weights, novelty keys."""
    lang = cfg.shaping.language
    if lang.parser not in ("regex", "llm"):
        raise ConfigError(f"shaping.language.parser: expected 'regex' or 'llm', got {lang.parser!r}")
    if lang.distance not in LANGUAGE_DISTANCES:
        raise ConfigError(
            f"shaping.language.distance: expected one of {', '.join(LANGUAGE_DISTANCES)}, got {lang.distance!r}"
        )
    if lang.weight and lang.parser == "llm" and not lang.llm_path:
        raise ConfigError(
            "shaping.language.llm_path: parser 'llm' needs the local directory of the model weights "
            "(e.g. Qwen2.5-1.5B-Instruct), or use shaping.language.parser=regex"
        )
    if cfg.shaping.novelty.weight and not cfg.shaping.novelty.keys:
        raise ConfigError("shaping.novelty.keys: got [], give at least one observation entry to hash")


def privileged_information(cfg: Any) -> list[str]:
    """What of a run's config reads information the agent cannot observe, as ``"dotted.key=value"`` entries ([] when
    nothing does): ``shaping.language.distance=oracle`` with the language reward on (its b_prox is a BFS on the full
    MiniGrid map); ``model.flow.targets=paired`` (its refiners train on the clean copy of an observation the run
    itself corrupts, which no deployed sensor offers). A schema without those sections has none."""
    out = []
    lang = cfg.shaping.language if hasattr(cfg, "shaping") else None
    if lang is not None and lang.weight and lang.distance == "oracle":
        out.append("shaping.language.distance=oracle")
    flow = getattr(getattr(cfg, "model", None), "flow", None)
    if getattr(flow, "targets", "synthetic") == "paired":
        out.append("model.flow.targets=paired")
    return out


def check_machinery(cfg: Any) -> None:
    """Choices of FreamerV1's training machinery (``shaping``, ``ogm``) and what they need from the model: parser
    kind, OGM-GE mode, the modalities R_VL compares, hashed novelty keys."""
    check_shaping(cfg)
    if cfg.ogm.mode not in ("none", "A", "B"):
        raise ConfigError(f"ogm.mode: expected none, A or B, got {cfg.ogm.mode!r}")
    if cfg.ogm.mode != "none" and cfg.model.flow.placement != "pre":
        raise ConfigError(
            f"ogm.mode: got {cfg.ogm.mode!r}, but OGM-GE modulates one refiner per modality and "
            f"model.flow.placement is {cfg.model.flow.placement!r}; use placement pre or ogm.mode=none"
        )
    if cfg.ogm.mode != "none" and not cfg.aux.lambda_fm:
        raise ConfigError(
            f"ogm.mode: got {cfg.ogm.mode!r}, but OGM-GE is driven by the FM losses and aux.lambda_fm "
            "is 0; set aux.lambda_fm > 0 or ogm.mode=none"
        )
    mods = set(cfg.model.modalities)
    if cfg.shaping.vision_language and not ("language" in mods and mods & {"vision", "state"}):
        raise ConfigError(
            f"shaping.vision_language: got {cfg.shaping.vision_language}, but R_VL needs the language "
            f"modality and vision or state in model.modalities {cfg.model.modalities}; set it to 0"
        )
