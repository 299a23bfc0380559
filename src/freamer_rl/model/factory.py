"""Build the FreamerV1 policy from an environment's specs and a :class:`~freamer_rl.config.loader.ModelConfig`.

The result is made of plain TorchRL/tensordict parts::

    trunk  = TensorDictSequential(encoders -> [cross-modal] -> pools -> FM refiners -> stack -> FNO -> DNC)
             (ablations: model.flow.placement pre | post | off moves the refiner after the fuser or drops it;
              model.fusion fno | concat | mean swaps the fuser; model.dnc.enabled false drops the memory)
    actor  = ProbabilisticActor(head on "hidden")                 # from the action spec (freamer_rl.model.heads)
    critic = ValueOperator(value head on "hidden")
    actor_value = ActorValueOperator(trunk, actor, critic)        # .get_policy_operator() / .get_value_operator()

``ClipPPOLoss(actor_value.get_policy_operator(), actor_value.get_value_operator())`` works as usual. The trainer
runs the trunk once per minibatch and gives ClipPPOLoss the two heads (TorchRL's documented shared-trunk option),
so the auxiliary losses (Eq. 6) can read the same intermediate keys.

Layers 2-4 (refiners -> stack -> FNO -> DNC) come from :func:`build_filter_mix_memory`, the one trunk builder that
every domain uses (the health foundation encoder, :class:`~freamer_rl.health.encoders.FoundationHealthEncoder`,
puts its own Stage 1 in front of the same layers).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from tensordict import unravel_key
from tensordict.nn import TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Composite
from torchrl.modules import ActorValueOperator, ProbabilisticActor, ValueOperator

from freamer_rl.errors import EnvSetupError
from freamer_rl.layers.dnc import DNCModule
from freamer_rl.layers.encoders import CrossModalAttention, SlotPool
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fno import FNOFuser
from freamer_rl.layers.fusion import ConcatFuser, MeanFuser, PresenceMask
from freamer_rl.layers.tdmodule import KeyedModule
from freamer_rl.model.action_prior import check_prior_key
from freamer_rl.model.config import ModelConfig
from freamer_rl.model.heads import action_kind, build_actor, build_critic
from freamer_rl.model.modalities import MODALITIES, EncoderContext, check_observation_keys, modality_keys

logger = logging.getLogger(__name__)


class EmbeddingNoise(nn.Module):
    """``e [*B, d] -> e + level * std_row(e) * N(0, 1)``: Gaussian noise of ``level`` times each row's own std
    across its ``d`` entries (the paper's Table 13 protocol, applied to a Layer-1 embedding before its refiner)."""

    def __init__(self, level: float) -> None:
        super().__init__()
        self.level = float(level)

    def forward(self, e: torch.Tensor) -> torch.Tensor:
        return e + self.level * e.std(dim=-1, keepdim=True) * torch.randn_like(e)


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
    refiners: nn.ModuleDict  # {modality: refiner} (placement pre), {"fused": refiner} (post) or {} (off)
    fuser: FNOFuser | ConcatFuser | MeanFuser
    dnc: DNCModule | None
    modalities: list[str]
    # Layer 1 alone (the encoders, cross-modal attention, slot pooling; the trunk's own modules): writes ("embed", m)
    encoders: TensorDictSequential | None = None

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

    def policy_with_embedding_noise(self, levels: Mapping[str, float]):
        """The policy with :class:`EmbeddingNoise` on ``("embed", m)`` right after modality ``m``'s encoder, for each
        ``m: level`` of ``levels`` (evaluation of Table 13; the weights are shared with this model)."""
        unknown = sorted(set(levels) - set(self.modalities))
        if unknown:
            raise EnvSetupError(f"embedding noise: {unknown} are not modalities of this model {self.modalities}")
        steps = list(self.trunk.module)
        for m, level in levels.items():
            at = next(i for i, s in enumerate(steps) if ("embed", m) in [unravel_key(k) for k in s.out_keys])
            steps.insert(at + 1, KeyedModule(EmbeddingNoise(level), in_keys=[("embed", m)], out_keys=[("embed", m)]))
        return ActorValueOperator(TensorDictSequential(*steps), self.actor, self.critic).get_policy_operator()

    def refiner_keys(self) -> dict[str, tuple[NestedKey, NestedKey]]:
        """``{m: (input key, output key)}`` of each refiner: ``("embed", m) -> ("refined", m)`` before the fuser,
        ``("embed", "fused") -> "fused"`` after it."""
        return {m: (("embed", m), "fused" if m == "fused" else ("refined", m)) for m in self.refiners}

    def telemetry(self, td) -> dict[str, torch.Tensor]:
        """Per refined modality ``m``, means over the rows of a trunk pass written to ``td``:
        ``fm_displacement_<m>`` (:meth:`displacement`) and, for refiners with score-based reliability,
        ``gate_input_<m>`` (the input-dependent gate) and ``weight_<m>`` (the mixing weight)."""
        out = {f"fm_displacement_{m}": v for m, v in self.displacement(td).items()}
        keys = self.refiner_keys()
        for m, refiner in self.refiners.items():
            if refiner.reliability != "off":
                with torch.no_grad():
                    gate, weight = refiner.reliability_terms(td.get(keys[m][0]))
                out[f"gate_input_{m}"], out[f"weight_{m}"] = gate.mean(), weight.mean()
        return out

    def displacement(self, td) -> dict[str, torch.Tensor]:
        """How far each refiner moved its input in a trunk pass written to ``td``: the mean over rows of
        ``||e_hat - e|| / ||e||`` (0: the filter is off; 1: it moved the embedding by its own length)."""
        out = {}
        for m, (src, dst) in self.refiner_keys().items():
            e, e_hat = td.get(src), td.get(dst)
            out[m] = ((e_hat - e).norm(dim=-1) / e.norm(dim=-1).clamp_min(1e-8)).mean().detach()
        return out


def build_freamer(
    observation_spec: Composite, action_spec, cfg: ModelConfig, env_name: str = "the env"
) -> FreamerModules:
    """Assemble the FreamerV1 TensorDictSequential from unbatched env specs and a model config.

    Modalities come from :data:`freamer_rl.model.modalities.MODALITIES` (keys remapped by ``cfg.observation_keys``); the
    heads follow the action spec (:mod:`freamer_rl.model.heads`). Bad specs raise one :class:`EnvSetupError` line.
    """
    modalities = list(cfg.modalities)
    check_observation_keys(observation_spec, cfg, env_name)
    action_kind(action_spec)  # fail on an action spec without a head before building anything
    _check_presence_keys(observation_spec, cfg.presence_keys, env_name)
    d = cfg.embed_dim
    steps: list[nn.Module] = _layer1_encoders(observation_spec, cfg)
    encoders = TensorDictSequential(*steps)

    # Layers 2-4: flow-matching refiners, FNO fusion, DNC memory (the shared trunk builder).
    layers, refiners, fuser, dnc = build_filter_mix_memory(
        modalities,
        d,
        flow_hidden=cfg.flow.hidden,
        flow_steps=cfg.flow.steps,
        flow_adaptive_steps=tuple(cfg.flow.adaptive_steps or ()) or None,
        flow_tau=float(cfg.flow.adaptive_tau),
        reliability=cfg.flow.reliability,
        reliability_margin=float(cfg.flow.reliability_margin),
        gate_init={
            **{m: cfg.flow.gate_init.get(m, MODALITIES[m].gate_init) for m in modalities},
            "fused": cfg.flow.gate_init.get("fused", FUSED_GATE_INIT),
        },
        placement=cfg.flow.placement,
        presence_keys=cfg.presence_keys,
        fusion=cfg.fusion,
        fusion_hidden=cfg.fusion_hidden,
        fno_modes=cfg.fno.modes,
        fno_residual_scale=cfg.fno.residual_scale,
        fno_output_norm=cfg.fno.output_norm,
        dnc=cfg.dnc.enabled,
        memory_slots=cfg.dnc.memory_slots,
        memory_width=cfg.dnc.memory_width,
        dnc_write=cfg.dnc.write,
        dnc_output_norm=cfg.dnc.output_norm,
        compile=cfg.compile,
    )
    steps.extend(layers)
    trunk = TensorDictSequential(*steps)

    check_prior_key(cfg.action_prior, observation_spec, action_spec, "model")
    actor = build_actor(action_spec, d, cfg.head_hidden, prior=cfg.action_prior)
    critic = build_critic(d, cfg.head_hidden, detached=cfg.critic_input == "detached")
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
        encoders=encoders,
    )


