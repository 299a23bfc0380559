"""Checks of FreamerV1's ``model`` section (names, choices, sizes that must fit each other); one ConfigError line
naming the dotted field."""

from __future__ import annotations

from typing import Any

from freamer_rl.errors import ConfigError
from freamer_rl.layers.dnc import WRITES
from freamer_rl.layers.encoders import VISION_POOLINGS
from freamer_rl.layers.flow_matching import RELIABILITY_MODES
from freamer_rl.model.action_prior import check_action_prior
from freamer_rl.model.factory import FUSIONS, PLACEMENTS
from freamer_rl.model.heads import CRITIC_INPUTS
from freamer_rl.model.modalities import MODALITIES

__all__ = ["check_model_names", "check_model_shapes"]

#: Step counts a refiner may choose from (App. G.4 lists 1, 2, 3, 5, 7, 10).
_MAX_ADAPTIVE_STEPS = 32

#: Cells of the MiniGrid symbolic view (7 x 7) the state encoder's FNO runs along.
_MINIGRID_VIEW_CELLS = 49


def check_model_shapes(cfg: Any) -> None:
    """Sizes that must fit each other: attention heads divide the embedding, Fourier modes fit the signal."""
    m = cfg.model
    mods, d = set(m.modalities), m.embed_dim
    heads = [("model.language.heads", m.language.heads)] if "language" in mods else []
    if {"vision", "language"} <= mods:  # cross-modal attention between vision and language slots
        heads.append(("model.cross_modal_heads", m.cross_modal_heads))
    for name, h in heads:
        if d % h:
            raise ConfigError(f"model.embed_dim: got {d}, must be divisible by {name} ({h})")
    if m.fusion == "fno" and m.fno.modes > d // 2 + 1:
        raise ConfigError(
            f"model.fno.modes: got {m.fno.modes}, must be <= model.embed_dim // 2 + 1 = {d // 2 + 1} "
            f"(the fuser's rfft runs along the {d} embedding entries)"
        )
    cells = _MINIGRID_VIEW_CELLS
    if "state" in mods and "state" not in m.observation_keys and m.state.modes > cells // 2 + 1:
        raise ConfigError(
            f"model.state.modes: got {m.state.modes}, must be <= {cells // 2 + 1} (the rfft modes "
            f"of the {cells} cells of the 7x7 view)"
        )
    if "reward" in mods and "reward" not in m.observation_keys and cfg.env.reward_history == 0:
        raise ConfigError(
            "env.reward_history: got 0 (no reward history), but model.modalities includes reward; "
            "use env.reward_history >= 1"
        )


