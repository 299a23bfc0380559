"""Typed run configuration: dataclass schema, YAML recipes, dotted command-line overrides.

A recipe is a YAML mapping whose keys mirror :class:`FreamerConfig`. Loading validates every key and type and
raises :class:`ConfigError` naming the dotted field, e.g. ``ppo.lr: expected float, got str 'fast'``.

    cfg = load_config("recipes/minigrid_multiroom_n2s4.yaml", overrides=["ppo.lr=3e-4", "run.seed=1"])
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable
from typing import Any

import yaml

from freamer_rl.errors import FreamerError


class ConfigError(FreamerError, ValueError):
    """A recipe or override is invalid; the message names the dotted field."""


@dataclass
class EnvConfig:
    """Which environment to train on. ``adapter`` is an entry point of the ``freamer_rl.envs`` group."""

    adapter: str = "minigrid"
    id: str = "MiniGrid-MultiRoom-N2-S4-v0"
    num_envs: int = 8
    reward_history: int = 8
    max_mission_tokens: int = 16


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


@dataclass
class VectorConfig:
    """Encoder of the ``vector`` modality (plain vector observations, see ``layers/vector.py``)."""

    hidden: int = 128


@dataclass
class FlowConfig:
    """Layer 2 per-modality flow-matching refiner (Eq. 1-3, A13)."""

    hidden: int = 128
    steps: int = 4
    noise_std: float = 1.0
    gate_init: dict[str, float] = field(
        default_factory=lambda: {"vision": -5.0, "state": -3.0, "language": -3.0, "reward": -1.0}
    )
    # Score-based adaptive complexity (App. G.4): each refiner picks its Euler step count per row from these choices
    # (paper: [1, 2, 3, 5, 7, 10]) by a straight-through Gumbel-Softmax on E_t ||v(x, t)||^2. Empty: fixed ``steps``.
    adaptive_steps: list[int] = field(default_factory=list)
    adaptive_tau: float = 1.0


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


@dataclass
class ModelConfig:
    # Names from freamer_rl.modalities.MODALITIES, in the order they are stacked for the FNO fuser (Layer 3).
    modalities: list[str] = field(default_factory=lambda: ["state", "language", "reward"])
    # Env observation keys per modality when they differ from the registry's defaults, e.g. {vector: [observation]}.
    observation_keys: dict[str, list[str]] = field(default_factory=dict)
    # Modalities whose Layer-1 encoder is frozen (kept at its initial or loaded weights, left out of the optimiser),
    # as the CLIP tower always is. Their refiners, the fuser and everything downstream still train.
    freeze_encoders: list[str] = field(default_factory=list)
    embed_dim: int = 128
    cross_modal_heads: int = 4
    head_hidden: int = 128
    vision: VisionConfig = field(default_factory=VisionConfig)
    language: LanguageConfig = field(default_factory=LanguageConfig)
    state: StateConfig = field(default_factory=StateConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    vector: VectorConfig = field(default_factory=VectorConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    fno: FNOConfig = field(default_factory=FNOConfig)
    dnc: DNCConfig = field(default_factory=DNCConfig)
    # torch.compile the hot spots that gain from it on CPU: the DNC step (collection, values, and the training loop
    # over time: ~2-3x faster) and the state FNO encoder's maths (~1.4x). Same maths; value checks stay eager.
    # Costs seconds of compiling at the first batch (see README "Speed"; torch caches the kernels on disk). A failed
    # compilation warns once and runs eagerly (counted as compile_fallbacks in progress.csv).
    compile: bool = False


@dataclass
class PPOConfig:
    """PPO and auxiliary-loss settings (paper Table A20 defaults, tuned where the benchmark showed better)."""

    lr: float = 1e-4
    # "constant", or "linear": decays to 0 at run.total_frames (as in SB3/RL-Zoo's PPO recipes); the rate follows the
    # frames done, so a resume continues the decay, and raising run.total_frames on resume stretches it
    lr_schedule: str = "constant"
    adam_eps: float = 1e-5
    max_grad_norm: float = 1.0
    clip_epsilon: float = 0.2
    epochs: int = 4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    entropy_coeff: float = 0.01
    critic_coeff: float = 0.5
    normalize_advantage: bool = True
    frames_per_batch: int = 2048
    sequence_length: int = 16
    minibatch_size: int = 256  # frames per minibatch (= sequences * sequence_length)
    lambda_fm: float = 0.1
    lambda_cl: float = 0.1
    lambda_smooth: float = 1e-3
    # False: L_smooth (Eq. A16) trains only the FNO fuser (Layer 3); its gradient does not reach the encoders and
    # refiners. True: the literal Eq. 6, which pulls every modality's embedding towards its neighbours' -- towards the
    # constant mission and reward-history rows in MiniGrid, collapsing the state embedding (see losses.py)
    smooth_into_encoders: bool = False


@dataclass
class CollectorConfig:
    num_collectors: int = 1  # > 1: TorchRL multi-process synchronous collection
    backend: str = "local"  # local: this machine's processes | ray: Ray actors (the `ray` extra), here or a cluster
    ray_address: str | None = None  # None: start a local Ray instance; "auto" or "host:6379": join a running cluster
    ray_num_cpus: int | None = None  # CPUs of a locally started Ray instance (None: all); only with ray_address None
    ray_collector_cpus: float = 1.0  # CPUs Ray reserves per collector actor


@dataclass
class LoggingConfig:
    backend: str = "csv"  # csv | wandb | tensorboard
    log_every_batches: int = 1
    checkpoint_every_frames: int = 20_000
    success_window: int = 100
    progress_bar: bool = True


@dataclass
class RunConfig:
    seed: int = 0
    total_frames: int = 100_000
    output_dir: str = "runs"
    name: str | None = None
    threads: int = 1
    device: str = "cpu"
    stop_at_success: float | None = None  # stop early once the windowed success rate reaches this
    # Transfer: start a fresh run from the model weights of another run (its directory, or a checkpoint file), e.g.
    # a simpler env of a curriculum. Only the weights: optimiser, frames and statistics start anew. The model
    # sections of both configs must match; a run resuming its own checkpoint ignores this.
    init_from: str | None = None


@dataclass
class LanguageRewardConfig:
    """R_lang = s_match * r_scale + b_goal + b_prox (App. A.2, Eq. A10) from the parsed mission (App. A.1)."""

    weight: float = 0.0  # lambda_lang (Table A20: 0.2); 0 = off
    parser: str = "regex"  # regex | llm (a causal LM through transformers, from llm_path)
    llm_path: str | None = None  # local directory of e.g. Qwen2.5-1.5B-Instruct (config, tokenizer, weights)
    r_scale: float = 0.1  # per step while the current target is in view
    goal_bonus: float = 1.0  # once per target reached (key carried, door opened, goal reached)
    proximity_bonus: float = 0.1  # per cell of shortest-path distance gained towards the current target


@dataclass
class NoveltyConfig:
    """Count-based novelty bonus of the NovelD family (``freamer_rl.exploration.NoveltyBonus``)."""

    weight: float = 0.0  # 0 = off
    alpha: float = 0.5  # NovelD: bonus = max(N(s') - alpha * N(s), 0) on the first visit of s' in an episode
    keys: list[str] = field(default_factory=lambda: ["grid", "direction"])  # observation entries hashed


@dataclass
class ShapingConfig:
    """Reward terms added to the env reward for PPO (App. G.1-G.2, A.5). Success is still judged on the env reward.

    shaped = r_env + decay * (sum of weight * term) - time_penalty * (1 + success_rate), with decay =
    max(1 - 1.25 * success_rate, 0) when ``adaptive`` (G.2), else 1.
    """

    adaptive: bool = False
    language: LanguageRewardConfig = field(default_factory=LanguageRewardConfig)
    vision_language: float = 0.0  # lambda_VL (Table A20: 0.1): cosine of the refined vision (or state) and language
    curiosity: float = 0.0  # lambda_intrinsic (Table A20: 0.2): forward-model prediction error on the fused embedding
    novelty: NoveltyConfig = field(default_factory=NoveltyConfig)
    time_penalty: float = 0.0  # alpha of P_time (App. A.5; 0.02 recommended with the language reward)


@dataclass
class SuccessBufferConfig:
    """Successful episodes replayed into PPO (App. G.3) with V-trace targets and truncated importance weights."""

    enabled: bool = False
    mix: float = 0.25  # fraction of each minibatch's sequences drawn from the buffer
    capacity: int = 512  # sequences kept (oldest dropped first)
    rho_clip: float = 1.0  # truncation of the importance weights (V-trace rho-bar = c-bar)


@dataclass
class OGMConfig:
    """OGM-GE gate modulation driven by each modality's FM-loss convergence (Section 4.3.5, Appendix K)."""

    mode: str = "none"  # none | A (gate logits only, lr x lr_scale) | B (all FM parameters)
    alpha: float = 0.5  # modulation strength: coefficient 1 - tanh(alpha * relu(discrepancy - 1))
    lr_scale: float = 10.0  # Mode A learning-rate amplification of the gate logits
    noise: bool = True  # GE: Gaussian noise with the gradient's own std
    ema: float = 0.9  # smoothing of the per-modality FM losses