def build_filter_mix_memory(
    modalities: Sequence[str],
    dim: int,
    *,
    flow_hidden: int,
    flow_steps: int,
    gate_init: Mapping[str, float],
    flow_adaptive_steps: Sequence[int] | None = None,
    flow_tau: float = 1.0,
    reliability: str = "off",
    reliability_margin: float = 2.0,
    placement: str = "pre",
    presence_keys: Mapping[str, NestedKey] | None = None,
    fusion: str = "fno",
    fusion_hidden: int | None = None,
    fno_modes: int,
    fno_residual_scale: float,
    fno_output_norm: bool = False,
    dnc: bool = True,
    memory_slots: int = 32,
    memory_width: int = 64,
    dnc_write: str = "additive",
    dnc_output_norm: bool = False,
    compile: bool = False,
    output_dim: int | None = None,
    out_key: NestedKey = "hidden",
    memory_key: NestedKey = ("dnc", "memory"),
    is_init_key: NestedKey = "is_init",
) -> tuple[list[nn.Module], nn.ModuleDict, FNOFuser, DNCModule | None]:
    """Layers 2-4 of FreamerV1 as TensorDict modules: the one trunk builder of every domain.

    For M = ``len(modalities)`` modalities of width ``d = dim`` the returned ``steps`` (to put in a
    ``TensorDictSequential`` after the Layer-1 encoders that wrote ``("embed", m) [*B, d]``) are::

        ("embed", m)   -> FlowMatchingRefiner_m -> ("refined", m)        [*B, d]         Eq. 1-3, one per modality
        ("refined", *) -> StackModalities      -> "modal_stack"          [*B, M, d]
        "modal_stack"  -> FNOFuser             -> "fused", "fused_modalities"  [*B, d], [*B, M, d]  Eq. A14-A15
        "fused"        -> DNCModule            -> out_key [*B, D_out], ("next", *memory_key) [*B, N, W]  App. F.1
                          (``dnc=False``: Linear(d, D_out) -> GELU, stateless)

    ``presence_keys`` ``{m: key}``: modality ``m``'s row is multiplied by the flag ``key [*B, 1]``
    (:class:`~freamer_rl.layers.fusion.PresenceMask`, written to ``("masked", m)`` and stacked from there), so a
    dropped sensor adds nothing to the mix.

    ``placement="post"`` stacks the raw ``("embed", m)``, the fuser writes ``("embed", "fused")`` and one refiner
    (``refiners["fused"]``) turns it into ``"fused"``: refinement after mixing, the comparison the paper names as
    missing. ``placement="off"`` stacks ``("embed", m)`` and refines nothing. ``fusion="concat"`` /
    ``"mean"`` swap the FNO fuser for :class:`~freamer_rl.layers.fusion.ConcatFuser` (``fusion_hidden`` wide) or
    :class:`~freamer_rl.layers.fusion.MeanFuser` (same keys).

    The modules are built in that order (refiners in ``modalities`` order, then the fuser, then the DNC), so a seeded
    model gets the same initial weights wherever it is built. ``fno_modes`` is used as given (the fuser checks it
    against ``d``). The DNC follows TorchRL's stateful pattern: step mode by default, ``[*B, T]`` sequences under
    ``torchrl.modules.set_recurrent_mode(True)``.

    Args:
        modalities: modality names ``m`` (keys ``("embed", m)``, ``("refined", m)``).
        dim: embedding width ``d``. flow_hidden, flow_steps: velocity MLP width and Euler steps of each refiner.
        flow_adaptive_steps, flow_tau: step-count choices and Gumbel-Softmax temperature of the score-based
            adaptive complexity (Appendix G.4; ``None``/empty: off, every refiner takes ``flow_steps`` steps).
        reliability, reliability_margin: the refiners' score-based input gate and/or mixing weight
            (:class:`~freamer_rl.layers.flow_matching.FlowMatchingRefiner`; ``placement="pre"`` only).
        gate_init: initial gate logit ``alpha_m`` per refined modality (``"fused"`` for ``placement="post"``).
        placement, fusion, fusion_hidden: where the refiners sit (``pre``, ``post``, ``off``), the fuser (``fno``,
            ``concat``, ``mean``) and the concat MLP's width (default ``d``).
        fno_modes, fno_residual_scale, fno_output_norm: :class:`~freamer_rl.layers.fno.FNOFuser` settings.
        dnc, memory_slots, memory_width: Layer 4 DNC (``N``, ``W``) or the stateless projection when False.
        dnc_write, dnc_output_norm: the DNC's memory write (``additive``, the layer's default, | ``bounded``) and
            the LayerNorm on its output (:class:`~freamer_rl.layers.dnc.DNCMemory`); FreamerV1 passes its
            ``model.dnc`` choices.
        compile: ``torch.compile`` the DNC step (with an eager fallback; :class:`~freamer_rl.layers.dnc.DNCModule`).
        output_dim: ``D_out`` (default ``d``). out_key: where Layer 4 writes ``e_aug``.
        memory_key, is_init_key: DNC state and episode-start keys.

    Returns:
        ``(steps, refiners, fuser, dnc)``: the TensorDict modules, ``{m: FlowMatchingRefiner}``, the fuser and the
        :class:`~freamer_rl.layers.dnc.DNCModule` (``None`` when ``dnc=False``).
    """
    if placement not in PLACEMENTS or fusion not in FUSIONS:
        raise ValueError(
            f"placement must be one of {PLACEMENTS} and fusion one of {FUSIONS}; got {placement!r}, {fusion!r}"
        )
    if reliability != "off" and placement != "pre":
        raise ValueError(f"reliability={reliability!r} needs placement='pre' (one refiner per modality)")
    refined = list(modalities) if placement == "pre" else ["fused"] if placement == "post" else []
    missing = [m for m in refined if m not in gate_init]
    if missing:
        raise ValueError(f"gate_init: no initial gate for {missing} (given: {sorted(gate_init)})")
    d_out = dim if output_dim is None else output_dim
    refiners = nn.ModuleDict()
    for m in refined:
        refiners[m] = FlowMatchingRefiner(
            dim=dim,
            hidden=flow_hidden,
            steps=flow_steps,
            gate_init=gate_init[m],
            adaptive_steps=flow_adaptive_steps,
            tau=flow_tau,
            reliability=reliability,
            reliability_margin=reliability_margin,
        )
    steps = _refine_and_stack(modalities, refiners if placement == "pre" else None, presence_keys)
    fuser = _build_fuser(fusion, len(modalities), dim, fno_modes, fno_residual_scale, fno_output_norm, fusion_hidden)
    fused_key = ("embed", "fused") if placement == "post" else "fused"
    steps.append(KeyedModule(fuser, in_keys=["modal_stack"], out_keys=[fused_key, "fused_modalities"]))
    if placement == "post":  # one refiner on the mixed vector (refinement after fusion)
        steps.append(KeyedModule(refiners["fused"], in_keys=[fused_key], out_keys=["fused"]))
    memory = _layer4(
        dnc,
        dim,
        d_out,
        memory_slots,
        memory_width,
        out_key,
        memory_key,
        is_init_key,
        compile,
        dnc_write,
        dnc_output_norm,
    )
    steps.append(memory if memory is not None else _projection(dim, d_out, out_key))
    return steps, refiners, fuser, memory


