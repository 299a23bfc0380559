"""FreamerV1's ``model`` section: modalities, per-modality encoders, flow refiners (Layer 2), FNO fuser, DNC."""

from __future__ import annotations

from dataclasses import dataclass, field

from freamer_rl.config.checks import LAYERS_LIMIT, NON_NEGATIVE, POSITIVE, WIDTH_LIMIT, Range, size_range
from freamer_rl.model.action_prior import ActionPriorConfig


@dataclass
class VisionConfig:
    backbone: str = "cnn"  # "cnn" (trainable, offline) or "clip" (frozen open_clip patch tokens)
    clip_model: str = "ViT-B-32"
    clip_pretrained: str | None = "openai"
    clip_checkpoint: str | None = None
    # Random CLIP weights only on explicit request (tests, parameter counting); a warning is logged.
    allow_random_weights: bool = False
    num_slots: int = 8
    slot_iters: int = 3
    # slots: the paper's Slot Attention over the backbone's tokens (Appendix E.1); flatten: the tokens flattened in
    # their grid order and projected by one Linear, as TorchRL's PPO-CNN reads its conv map (an ablation; README
    # "Robustness", pixels alone). num_slots and slot_iters apply to slots only.
    pooling: str = "slots"


@dataclass
class LanguageConfig:
    num_slots: int = 4
    layers: int = 1
    heads: int = 4
    slot_iters: int = 3


@dataclass
class StateConfig:
    channels: int = 32
    modes: int = 12


@dataclass
class RewardConfig:
    channels: int = 16
    kernel: int = 3
    # symlog the reward history before the Conv1D (layers/encoders.py RewardEncoder): raw rewards of large scale
    # (Pendulum's -16..0) otherwise make this modality's embedding outweigh the others in the fuser
    symlog: bool = False


@dataclass
class VectorConfig:
    """Encoder of the ``vector`` modality (plain vector observations, see ``layers/vector.py``)."""

    hidden: int = 128


@dataclass
class FlowConfig:
    """Layer 2 per-modality flow-matching refiner (Eq. 1-3, A13)."""

    # pre: one refiner per modality before the fuser (the paper's "filter before mixing"); post: one refiner on the
    # fused vector before the DNC; off: no refiner and no FM loss (ablations, see README "Architecture switches")
    placement: str = "pre"
    hidden: int = 128
    steps: int = 4
    noise_std: float = 1.0
    # initial gate logit alpha_m per modality (Eq. 3); a modality left out starts at its registry default
    # (freamer_rl.model.modalities.MODALITIES[m].gate_init: vision -5, state / language / vector -3, reward -1)
    gate_init: dict[str, float] = field(default_factory=dict)
    # Score-based adaptive complexity (App. G.4): each refiner picks its Euler step count per row from these choices
    # (paper: [1, 2, 3, 5, 7, 10]) by a straight-through Gumbel-Softmax on E_t ||v(x, t)||^2. Empty: fixed ``steps``.
    adaptive_steps: list[int] = field(default_factory=list)
    adaptive_tau: float = 1.0
    # FM training noise: absolute (noise_std itself) or relative (noise_std times each embedding row's own std, the
    # scale of the Table 13 protocol; a modality with small embeddings is not trained on noise ten times its size)
    noise_scale: str = "absolute"
    # Score-based reliability (placement pre; layers/flow_matching.py): off | gate (the residual gate opens with the
    # refiner's score) | weight (an embedding whose score is unusual for training data weighs less in the mix) | both
    reliability: str = "off"
    reliability_margin: float = 2.0  # the weight starts falling this many std of the training scores above their mean
    # What the FM loss trains the refiners on (Eq. A13's pairs): synthetic (a clean embedding and itself plus Gaussian
    # noise, the paper's) or paired (also the embedding of a corrupted observation and that of its clean copy, from
    # env.clean_copies, with the residual gate trained to land on the clean one; needs a training corruption of those
    # keys: the pairs exist only where the noise is added by the run itself)
    targets: str = "synthetic"


@dataclass
class FNOConfig:
    modes: int = 16
    residual_scale: float = 0.1
    # LayerNorm on the modality-mean (see FNOFuser): keeps the policy input's scale independent of M. Off by default:
    # on MultiRoom-N2-S4 seeds 1 and 2 it did not learn faster (success 0.06 / 0.29 at 61k frames).
    output_norm: bool = False


@dataclass
class DNCConfig:
    enabled: bool = True
    memory_slots: int = 32
    memory_width: int = 64
    # additive: Appendix F.1 as printed, whose memory saturates at the +-10 clamp in long episodes (CartPole: 16-34% of
    # the entries at step 400); bounded: the convex erase/write, |M| <= 1 in any episode (layers/dnc.py). The default
    # stays additive so every published MiniGrid result reproduces (bounded is measured on CartPole only, where it
    # removes the saturation but not the return gap); recipes/gym/cartpole.yaml sets bounded (Pendulum, not measured,
    # keeps additive). A checkpoint whose state predates this field was trained with additive and loads as additive whatever
    # the config says (a warning names this field).
    write: str = "additive"
    # LayerNorm on the DNC's output e_aug, the features both heads read
    output_norm: bool = False


