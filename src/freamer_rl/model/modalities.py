"""The modality registry: one plain-dict entry per Layer-1 modality.

``MODALITIES[name]`` is a :class:`ModalitySpec`: the observation keys the modality reads by default, whether its
encoder writes one embedding (``"vector"`` kind, key ``("embed", name)``) or a set of slots (``"slots"`` kind, key
``("slots", name)``, mean-pooled into ``("embed", name)`` after cross-modal attention), its default residual-gate
logit (Eq. 3), a check of the env's specs for those keys, and the encoder factory. The factory
(:func:`freamer_rl.model.factory.build_freamer`) only walks this dict; adding a modality is one entry plus its encoder::

    MODALITIES["lidar"] = ModalitySpec(default_keys=("lidar",), kind="vector", gate_init=-1.0,
                                       build_encoder=my_lidar_encoder, check_spec=check_float)

A recipe maps an env's own observation keys onto a modality with ``model.observation_keys``, e.g.
``{vector: [observation]}`` for a gymnasium env, or ``{state: [image, direction]}``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn

from freamer_rl.errors import EnvSetupError
from freamer_rl.layers.encoders import CNNBackbone, LanguageEncoder, RewardEncoder, VisionEncoder
from freamer_rl.layers.fno import StateFNOEncoder
from freamer_rl.layers.vector import VectorEncoder

if TYPE_CHECKING:
    from freamer_rl.model.config import ModelConfig


@dataclass(frozen=True)
class EncoderContext:
    """What an encoder factory gets: the modality's name, its keys, their unbatched specs and the model config."""

    name: str
    keys: tuple[str, ...]
    specs: tuple  # unbatched TensorSpecs, one per key
    cfg: ModelConfig


@dataclass(frozen=True)
class ModalitySpec:
    """One registry entry (see the module docstring).

    Attributes:
        default_keys: observation keys read when ``model.observation_keys`` does not name others.
        kind: ``"vector"`` (encoder output ``[*B, d]``) or ``"slots"`` (``[*B, K, d]``).
        gate_init: default gate logit alpha of the modality's refiner (Eq. 3); ``model.flow.gate_init`` overrides.
        build_encoder: ``EncoderContext -> nn.Module`` taking the keys' tensors in order.
        check_spec: ``(modality, key, spec) -> None``, raising :class:`EnvSetupError` for a wrong dtype or shape.
        num_keys: how many keys the encoder takes (``None``: one or more).
    """

    default_keys: tuple[str, ...]
    kind: str
    gate_init: float
    build_encoder: Callable[[EncoderContext], nn.Module]
    check_spec: Callable[[str, str, object], None]
    num_keys: int | None = None


# --------------------------------------------------------------------------------------------------------------
# spec checks (build time, so a forward never has to)
# --------------------------------------------------------------------------------------------------------------


def _fail(modality: str, key: str, spec, expected: str) -> None:
    raise EnvSetupError(
        f"model.observation_keys: modality '{modality}' reads key '{key}' with spec "
        f"{type(spec).__name__}(shape={tuple(spec.shape)}, dtype={spec.dtype}); expected {expected}"
    )


def _is_int(dtype: torch.dtype) -> bool:
    return not (dtype.is_floating_point or dtype.is_complex or dtype == torch.bool)


def check_float(modality: str, key: str, spec) -> None:
    """Floating (or integer, read as float) entries with at least one element."""
    if spec.dtype == torch.bool or spec.dtype.is_complex or spec.shape.numel() == 0:
        _fail(modality, key, spec, "a float or integer tensor with at least one element")


def _check_grid(modality: str, key: str, spec) -> None:
    if key == "direction" or spec.ndim == 0:
        if not _is_int(spec.dtype) or spec.ndim > 1 or (spec.ndim == 1 and spec.shape[0] != 1):
            _fail(modality, key, spec, "an integer direction of shape [] or [1]")
        return
    if not _is_int(spec.dtype) or spec.ndim != 3 or spec.shape[-1] != 3:
        _fail(modality, key, spec, "MiniGrid's integer symbolic view of shape [V, V, 3]")


def _check_reward_history(modality: str, key: str, spec) -> None:
    if spec.ndim != 1 or spec.dtype == torch.bool or spec.dtype.is_complex:
        _fail(modality, key, spec, "a float reward history of shape [H]")


def _check_tokens(modality: str, key: str, spec) -> None:
    if spec.ndim != 1 or not _is_int(spec.dtype):
        _fail(modality, key, spec, "integer token ids of shape [L] (0 = padding)")


def _check_pixels(modality: str, key: str, spec) -> None:
    if spec.ndim != 3 or spec.shape[-1] != 3 or not (spec.dtype == torch.uint8 or spec.dtype.is_floating_point):
        _fail(modality, key, spec, "channels-last RGB pixels [H, W, 3], uint8 or float on the 0-255 scale")


# --------------------------------------------------------------------------------------------------------------
# encoder factories
# --------------------------------------------------------------------------------------------------------------


def _state_encoder(ctx: EncoderContext) -> nn.Module:
    grid_spec = ctx.specs[0]
    return StateFNOEncoder(
        out_dim=ctx.cfg.embed_dim,
        channels=ctx.cfg.state.channels,
        modes=ctx.cfg.state.modes,
        view_size=int(grid_spec.shape[0]),
        compile=ctx.cfg.compile,
    )