def check_model_names(model: Any) -> None:
    """Names and choices of the ``model`` section: modalities and their keys, frozen encoders, backbone, gates."""
    mods = model.modalities
    if not mods:
        raise ConfigError("model.modalities: at least one modality is required")
    for m in mods:
        if m not in MODALITIES:
            raise ConfigError(f"model.modalities: unknown modality '{m}' (known: {', '.join(MODALITIES)})")
    for m, keys in model.observation_keys.items():
        if m not in mods:
            raise ConfigError(f"model.observation_keys: '{m}' is not one of model.modalities {mods}")
        if not keys:
            raise ConfigError(f"model.observation_keys.{m}: give at least one observation key")
    if len(set(mods)) != len(mods):
        raise ConfigError(f"model.modalities: duplicates in {mods}")
    for m, key in model.presence_keys.items():
        if m not in mods:
            raise ConfigError(f"model.presence_keys: '{m}' is not one of model.modalities {mods}")
        if not isinstance(key, str) or not key:
            raise ConfigError(f"model.presence_keys.{m}: give the observation key of its flag, e.g. grid_present")
    check_action_prior(model.action_prior, "model")
    for m in model.freeze_encoders:
        if m not in mods:
            raise ConfigError(f"model.freeze_encoders: '{m}' is not one of model.modalities {mods}")
    if model.vision.backbone not in ("cnn", "clip"):
        raise ConfigError(f"model.vision.backbone: expected 'cnn' or 'clip', got {model.vision.backbone!r}")
    if model.vision.pooling not in VISION_POOLINGS:
        expected = ", ".join(VISION_POOLINGS)
        raise ConfigError(f"model.vision.pooling: expected one of {expected}, got {model.vision.pooling!r}")
    for m in model.flow.gate_init:
        if m not in MODALITIES and m != "fused":
            raise ConfigError(
                f"model.flow.gate_init: unknown modality '{m}' (known: {', '.join(MODALITIES)}, and "
                "fused for model.flow.placement=post)"
            )
    if model.flow.placement not in PLACEMENTS:
        raise ConfigError(
            f"model.flow.placement: expected one of {', '.join(PLACEMENTS)}, got {model.flow.placement!r}"
        )
    _check_flow_choices(model.flow)
    if model.dnc.write not in WRITES:
        raise ConfigError(f"model.dnc.write: expected one of {', '.join(WRITES)}, got {model.dnc.write!r}")
    if model.critic_input not in CRITIC_INPUTS:
        raise ConfigError(f"model.critic_input: expected one of {', '.join(CRITIC_INPUTS)}, got {model.critic_input!r}")
    if model.fusion not in FUSIONS:
        raise ConfigError(f"model.fusion: expected one of {', '.join(FUSIONS)}, got {model.fusion!r}")
    if model.fusion_hidden is not None and model.fusion != "concat":
        raise ConfigError(
            f"model.fusion_hidden: got {model.fusion_hidden}, but only model.fusion=concat has an MLP "
            f"(model.fusion is {model.fusion!r}); leave it unset"
        )
    steps = model.flow.adaptive_steps
    if any(not 1 <= s <= _MAX_ADAPTIVE_STEPS for s in steps) or len(set(steps)) != len(steps):
        raise ConfigError(
            f"model.flow.adaptive_steps: got {steps}, expected distinct step counts in "
            f"[1, {_MAX_ADAPTIVE_STEPS}] (paper: [1, 2, 3, 5, 7, 10]; [] = fixed model.flow.steps)"
        )
    if len(steps) == 1:
        raise ConfigError(
            f"model.flow.adaptive_steps: got {steps}: give two or more choices, or set "
            "model.flow.steps and leave adaptive_steps empty"
        )


#: ``model.flow.noise_scale`` choices
NOISE_SCALES = ("absolute", "relative")
#: ``model.flow.targets`` choices
FM_TARGETS = ("synthetic", "paired")


def _check_flow_choices(flow: Any) -> None:
    """``model.flow.noise_scale`` and ``model.flow.reliability``: known choices; reliability needs refiners per
    modality (placement pre)."""
    if flow.noise_scale not in NOISE_SCALES:
        raise ConfigError(
            f"model.flow.noise_scale: expected one of {', '.join(NOISE_SCALES)}, got {flow.noise_scale!r}"
        )
    if flow.targets not in FM_TARGETS:
        raise ConfigError(f"model.flow.targets: expected one of {', '.join(FM_TARGETS)}, got {flow.targets!r}")
    if flow.targets == "paired" and flow.placement != "pre":
        raise ConfigError(
            "model.flow.targets: paired trains each modality's refiner on its own corrupted and clean embeddings, "
            f"so it needs model.flow.placement=pre (got {flow.placement!r})"
        )
    if flow.reliability not in RELIABILITY_MODES:
        raise ConfigError(
            f"model.flow.reliability: expected one of {', '.join(RELIABILITY_MODES)}, got {flow.reliability!r}"
        )
    if flow.reliability != "off" and flow.placement != "pre":
        raise ConfigError(
            f"model.flow.reliability: {flow.reliability} weighs each modality by its own refiner's score, so it "
            f"needs model.flow.placement=pre (got {flow.placement!r})"
        )