def _refine_and_stack(
    modalities: Sequence[str],
    refiners: nn.ModuleDict | None,
    presence_keys: Mapping[str, NestedKey] | None,
) -> list[nn.Module]:
    """Steps from ``("embed", m)`` to ``"modal_stack" [*B, M, d]``: each modality's refiner (``refiners`` given,
    placement ``pre``), then its presence mask where ``presence_keys`` names one, then the stack."""
    steps: list[nn.Module] = []
    stack_in = [("embed", m) for m in modalities]
    if refiners is not None:
        steps = [KeyedModule(refiners[m], in_keys=[("embed", m)], out_keys=[("refined", m)]) for m in modalities]
        stack_in = [("refined", m) for m in modalities]
    presence = dict(presence_keys or {})
    unknown = sorted(set(presence) - set(modalities))
    if unknown:
        raise ValueError(f"presence_keys: {unknown} are not among the modalities {list(modalities)}")
    for i, m in enumerate(modalities):
        if m in presence:  # a dropped sensor's row enters the fuser as zeros
            steps.append(KeyedModule(PresenceMask(), in_keys=[stack_in[i], presence[m]], out_keys=[("masked", m)]))
            stack_in[i] = ("masked", m)
    steps.append(KeyedModule(StackModalities(), in_keys=stack_in, out_keys=["modal_stack"]))
    return steps


