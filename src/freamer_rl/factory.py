"""Build the FreamerV1 policy from an environment's specs and a :class:`~freamer_rl.config.ModelConfig`.

The result is made of plain TorchRL/tensordict parts::

    trunk  = TensorDictSequential(encoders -> [cross-modal] -> pools -> FM refiners -> stack -> FNO -> DNC)
    actor  = ProbabilisticActor(head on "hidden")                 # from the action spec (freamer_rl.heads)
    critic = ValueOperator(value head on "hidden")
    actor_value = ActorValueOperator(trunk, actor, critic)        # .get_policy_operator() / .get_value_operator()

``ClipPPOLoss(actor_value.get_policy_operator(), actor_value.get_value_operator())`` works as usual. The trainer
runs the trunk once per minibatch and gives ClipPPOLoss the two heads (TorchRL's documented shared-trunk option),
so the auxiliary losses (Eq. 6) can read the same intermediate keys.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Composite
from torchrl.modules import ActorValueOperator, ProbabilisticActor, ValueOperator

from freamer_rl.config import ModelConfig
from freamer_rl.heads import action_kind, build_actor, build_critic
from freamer_rl.layers.dnc import DNCModule
from freamer_rl.layers.encoders import CrossModalAttention, SlotPool
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fno import FNOFuser
from freamer_rl.modalities import MODALITIES, EncoderContext, check_observation_keys, modality_keys

logger = logging.getLogger(__name__)


class StackModalities(nn.Module):
    """Stack M embeddings ``[*B, d]`` into the Layer-3 input ``E`` of shape ``[*B, M, d]``."""

    def forward(self, *embeddings: torch.Tensor) -> torch.Tensor:
        return torch.stack(embeddings, dim=-2)


@dataclass
class FreamerModules:
    """Everything the trainer, the evaluator and user pipelines need."""

    actor_value: ActorValueOperator
    trunk: TensorDictSequential
    actor: ProbabilisticActor
    critic: ValueOperator
    refiners: nn.ModuleDict
    fuser: FNOFuser
    dnc: DNCModule | None
    modalities: list[str]

    @property
    def policy(self):
        """Trunk + policy head: the module a Collector runs."""
        return self.actor_value.get_policy_operator()

    @property
    def value(self):
        """Trunk + value head: the module GAE runs."""
        return self.actor_value.get_value_operator()

    def primers(self) -> list:
        """TensorDictPrimers for the stateful parts (append them to the env with InitTracker)."""
        return [self.dnc.make_tensordict_primer()] if self.dnc is not None else []

    def gates(self) -> dict[str, float]:
        """Per-modality residual gate sigma(alpha_m) (Eq. 3)."""
        return {m: float(r.gate.detach()) for m, r in self.refiners.items()}


def build_freamer(observation_spec: Composite, action_spec, cfg: ModelConfig, env_name: str = "the env") -> FreamerModules:
    """Assemble the FreamerV1 TensorDictSequential from unbatched env specs and a model config.

    Modalities come from :data:`freamer_rl.modalities.MODALITIES` (keys remapped by ``cfg.observation_keys``); the
    heads follow the action spec (:mod:`freamer_rl.heads`). Bad specs raise one :class:`EnvSetupError` line.
    """
    modalities = list(cfg.modalities)
    check_observation_keys(observation_spec, cfg, env_name)
    action_kind(action_spec)  # fail on an action spec without a head before building anything
    d = cfg.embed_dim
    steps: list[nn.Module] = _layer1_encoders(observation_spec, cfg)

    # Layer 2: one flow-matching refiner per modality, each with its own gate init (Eq. 1-3).
    refiners = nn.ModuleDict()
    for m in modalities:
        refiners[m] = FlowMatchingRefiner(
            dim=d, hidden=cfg.flow.hidden, steps=cfg.flow.steps,
            gate_init=cfg.flow.gate_init.get(m, MODALITIES[m].gate_init),
        )
        steps.append(TensorDictModule(refiners[m], in_keys=[("embed", m)], out_keys=[("refined", m)]))

    # Layer 3: spectral fusion over the M refined embeddings (Eq. A14-A15).
    steps.append(
        TensorDictModule(
            StackModalities(), in_keys=[("refined", m) for m in modalities], out_keys=["modal_stack"]
        )
    )
    fuser = FNOFuser(
        num_modalities=len(modalities),
        dim=d,
        modes=cfg.fno.modes,
        residual_scale=cfg.fno.residual_scale,
        output_norm=cfg.fno.output_norm,
    )
    steps.append(TensorDictModule(fuser, in_keys=["modal_stack"], out_keys=["fused", "fused_modalities"]))

    # Layer 4: DNC episodic memory (Appendix F.1) or a plain projection when disabled.
    dnc = None
    if cfg.dnc.enabled:
        dnc = DNCModule(
            input_dim=d,
            memory_slots=cfg.dnc.memory_slots,
            memory_width=cfg.dnc.memory_width,
            output_dim=d,
            in_key="fused",
            out_key="hidden",
        )
        steps.append(dnc)
    else:
        steps.append(TensorDictModule(nn.Sequential(nn.Linear(d, d), nn.GELU()), in_keys=["fused"], out_keys=["hidden"]))
    trunk = TensorDictSequential(*steps)

    actor = build_actor(action_spec, d, cfg.head_hidden)
    critic = build_critic(d, cfg.head_hidden)
    actor_value = ActorValueOperator(trunk, actor, critic)
    return FreamerModules(
        actor_value=actor_value,
        trunk=trunk,
        actor=actor,
        critic=critic,
        refiners=refiners,
        fuser=fuser,
        dnc=dnc,
        modalities=modalities,
    )


def _layer1_encoders(observation_spec: Composite, cfg: ModelConfig) -> list[nn.Module]:
    """Layer 1: one encoder per modality (registry), cross-modal attention over the slot modalities, slot pooling."""
    steps: list[nn.Module] = []
    slot_mods = []
    for m in [name for name in MODALITIES if name in cfg.modalities]:  # registry order: see MODALITIES
        entry = MODALITIES[m]
        keys = modality_keys(m, cfg.observation_keys)
        ctx = EncoderContext(name=m, keys=keys, specs=tuple(observation_spec[k] for k in keys), cfg=cfg)
        out_key = ("slots", m) if entry.kind == "slots" else ("embed", m)
        encoder = TensorDictModule(entry.build_encoder(ctx), in_keys=list(keys), out_keys=[out_key])
        if m in cfg.freeze_encoders:
            encoder.requires_grad_(False)  # the CLIP tower is frozen regardless
            logger.info("model.freeze_encoders: the %s encoder is frozen (%d parameters)", m,
                        sum(p.numel() for p in encoder.parameters()))
        steps.append(encoder)
        if entry.kind == "slots":
            slot_mods.append(m)
    if "vision" in slot_mods and "language" in slot_mods:
        # bidirectional cross-modal attention between vision and language slots (Section 3.2)
        steps.append(
            TensorDictModule(
                CrossModalAttention(cfg.embed_dim, heads=cfg.cross_modal_heads),
                in_keys=[("slots", "vision"), ("slots", "language")],
                out_keys=[("slots", "vision"), ("slots", "language")],
            )
        )
    for m in slot_mods:
        steps.append(TensorDictModule(SlotPool(), in_keys=[("slots", m)], out_keys=[("embed", m)]))
    return steps