@dataclass
class FreamerConfig:
    env: EnvConfig = field(default_factory=EnvConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    run: RunConfig = field(default_factory=RunConfig)
    shaping: ShapingConfig = field(default_factory=ShapingConfig)
    success_buffer: SuccessBufferConfig = field(default_factory=SuccessBufferConfig)
    ogm: OGMConfig = field(default_factory=OGMConfig)


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
    raise ConfigError(f"{path}: unsupported field type {tp}")


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


def _merge(base: dict, update: dict) -> dict:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict) and key != "gate_init":
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"ppo.lr=3e-4"`` -> (["ppo", "lr"], 3e-4). The value is parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"override '{text}' must look like dotted.key=value")
    key, raw = text.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"override '{text}' has an empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
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


#: The recipe's top-level key naming its trainer (an entry of :data:`freamer_rl.trainers.TRAINERS`).
TRAINER_KEY = "trainer"
#: The trainer of a recipe without a ``trainer:`` key (every MiniGrid / gym recipe written before the key existed).
DEFAULT_TRAINER = "minigrid_ppo"
#: Cross-field validator per schema dataclass, run after the typed build; a domain's config module registers its own
#: (the health one: ``VALIDATORS[HealthConfig] = validate_health_config``).
VALIDATORS: dict[type, Callable[[Any], None]] = {}