def _check_presence_keys(observation_spec: Composite, presence_keys: Mapping[str, str], env_name: str) -> None:
    """Each ``model.presence_keys`` flag is an observation ``[1]`` of the env (``env.presence`` writes them)."""
    keys = observation_spec.keys(True)
    for m, key in presence_keys.items():
        if key not in keys:
            raise EnvSetupError(
                f"model.presence_keys.{m}: {env_name} has no observation {key!r} (env.presence: [<key>] writes "
                "<key>_present in every phase)"
            )
        shape = tuple(observation_spec[key].shape)
        if shape != (1,):
            raise EnvSetupError(f"model.presence_keys.{m}: {key!r} has shape {shape}; a presence flag is [1]")


def _layer4(
    dnc: bool,
    dim: int,
    d_out: int,
    memory_slots: int,
    memory_width: int,
    out_key: NestedKey,
    memory_key: NestedKey,
    is_init_key: NestedKey,
    compile: bool,
    write: str,
    output_norm: bool,
) -> DNCModule | None:
    """Layer 4's DNC reading ``"fused"`` (App. F.1), or None without memory."""
    if not dnc:
        return None
    return DNCModule(
        input_dim=dim,
        memory_slots=memory_slots,
        memory_width=memory_width,
        output_dim=d_out,
        in_key="fused",
        out_key=out_key,
        memory_key=memory_key,
        is_init_key=is_init_key,
        write=write,
        output_norm=output_norm,
        compile=compile,
    )