@dataclass
class ModelConfig:
    # Names from freamer_rl.model.modalities.MODALITIES, in the order they are stacked for the FNO fuser (Layer 3).
    modalities: list[str] = field(default_factory=lambda: ["state", "language", "reward"])
    # Env observation keys per modality when they differ from the registry's defaults, e.g. {vector: [observation]}.
    observation_keys: dict[str, list[str]] = field(default_factory=dict)
    # Modalities whose Layer-1 encoder is frozen (kept at its initial or loaded weights, left out of the optimiser),
    # as the CLIP tower always is. Their refiners, the fuser and everything downstream still train.
    freeze_encoders: list[str] = field(default_factory=list)
    embed_dim: int = 128
    # Layer 3: fno (spectral fusion, the paper's), concat (concatenation + MLP to embed_dim), mean (no parameters)
    fusion: str = "fno"
    fusion_hidden: int | None = None  # width of the concat MLP (None: embed_dim); set it to match parameter counts
    # {modality: observation key} of a presence flag (env.presence writes <key>_present: 1 present, 0 dropped) that
    # multiplies the modality's row of the fuser's input, so a dropped modality adds exactly nothing to the mix and its
    # rows are left out of its refiner's FM loss and score statistics (README "Robustness", presence-aware fusion)
    presence_keys: dict[str, str] = field(default_factory=dict)
    cross_modal_heads: int = 4
    head_hidden: int = 128
    # what the value head's gradient reaches: shared (the paper's: the critic loss trains the trunk with the actor)
    # or detached (the critic reads the trunk's features through a stop-gradient; the trunk learns from the policy
    # and auxiliary losses only -- a value loss on returns of ~100 no longer swamps the actor's signal in the trunk)
    critic_input: str = "shared"
    vision: VisionConfig = field(default_factory=VisionConfig)
    language: LanguageConfig = field(default_factory=LanguageConfig)
    state: StateConfig = field(default_factory=StateConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    vector: VectorConfig = field(default_factory=VectorConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    fno: FNOConfig = field(default_factory=FNOConfig)
    dnc: DNCConfig = field(default_factory=DNCConfig)
    # a fixed threshold rule on one observation added to the actor's logits (freamer_rl.model.action_prior)
    action_prior: ActionPriorConfig = field(default_factory=ActionPriorConfig)
    # torch.compile the hot spots that gain from it on CPU: the DNC step (collection, values, and the training loop
    # over time: ~2-3x faster) and the state FNO encoder's maths (~1.4x). Same maths; value checks stay eager.
    # Costs seconds of compiling at the first batch (see README "Speed"; torch caches the kernels on disk). A failed
    # compilation warns once and runs eagerly (counted as compile_fallbacks in progress.csv).
    compile: bool = False


@dataclass
class AuxConfig:
    """Weights of FreamerV1's auxiliary losses (Eq. 6): flow matching, contrastive, FNO smoothness."""

    lambda_fm: float = 0.1
    lambda_cl: float = 0.1
    lambda_smooth: float = 1e-3
    # False: L_smooth (Eq. A16) trains only the FNO fuser (Layer 3); its gradient does not reach the encoders and
    # refiners. True: the literal Eq. 6, which pulls every modality's embedding towards its neighbours' -- towards the
    # constant mission and reward-history rows in MiniGrid, collapsing the state embedding (see losses.py)
    smooth_into_encoders: bool = False


MODEL_RANGES: dict[str, Range] = {
    **{
        f"model.{k}": size_range(WIDTH_LIMIT)
        for k in (
            "embed_dim",
            "head_hidden",
            "fusion_hidden",
            "vector.hidden",
            "flow.hidden",
            "state.channels",
            "reward.channels",
            "dnc.memory_slots",
            "dnc.memory_width",
            "vision.num_slots",
            "language.num_slots",
        )
    },
    **{
        f"model.{k}": size_range(LAYERS_LIMIT)
        for k in (
            "flow.steps",
            "language.layers",
            "language.heads",
            "cross_modal_heads",
            "vision.slot_iters",
            "language.slot_iters",
        )
    },
    "model.flow.noise_std": (NON_NEGATIVE, ">= 0"),
    "model.flow.adaptive_tau": (POSITIVE, "> 0"),
    "model.flow.reliability_margin": (NON_NEGATIVE, ">= 0"),
    "aux.lambda_fm": (NON_NEGATIVE, ">= 0"),
    "aux.lambda_cl": (NON_NEGATIVE, ">= 0"),
    "aux.lambda_smooth": (NON_NEGATIVE, ">= 0"),
}

#: ``ppo.*`` keys of earlier releases that moved to ``aux``.
AUX_RENAMED: dict[str, str] = {
    f"ppo.{k}": f"aux.{k}" for k in ("lambda_fm", "lambda_cl", "lambda_smooth", "smooth_into_encoders")
}