def _reward_encoder(ctx: EncoderContext) -> nn.Module:
    return RewardEncoder(
        history=int(ctx.specs[0].shape[-1]),
        out_dim=ctx.cfg.embed_dim,
        channels=ctx.cfg.reward.channels,
        kernel=ctx.cfg.reward.kernel,
        symlog=ctx.cfg.reward.symlog,
    )


def spec_vocab_size(key: str, spec) -> int:
    """Number of token ids a token spec admits (Categorical ``n`` or Bounded ``high + 1``)."""
    n = getattr(spec, "n", None)
    if n is None and hasattr(spec, "space"):
        n = getattr(spec.space, "n", None)
    if n is not None:
        return int(n)
    high = getattr(spec, "high", None)
    if high is None:
        high = getattr(getattr(spec, "space", None), "high", None)
    if high is None:
        raise EnvSetupError(
            f"observation '{key}' has no bounded spec ({type(spec).__name__}): cannot size the vocabulary"
        )
    return int(torch.as_tensor(high).max()) + 1


def _language_encoder(ctx: EncoderContext) -> nn.Module:
    c = ctx.cfg.language
    return LanguageEncoder(
        vocab_size=spec_vocab_size(ctx.keys[0], ctx.specs[0]),
        out_dim=ctx.cfg.embed_dim,
        num_slots=c.num_slots,
        layers=c.layers,
        heads=c.heads,
        max_len=int(ctx.specs[0].shape[-1]),
        slot_iters=c.slot_iters,
    )


def _vision_encoder(ctx: EncoderContext) -> nn.Module:
    c = ctx.cfg.vision
    if c.backbone == "cnn":
        backbone = CNNBackbone(in_channels=3)
    else:
        from freamer_rl.layers.clip_backbone import ClipBackbone  # optional dependency (open_clip)

        backbone = ClipBackbone(
            model_name=c.clip_model,
            pretrained=c.clip_pretrained,
            checkpoint_path=c.clip_checkpoint,
            allow_random_weights=c.allow_random_weights,
        )
    num_tokens = None
    if c.pooling == "flatten":  # the token count of this env's frames, from one blank frame of its spec's size
        frame = torch.zeros(1, *(int(n) for n in ctx.specs[0].shape[-3:]), dtype=torch.uint8)
        with torch.no_grad():
            num_tokens = int(backbone(frame).shape[1])
    return VisionEncoder(
        backbone,
        out_dim=ctx.cfg.embed_dim,
        num_slots=c.num_slots,
        slot_iters=c.slot_iters,
        pooling=c.pooling,
        num_tokens=num_tokens,
    )


def _vector_encoder(ctx: EncoderContext) -> nn.Module:
    shapes = [tuple(int(n) for n in s.shape) for s in ctx.specs]
    total = sum(int(torch.Size(s).numel()) for s in shapes)
    return VectorEncoder(total, ctx.cfg.embed_dim, hidden=ctx.cfg.vector.hidden, in_shapes=shapes)


#: The registry. Encoders are built in this dict's order (it fixes how the seeded initialisation is drawn, kept as in
#: earlier releases so a seed gives the same model); modalities are stacked for the fuser in ``model.modalities`` order.
MODALITIES: dict[str, ModalitySpec] = {
    "state": ModalitySpec(("grid", "direction"), "vector", -3.0, _state_encoder, _check_grid, num_keys=2),
    "reward": ModalitySpec(("reward_history",), "vector", -1.0, _reward_encoder, _check_reward_history, num_keys=1),
    "language": ModalitySpec(("mission_tokens",), "slots", -3.0, _language_encoder, _check_tokens, num_keys=1),
    "vision": ModalitySpec(("pixels",), "slots", -5.0, _vision_encoder, _check_pixels, num_keys=1),
    "vector": ModalitySpec(("observation",), "vector", -3.0, _vector_encoder, check_float),
    # the wearable-health env's two sensors (freamer_rl_envs.health), each with its own encoder and refiner
    "imu": ModalitySpec(("imu",), "vector", -3.0, _vector_encoder, check_float),
    "heart_rate": ModalitySpec(("hr_features",), "vector", -3.0, _vector_encoder, check_float),
}


def modality_keys(name: str, observation_keys: dict[str, list[str]] | None = None) -> tuple[str, ...]:
    """Observation keys of modality ``name``: ``observation_keys[name]`` if the recipe maps it, else the default."""
    mapped = (observation_keys or {}).get(name)
    return tuple(mapped) if mapped else MODALITIES[name].default_keys


def check_observation_keys(observation_spec, cfg: ModelConfig, env_name: str = "the env") -> None:
    """Raise :class:`EnvSetupError` naming the first modality key the env lacks or whose spec does not fit."""
    available = set(observation_spec.keys(True, True))
    for m in cfg.modalities:
        entry = MODALITIES[m]
        keys = modality_keys(m, cfg.observation_keys)
        if entry.num_keys is not None and len(keys) != entry.num_keys:
            raise EnvSetupError(
                f"model.observation_keys.{m}: modality '{m}' reads exactly {entry.num_keys} key(s) "
                f"(default {list(entry.default_keys)}); got {list(keys)}"
            )
        missing = [k for k in keys if k not in available]
        if missing:
            raise EnvSetupError(
                f"model.modalities includes '{m}' but {env_name} provides no {missing} observation "
                f"(it provides: {', '.join(sorted(map(str, available)))}); map the modality to the env's keys with "
                f"model.observation_keys.{m}=[...]"
            )
        for k in keys:
            entry.check_spec(m, k, observation_spec[k])