def config_from_dict(data: dict | None, schema: type | None = None) -> Any:
    """Build and validate a ``schema`` instance (default :class:`FreamerConfig`) from a plain mapping.

    Unknown keys and wrong types raise :class:`ConfigError` naming the dotted field; then the schema's registered
    validator (:data:`VALIDATORS`) runs its cross-field checks. A top-level ``trainer:`` entry is not a field of
    any schema and is dropped here (:func:`split_trainer` reads it).
    """
    schema = FreamerConfig if schema is None else schema
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"a recipe must be a YAML mapping, got {type(data).__name__}")
    data = {k: v for k, v in data.items() if k != TRAINER_KEY}
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
        _check_recipe_file(path)  # duplicate keys, an empty file (helpers above validate)
        try:
            data = yaml.safe_load(path.read_text()) or {}
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


def recipe_trainer(path: str | Path, overrides: list[str] | None = None) -> str:
    """The trainer a recipe names (its ``trainer:`` key after ``overrides``; :data:`DEFAULT_TRAINER` without one)."""
    return split_trainer(read_recipe(path, overrides), str(path))[0]


def load_config(
    path: str | Path | None = None, overrides: list[str] | None = None, schema: type | None = None
) -> Any:
    """Load a YAML recipe (or the defaults when ``path`` is None), apply dotted overrides, build and validate.

    ``schema`` None: the schema of the recipe's ``trainer:`` (:data:`freamer_rl.trainers.TRAINERS`; no key means
    :data:`DEFAULT_TRAINER`, whose schema is :class:`FreamerConfig`). An explicit ``schema`` must match the recipe's
    trainer when the recipe names one (``load_config("recipes/health/health_mlp.yaml", schema=HealthConfig)``).
    """
    from freamer_rl.trainers import get_trainer

    source = str(path) if path is not None else "defaults"
    raw = read_recipe(path, overrides)
    name, data = split_trainer(raw, source)
    spec = get_trainer(name, source)
    if schema is not None and TRAINER_KEY in raw and spec.schema is not schema:
        raise ConfigError(
            f"{source}: {TRAINER_KEY}: {name!r} recipes are {spec.schema.__name__}s, not {schema.__name__}s"
        )
    return config_from_dict(data, schema if schema is not None else spec.schema)


def config_to_dict(cfg: FreamerConfig) -> dict:
    return dataclasses.asdict(cfg)


def _check_recipe_file(path: Path) -> None:
    """Duplicate keys and an empty file (:func:`freamer_rl.config_checks.check_recipe_file`)."""
    from freamer_rl.config_checks import check_recipe_file

    check_recipe_file(path)


def validate(cfg: FreamerConfig) -> None:
    """Every value of a built config: one ConfigError line naming the dotted field, the value and what is allowed.

    Types and unknown keys are checked while building; here: names and choices, every number's range (generically,
    :data:`freamer_rl.config_checks.RANGES`), sizes that must fit each other, and the batch layout. CUDA visibility
    of ``run.device`` is checked when a run starts (:func:`freamer_rl.config_checks.resolve_device`).
    """
    from freamer_rl.config_checks import check_model_shapes, check_names, check_numbers

    check_names(cfg)
    check_numbers(cfg)
    check_model_shapes(cfg)
    p = cfg.ppo
    if p.lr_schedule not in ("constant", "linear"):
        raise ConfigError(f"ppo.lr_schedule: expected 'constant' or 'linear', got {p.lr_schedule!r}")
    envs_total = cfg.env.num_envs * cfg.collector.num_collectors
    if p.frames_per_batch % envs_total:
        raise ConfigError(
            f"ppo.frames_per_batch ({p.frames_per_batch}) must be divisible by env.num_envs * "
            f"collector.num_collectors ({envs_total})"
        )
    steps = p.frames_per_batch // envs_total
    if steps % p.sequence_length:
        raise ConfigError(
            f"ppo.sequence_length ({p.sequence_length}) must divide the steps per env per batch ({steps} = "
            f"ppo.frames_per_batch / (env.num_envs * collector.num_collectors))"
        )
    if p.frames_per_batch % p.minibatch_size:  # else an epoch draws short minibatches and repeats sequences
        raise ConfigError(
            f"ppo.minibatch_size ({p.minibatch_size}) must divide ppo.frames_per_batch ({p.frames_per_batch})"
        )
    if p.minibatch_size % p.sequence_length or p.minibatch_size > p.frames_per_batch:
        raise ConfigError(
            f"ppo.minibatch_size ({p.minibatch_size}) must be a multiple of ppo.sequence_length "
            f"({p.sequence_length}) and at most ppo.frames_per_batch ({p.frames_per_batch})"
        )


VALIDATORS[FreamerConfig] = validate  # registered here, after validate's definition
