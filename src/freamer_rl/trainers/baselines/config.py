"""Config schemas of the TorchRL baselines: the shared base (:class:`~freamer_rl.config.sections.BaseConfig`:
env, collector, logging, run, optim) plus each baseline's own sections, with their range tables and validators
(registered in :data:`freamer_rl.config.loader.VALIDATORS`). None carries FreamerV1's sections."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from freamer_rl.config.checks import (
    BATCH_LIMIT,
    LAYERS_LIMIT,
    NON_NEGATIVE,
    POSITIVE,
    UNIT_INTERVAL,
    WIDTH_LIMIT,
    Range,
    size_range,
)
from freamer_rl.config.loader import VALIDATORS
from freamer_rl.config.sections import (
    BASE_RANGES,
    BASE_RENAMED,
    PPO_RANGES,
    BaseConfig,
    OptimConfig,
    PPOConfig,
    check_base,
    check_ppo_layout,
)
from freamer_rl.errors import ConfigError
from freamer_rl.machinery.checks import check_shaping
from freamer_rl.machinery.config import MACHINERY_RANGES, ShapingConfig, SuccessBufferConfig
from freamer_rl.model.action_prior import ActionPriorConfig, check_action_prior
from freamer_rl.run.envs import check_env_options, check_env_writes

__all__ = [
    "NETWORK_KINDS",
    "FEEDFORWARD_KINDS",
    "RECURRENT_KINDS",
    "NETWORK_INITS",
    "lstm_width",
    "NetworkConfig",
    "network_init",
    "check_network",
    "check_baseline_shaping",
    "PPOBaselineConfig",
    "ImpalaSection",
    "ImpalaConfig",
    "DreamerSection",
    "DreamerConfig",
    "ARCHITECTURE_FIELDS",
]


NETWORK_RANGES: dict[str, Range] = {
    "network.hidden": size_range(WIDTH_LIMIT),
    "network.lstm_hidden": size_range(WIDTH_LIMIT),
}

FEEDFORWARD_KINDS = ("mlp", "cnn")
#: an encoder as the feed-forward kind's, then TorchRL's LSTMModule (``trainer: ppo_baseline`` only)
RECURRENT_KINDS = ("mlp_lstm", "cnn_lstm")
NETWORK_KINDS = FEEDFORWARD_KINDS + RECURRENT_KINDS


NETWORK_INITS = ("auto", "orthogonal", "torch_default")


def network_init(net: NetworkConfig) -> str:
    """``network.init`` with ``auto`` resolved: ``torch_default`` for ``kind: mlp`` / ``mlp_lstm``, ``orthogonal``
    for ``cnn`` / ``cnn_lstm`` (the LSTM itself always keeps PyTorch's init)."""
    if net.init != "auto":
        return net.init
    return "torch_default" if net.kind in ("mlp", "mlp_lstm") else "orthogonal"


def lstm_width(net: NetworkConfig) -> int:
    """The LSTM's hidden size of the ``*_lstm`` kinds: ``network.lstm_hidden``, else ``network.hidden``."""
    return net.lstm_hidden if net.lstm_hidden is not None else net.hidden


@dataclass
class NetworkConfig:
    kind: str = "mlp"  # mlp | cnn | mlp_lstm | cnn_lstm (the encoder of mlp / cnn, then an LSTM; ppo_baseline only)
    observation_keys: list[str] = field(default_factory=lambda: ["grid", "direction"])
    hidden: int = 256  # width of the encoder's last layer and of the heads' hidden layer
    shared: bool = False  # one trunk for actor and critic (true) or one encoder each (false)
    cnn_channels: list[int] = field(default_factory=lambda: [32, 64, 64])
    # weight init of the Linear layers: orthogonal (gain sqrt 2, policy output 0.01, critic output 1, zero biases) or
    # PyTorch's own U(+-1/sqrt(fan_in)); auto: torch_default for kind mlp, orthogonal for kind cnn. On N2-S4 the
    # PPO-MLP reaches 95% in ~1,016 episodes with torch_default, ~1,604 with orthogonal (3 seeds; README baselines)
    init: str = "auto"
    # hidden size of the LSTM of the *_lstm kinds (None: network.hidden); trained on ppo.sequence_length sequences
    lstm_hidden: int | None = None
    # kind cnn / cnn_lstm: the key the conv stack reads (None: the one [H, W, C] key among observation_keys); name it
    # when several keys are image-shaped (MiniGrid's 7x7x3 grid beside its RGB view), the others are flattened
    image_key: str | None = None
    # a fixed threshold rule on one observation added to the actor's logits (freamer_rl.model.action_prior)
    action_prior: ActionPriorConfig = field(default_factory=ActionPriorConfig)


def check_network(net: NetworkConfig, kinds: tuple[str, ...] = FEEDFORWARD_KINDS) -> None:
    """Every ``network`` field, named in the error; ``kinds``: those the trainer supports."""
    if net.kind not in kinds:
        others = [k for k in NETWORK_KINDS if k not in kinds]
        note = f" ({', '.join(others)}: trainer ppo_baseline only)" if net.kind in others else ""
        raise ConfigError(f"network.kind: expected one of {', '.join(kinds)}, got {net.kind!r}{note}")
    if not net.observation_keys:
        raise ConfigError("network.observation_keys: expected at least one observation key, got []")
    if len(set(net.observation_keys)) != len(net.observation_keys):
        raise ConfigError(f"network.observation_keys: duplicate keys in {net.observation_keys}")
    if net.image_key is not None and net.image_key not in net.observation_keys:
        raise ConfigError(
            f"network.image_key: {net.image_key!r} is not one of network.observation_keys {net.observation_keys}"
        )
    if net.init not in NETWORK_INITS:
        raise ConfigError(f"network.init: expected one of {', '.join(NETWORK_INITS)}, got {net.init!r}")
    check_action_prior(net.action_prior, "network")
    if len(net.cnn_channels) != 3 or min(net.cnn_channels) < 1:
        raise ConfigError(
            f"network.cnn_channels: expected 3 positive ints (one per conv layer), got {net.cnn_channels}"
        )


#: the shaping terms that need FreamerV1's embeddings (the baselines have none): refused by the baselines
_EMBEDDING_TERMS = {
    "vision_language": "R_VL compares refined embeddings",
    "curiosity": "R_intrinsic reads the fused embedding",
}

#: the machinery's range rows of the ``shaping`` and ``success_buffer`` sections (MACHINERY_RANGES' own)
SHAPING_RANGES: dict[str, Range] = {k: v for k, v in MACHINERY_RANGES.items() if k.startswith("shaping.")}
SUCCESS_BUFFER_RANGES: dict[str, Range] = {k: v for k, v in MACHINERY_RANGES.items() if k.startswith("success_buffer.")}


def check_baseline_shaping(cfg, trainer: str) -> None:
    """The ``shaping`` checks every trainer shares, then the two terms a baseline cannot compute refused by name."""
    check_shaping(cfg)
    for name, why in _EMBEDDING_TERMS.items():
        if getattr(cfg.shaping, name):
            raise ConfigError(
                f"shaping.{name}: {why}, which the {trainer} trainer does not have; set it to 0 (the language "
                "reward, novelty bonus, time penalty and adaptive decay work for every trainer)"
            )
    check_env_writes(cfg)  # shaping terms the env cannot provide (R_lang on Crafter), refused at load
    check_env_options(cfg)  # env.options / env.eval_options the adapter does not take


@dataclass
class PPOBaselineConfig(BaseConfig):
    """``trainer: ppo_baseline``: the shared base, ``ppo`` (FreamerV1's PPO section), ``network``, ``shaping``
    (FreamerV1's section: the language reward, novelty bonus, time penalty and adaptive decay; not the two terms that
    read FreamerV1's embeddings) and ``success_buffer`` (FreamerV1's App. G.3 replay, every ``network.kind``), so a
    comparison can give both sides the same machinery."""

    ppo: PPOConfig = field(default_factory=PPOConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    shaping: ShapingConfig = field(default_factory=ShapingConfig)
    success_buffer: SuccessBufferConfig = field(default_factory=SuccessBufferConfig)

    RANGES: ClassVar[dict[str, Range]] = {
        **BASE_RANGES,
        **PPO_RANGES,
        **NETWORK_RANGES,
        **SHAPING_RANGES,
        **SUCCESS_BUFFER_RANGES,
    }

    def reads_observation(self, key: str) -> bool:
        return key in self.network.observation_keys


def validate_ppo_baseline(cfg: PPOBaselineConfig) -> None:
    check_base(cfg)
    check_ppo_layout(cfg)  # ppo.sequence_length tiles the [envs, T] batch: the *_lstm kinds train on sequences
    check_network(cfg.network, NETWORK_KINDS)
    check_baseline_shaping(cfg, "ppo_baseline")


VALIDATORS[PPOBaselineConfig] = validate_ppo_baseline


@dataclass
class ImpalaSection:
    """IMPALA's algorithm section (``impala:``); its optimiser's lr, eps, clip and schedule are ``optim``'s."""

    frames_per_batch: int = 2048  # frames of one actor process per batch, [env.num_envs, T]
    gamma: float = 0.99
    entropy_coeff: float = 0.01
    critic_coeff: float = 0.5

    rho_clip: float = 1.0  # rho-bar: clip of the importance ratio in the V-trace TD errors and the policy gradient
    c_clip: float = 1.0  # c-bar: clip of the traces c_t (<= rho_clip, the paper's assumption)
    optimizer: str = "adam"  # adam | rmsprop (the IMPALA paper's, with rmsprop_alpha; optim.eps is its eps)
    rmsprop_alpha: float = 0.99
    minibatches: int = 1  # gradient steps per collected batch, on random splits of its frames (1: the paper's)


@dataclass
class ImpalaConfig(BaseConfig):
    """``trainer: impala``: the shared base, ``network`` (as the PPO baseline's), ``impala`` and ``shaping`` (as the
    PPO baseline's: V-trace reads the shaped reward, success is judged on the env's). ``success_buffer`` is there so
    a recipe can say ``enabled: false``; ``enabled: true`` is refused at load (:func:`validate_impala` says why).

    Optimiser: Adam by default, not the paper's RMSprop -- the same optimiser, lr and grad clip as the PPO-MLP baseline
    it is compared with, so the comparison isolates V-trace + asynchronous actors; ``impala.optimizer: rmsprop``
    gives the paper's (and TorchRL's IMPALA example's) choice.
    """

    network: NetworkConfig = field(default_factory=NetworkConfig)
    impala: ImpalaSection = field(default_factory=ImpalaSection)
    shaping: ShapingConfig = field(default_factory=ShapingConfig)
    success_buffer: SuccessBufferConfig = field(default_factory=SuccessBufferConfig)

    RANGES: ClassVar[dict[str, Range]] = {
        **BASE_RANGES,
        **NETWORK_RANGES,
        "impala.frames_per_batch": size_range(BATCH_LIMIT * 16),
        "impala.gamma": (UNIT_INTERVAL, "in (0, 1]"),
        "impala.entropy_coeff": (NON_NEGATIVE, ">= 0"),
        "impala.critic_coeff": (NON_NEGATIVE, ">= 0"),
        "impala.rho_clip": (POSITIVE, "> 0"),
        "impala.rmsprop_alpha": (lambda v: 0 <= v < 1, "in [0, 1)"),
        **SHAPING_RANGES,
        **SUCCESS_BUFFER_RANGES,
    }

    def reads_observation(self, key: str) -> bool:
        return key in self.network.observation_keys

    RENAMED: ClassVar[dict[str, str]] = {
        **BASE_RENAMED,
        **{f"ppo.{k}": f"impala.{k}" for k in ("frames_per_batch", "gamma", "entropy_coeff", "critic_coeff")},
    }


def validate_impala(cfg: ImpalaConfig) -> None:
    check_base(cfg)
    check_network(cfg.network)
    s = cfg.impala
    if s.frames_per_batch % cfg.env.num_envs:
        raise ConfigError(
            f"impala.frames_per_batch ({s.frames_per_batch}) must be divisible by env.num_envs ({cfg.env.num_envs})"
        )
    if not 0 < s.c_clip <= s.rho_clip:
        raise ConfigError(f"impala.c_clip: expected a number in (0, impala.rho_clip={s.rho_clip}], got {s.c_clip}")
    if s.optimizer not in ("adam", "rmsprop"):
        raise ConfigError(f"impala.optimizer: expected 'adam' or 'rmsprop', got {s.optimizer!r}")
    if s.frames_per_batch % s.minibatches:
        raise ConfigError(
            f"impala.minibatches: got {s.minibatches}, must divide impala.frames_per_batch ({s.frames_per_batch})"
        )
    check_baseline_shaping(cfg, "impala")
    if cfg.success_buffer.enabled:
        # IMPALA's V-trace already learns from stale data; the buffer's correction (GePPO) re-centres ClipPPOLoss's
        # ratio on [S, L] sequences, and IMPALA's A2C steps on flat V-trace batches have neither; a replaying IMPALA
        # would also no longer be the published baseline it stands for
        raise ConfigError(
            "success_buffer.enabled: trainer impala has no success buffer (its off-policy correction re-centres "
            "PPO's clipped ratio, which IMPALA's A2C loss on V-trace targets does not have); set it to false, or "
            "use trainer ppo_baseline"
        )


VALIDATORS[ImpalaConfig] = validate_impala


@dataclass
class DreamerSection:
    """DreamerV3 sizes and training schedule (paper defaults in comments; CPU-sized values here)."""

    observation_keys: list[str] = field(default_factory=lambda: ["grid", "direction"])  # uint8 [H,W,C] -> CNN
    stoch_categoricals: int = 16  # paper: 32 (size S) .. 32
    stoch_classes: int = 16  # paper: 32
    deter: int = 256  # paper: 4096 (XL) / 512 (S)
    hidden: int = 256  # MLP width; paper: 512 (S) .. 1024
    mlp_layers: int = 2  # paper: 2 (S) .. 5
    cnn_depth: int = 16  # base channels of the image encoder/decoder; paper: 32 (S)
    cnn_mults: list[int] = field(default_factory=lambda: [2, 3, 4, 4])
    unimix: float = 0.01
    frames_per_batch: int = 256  # env frames collected between learning phases
    replay_capacity: int = 100_000  # env frames kept (oldest dropped)
    batch_size: int = 16  # paper: 16
    sequence_length: int = 32  # paper: 64
    train_every: int = 64  # env frames per update (train ratio = batch_size * sequence_length / train_every)
    prefill_frames: int = 2_000  # frames collected (acting with the untrained actor) before the first update
    horizon: int = 15  # imagination horizon
    gamma: float = 0.997  # paper: 1 - 1/333
    lmbda: float = 0.95
    # the world model's optimiser is the shared ``optim`` section (lr 1e-4, eps 1e-8, grad clip 1000 here)
    actor_lr: float = 3e-5
    value_lr: float = 3e-5
    actor_grad_clip: float = 100.0
    value_grad_clip: float = 100.0
    lambda_dynamic: float = 0.5  # KL(sg(post) || prior); paper 0.5, current reference code 1.0
    lambda_representation: float = 0.1
    free_nats: float = 1.0
    entropy_bonus: float = 3e-4
    slow_critic: float = 1.0  # weight of the slow-critic regulariser (0: off)
    slow_critic_tau: float = 0.02


_DREAMER_POSITIVE = ("actor_lr", "value_lr", "actor_grad_clip", "value_grad_clip")
_DREAMER_NON_NEGATIVE = (
    "lambda_dynamic",
    "lambda_representation",
    "free_nats",
    "entropy_bonus",
    "slow_critic",
    "prefill_frames",
)


def _dreamer_ranges() -> dict[str, Range]:
    ranges: dict[str, Range] = {**BASE_RANGES, "optim.max_grad_norm": (POSITIVE, "> 0")}
    ranges.update({f"dreamer.{n}": (POSITIVE, "> 0") for n in _DREAMER_POSITIVE})
    ranges.update({f"dreamer.{n}": (NON_NEGATIVE, ">= 0") for n in _DREAMER_NON_NEGATIVE})
    ranges.update({f"dreamer.{n}": (UNIT_INTERVAL, "in (0, 1]") for n in ("gamma", "lmbda", "slow_critic_tau")})
    ranges["dreamer.unimix"] = (lambda v: 0 <= v < 1, "in [0, 1)")
    ranges.update({f"dreamer.{n}": size_range(WIDTH_LIMIT) for n in ("deter", "hidden", "cnn_depth")})
    ranges.update({f"dreamer.{n}": size_range(1024) for n in ("stoch_categoricals", "stoch_classes")})
    ranges["dreamer.mlp_layers"] = size_range(LAYERS_LIMIT)
    ranges.update({f"dreamer.{n}": size_range(BATCH_LIMIT) for n in ("batch_size", "sequence_length", "horizon")})
    return ranges


@dataclass
class DreamerOptimConfig(OptimConfig):
    """The world model's Adam with DreamerV3's defaults (a recipe's partial ``optim`` section keeps them)."""

    lr: float = 1e-4
    eps: float = 1e-8
    max_grad_norm: float = 1000.0


@dataclass
class DreamerConfig(BaseConfig):
    """``trainer: dreamer_v3``: the shared base (``optim``: the world model's Adam) and ``dreamer``."""

    optim: DreamerOptimConfig = field(default_factory=DreamerOptimConfig)
    dreamer: DreamerSection = field(default_factory=DreamerSection)

    RANGES: ClassVar[dict[str, Range]] = _dreamer_ranges()
    RENAMED: ClassVar[dict[str, str]] = {
        **BASE_RENAMED,
        "dreamer.model_lr": "optim.lr",
        "dreamer.adam_eps": "optim.eps",
        "dreamer.model_grad_clip": "optim.max_grad_norm",
    }

    def reads_observation(self, key: str) -> bool:
        return key in self.dreamer.observation_keys


def _check_dreamer_section(d: DreamerSection, num_envs: int) -> None:
    """What the range table cannot say: keys, multipliers, and the batch / replay layout."""
    if not d.observation_keys or len(set(d.observation_keys)) != len(d.observation_keys):
        raise ConfigError(f"dreamer.observation_keys: expected distinct observation keys, got {d.observation_keys}")
    if not d.cnn_mults or min(d.cnn_mults) < 1:
        raise ConfigError(f"dreamer.cnn_mults: expected a non-empty list of ints >= 1, got {d.cnn_mults}")
    if d.frames_per_batch % num_envs:
        raise ConfigError(
            f"dreamer.frames_per_batch: must be divisible by env.num_envs ({num_envs}), got {d.frames_per_batch}"
        )
    steps = d.frames_per_batch // num_envs
    if d.sequence_length > steps:
        raise ConfigError(
            f"dreamer.sequence_length: must be <= the steps per env per batch ({steps} = "
            f"dreamer.frames_per_batch / env.num_envs), got {d.sequence_length}"
        )
    # the replay keeps whole [num_envs, steps] rows of one env: capacity_frames // steps sequences of `steps` frames
    held = (d.replay_capacity // steps) * steps
    if held < max(d.frames_per_batch, d.prefill_frames):
        raise ConfigError(
            f"dreamer.replay_capacity: must hold dreamer.frames_per_batch and dreamer.prefill_frames "
            f"({max(d.frames_per_batch, d.prefill_frames)}) in whole sequences of {steps} steps "
            f"(it holds {held} frames), got {d.replay_capacity}"
        )


def validate_dreamer(cfg: DreamerConfig) -> None:
    if cfg.run.init_from:
        raise ConfigError(
            "run.init_from: the dreamer_v3 trainer cannot start from another run's weights (its world model, actor "
            "and critic are not transferred); leave it unset, or chain FreamerV1 / ppo_baseline / impala stages"
        )
    """The shared checks, then the ``dreamer`` layout (the error names the field)."""
    check_base(cfg)
    _check_dreamer_section(cfg.dreamer, cfg.env.num_envs)
    if cfg.collector.num_collectors != 1:
        raise ConfigError(
            f"collector.num_collectors: the DreamerV3 trainer collects in one process (1), got "
            f"{cfg.collector.num_collectors}"
        )


VALIDATORS[DreamerConfig] = validate_dreamer


#: ``dreamer`` fields that shape the networks: a checkpoint only resumes / loads with the same values.
ARCHITECTURE_FIELDS = (
    "observation_keys",
    "stoch_categoricals",
    "stoch_classes",
    "deter",
    "hidden",
    "mlp_layers",
    "cnn_depth",
    "cnn_mults",
)