def _projection(dim: int, d_out: int, out_key: NestedKey) -> KeyedModule:
    """The stateless stand-in for the DNC: ``Linear(d, D_out) -> GELU`` on ``"fused"``."""
    return KeyedModule(nn.Sequential(nn.Linear(dim, d_out), nn.GELU()), in_keys=["fused"], out_keys=[out_key])


#: initial gate logit of the one refiner after the fuser (``placement: post``; ``model.flow.gate_init.fused``)
FUSED_GATE_INIT = -3.0
#: ``model.flow.placement`` choices: refiners before the fuser (the paper's), one after it, none
PLACEMENTS = ("pre", "post", "off")
#: ``model.fusion`` choices
FUSIONS = ("fno", "concat", "mean")


def _build_fuser(
    fusion: str, m: int, d: int, modes: int, residual_scale: float, output_norm: bool, hidden: int | None
) -> nn.Module:
    if fusion == "fno":
        return FNOFuser(num_modalities=m, dim=d, modes=modes, residual_scale=residual_scale, output_norm=output_norm)
    if fusion == "concat":
        return ConcatFuser(m, d, hidden=hidden)
    return MeanFuser(m, d)


def _layer1_encoders(observation_spec: Composite, cfg: ModelConfig) -> list[nn.Module]:
    """Layer 1: one encoder per modality (registry), cross-modal attention over the slot modalities, slot pooling."""
    steps: list[nn.Module] = []
    slot_mods = []
    for m in [name for name in MODALITIES if name in cfg.modalities]:  # registry order: see MODALITIES
        entry = MODALITIES[m]
        keys = modality_keys(m, cfg.observation_keys)
        ctx = EncoderContext(name=m, keys=keys, specs=tuple(observation_spec[k] for k in keys), cfg=cfg)
        out_key = ("slots", m) if entry.kind == "slots" else ("embed", m)
        encoder = KeyedModule(entry.build_encoder(ctx), in_keys=list(keys), out_keys=[out_key])
        if m in cfg.freeze_encoders:
            encoder.requires_grad_(False)  # the CLIP tower is frozen regardless
            logger.info(
                "model.freeze_encoders: the %s encoder is frozen (%d parameters)",
                m,
                sum(p.numel() for p in encoder.parameters()),
            )
        steps.append(encoder)
        if entry.kind == "slots":
            slot_mods.append(m)
    if "vision" in slot_mods and "language" in slot_mods:
        # bidirectional cross-modal attention between vision and language slots (Section 3.2)
        steps.append(
            KeyedModule(
                CrossModalAttention(cfg.embed_dim, heads=cfg.cross_modal_heads),
                in_keys=[("slots", "vision"), ("slots", "language")],
                out_keys=[("slots", "vision"), ("slots", "language")],
            )
        )
    for m in slot_mods:
        steps.append(KeyedModule(SlotPool(), in_keys=[("slots", m)], out_keys=[("embed", m)]))
    return steps
