"""Build the FreamerV1 policy from an environment's specs and a :class:`~freamer_rl.config.ModelConfig`.

The result is made of plain TorchRL/tensordict parts::

    trunk  = TensorDictSequential(encoders -> [cross-modal] -> pools -> FM refiners -> stack -> FNO -> DNC)
    actor  = ProbabilisticActor(logits head on "hidden")          # categorical policy (Eq. 5)
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
from freamer_rl.errors import EnvSetupError
from freamer_rl.layers.dnc import DNCModule
from freamer_rl.layers.encoders import (
    CNNBackbone,
    CrossModalAttention,
    LanguageEncoder,
    RewardEncoder,
    SlotPool,
    VisionEncoder,
)
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fno import FNOFuser, StateFNOEncoder

logger = logging.getLogger(__name__)

# Observation keys each modality reads (see docs/CONVENTIONS.md).
MODALITY_KEYS: dict[str, tuple[str, ...]] = {
    "state": ("grid", "direction"),
    "vision": ("pixels",),
    "language": ("mission_tokens",),
    "reward": ("reward_history",),
}
SLOT_MODALITIES = ("vision", "language")


class StackModalities(nn.Module):
    """Stack M embeddings ``[*B, d]`` into the Layer-3 input ``E`` of shape ``[*B, M, d]``."""

    def forward(self, *embeddings: torch.Tensor) -> torch.Tensor:
        return torch.stack(embeddings, dim=-2)


def _spec_vocab_size(spec) -> int:
    """Number of token ids a ``mission_tokens`` spec admits (Categorical ``n`` or Bounded ``high + 1``)."""
    n = getattr(spec, "n", None)
    if n is None and hasattr(spec, "space"):
        n = getattr(spec.space, "n", None)
    if n is not None:
        return int(n)
    high = getattr(spec, "high", None)
    if high is None and hasattr(spec, "space"):
        high = spec.space.high
    if high is None:
        raise EnvSetupError("observation 'mission_tokens' has no bounded spec: cannot size the vocabulary")
    return int(torch.as_tensor(high).max().item()) + 1


def check_modalities(observation_spec: Composite, modalities: list[str], env_name: str = "the env") -> None:
    """Raise :class:`EnvSetupError` naming the first modality whose observation keys the env lacks."""
    keys = set(observation_spec.keys(True, True))
    for m in modalities:
        missing = [k for k in MODALITY_KEYS[m] if k not in keys]
        if missing:
            raise EnvSetupError(
                f"model.modalities includes '{m}' but {env_name} provides no {missing} observation "
                f"(it provides: {', '.join(sorted(map(str, keys)))})"
            )


def _make_vision_backbone(cfg: ModelConfig) -> nn.Module:
    if cfg.vision.backbone == "cnn":
        return CNNBackbone(in_channels=3)
    from freamer_rl.layers.clip_backbone import ClipBackbone  # optional dependency (open_clip)

    return ClipBackbone(
        model_name=cfg.vision.clip_model,
        pretrained=cfg.vision.clip_pretrained,
        checkpoint_path=cfg.vision.clip_checkpoint,
        allow_random_weights=cfg.vision.allow_random_weights,
    )


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
        """Trunk + categorical head: the module a Collector runs."""
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
    """Assemble the FreamerV1 TensorDictSequential from unbatched env specs and a model config."""
    modalities = list(cfg.modalities)
    check_modalities(observation_spec, modalities, env_name)
    d = cfg.embed_dim
    steps: list[nn.Module] = []

    if "state" in modalities:
        enc = StateFNOEncoder(out_dim=d, channels=cfg.state.channels, modes=cfg.state.modes)
        steps.append(TensorDictModule(enc, in_keys=["grid", "direction"], out_keys=[("embed", "state")]))
    if "reward" in modalities:
        history = observation_spec["reward_history"].shape[-1]
        enc = RewardEncoder(history=history, out_dim=d, channels=cfg.reward.channels, kernel=cfg.reward.kernel)
        steps.append(TensorDictModule(enc, in_keys=["reward_history"], out_keys=[("embed", "reward")]))
    if "language" in modalities:
        tok_spec = observation_spec["mission_tokens"]
        enc = LanguageEncoder(
            vocab_size=_spec_vocab_size(tok_spec),
            out_dim=d,
            num_slots=cfg.language.num_slots,
            layers=cfg.language.layers,
            heads=cfg.language.heads,
            max_len=tok_spec.shape[-1],
            slot_iters=cfg.language.slot_iters,
        )
        steps.append(TensorDictModule(enc, in_keys=["mission_tokens"], out_keys=[("slots", "language")]))
    if "vision" in modalities:
        enc = VisionEncoder(
            _make_vision_backbone(cfg), out_dim=d, num_slots=cfg.vision.num_slots, slot_iters=cfg.vision.slot_iters
        )
        steps.append(TensorDictModule(enc, in_keys=["pixels"], out_keys=[("slots", "vision")]))
    if "vision" in modalities and "language" in modalities:
        steps.append(
            TensorDictModule(
                CrossModalAttention(d, heads=cfg.cross_modal_heads),
                in_keys=[("slots", "vision"), ("slots", "language")],
                out_keys=[("slots", "vision"), ("slots", "language")],
            )
        )
    for m in SLOT_MODALITIES:
        if m in modalities:
            steps.append(TensorDictModule(SlotPool(), in_keys=[("slots", m)], out_keys=[("embed", m)]))
    for m in cfg.freeze_encoders:
        # Layer-1 encoder of m: the step that reads m's observation keys (the CLIP tower is frozen regardless)
        encoder = next(s for s in steps if set(s.in_keys) == set(MODALITY_KEYS[m]))
        encoder.requires_grad_(False)
        logger.info("model.freeze_encoders: the %s encoder is frozen (%d parameters)", m,
                    sum(p.numel() for p in encoder.parameters()))

    # Layer 2: one flow-matching refiner per modality, each with its own gate init (Eq. 1-3).
    refiners = nn.ModuleDict()
    for m in modalities:
        refiners[m] = FlowMatchingRefiner(
            dim=d, hidden=cfg.flow.hidden, steps=cfg.flow.steps, gate_init=cfg.flow.gate_init.get(m, -3.0)
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

    n_actions = int(action_spec.n if hasattr(action_spec, "n") else action_spec.space.n)
    actor_net = _mlp_head(d, cfg.head_hidden, n_actions, out_gain=0.01)
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["hidden"], out_keys=["logits"]),
        in_keys=["logits"],
        out_keys=["action"],
        spec=action_spec,
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )
    critic = ValueOperator(_mlp_head(d, cfg.head_hidden, 1, out_gain=1.0), in_keys=["hidden"])
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


def _mlp_head(in_dim: int, hidden: int, out_dim: int, out_gain: float) -> nn.Sequential:
    """Two-layer tanh head with orthogonal init; a small output gain keeps the initial policy near uniform."""
    net = nn.Sequential(nn.Linear(in_dim, hidden), nn.Tanh(), nn.Linear(hidden, out_dim))
    nn.init.orthogonal_(net[0].weight, gain=2**0.5)
    nn.init.zeros_(net[0].bias)
    nn.init.orthogonal_(net[2].weight, gain=out_gain)
    nn.init.zeros_(net[2].bias)
    return net
