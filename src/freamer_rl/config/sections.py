"""The config sections every trainer shares, and the base schema they compose.

:class:`BaseConfig` holds ``env``, ``collector``, ``logging``, ``run`` and ``optim`` (learning rate, Adam eps,
gradient clip, schedule: the one optimiser section, read by every trainer's main optimiser). Each trainer's schema
subclasses it and adds its own sections (BenchMARL's experiment / algorithm / model split): FreamerV1 adds ``model``,
``ppo``, ``aux``, ``shaping``, ``success_buffer``, ``ogm``; the PPO baseline ``ppo`` and ``network``; IMPALA
``impala`` and ``network``; DreamerV3 ``dreamer``. :class:`PPOConfig` is the algorithm section of both PPO trainers.

Number ranges live beside the sections in tables (:data:`BASE_RANGES`, :data:`PPO_RANGES`) that a schema's
``RANGES`` class attribute composes; :func:`freamer_rl.config.checks.check_numbers` applies them.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

from freamer_rl.config.checks import (
    BATCH_LIMIT,
    NON_NEGATIVE,
    POSITIVE,
    UNIT_INTERVAL,
    Range,
    check_collector,
    check_device_name,
    check_logging,
    check_numbers,
    run_name_problem,
    size_range,
)
from freamer_rl.errors import ConfigError

#: kind -> (range check of ``level``, what it must be); integer-only kinds are checked against the key's dtype
CORRUPTION_KINDS: dict[str, tuple[Any, str]] = {
    "gaussian": (lambda v: 0 <= v <= 100, "a noise scale in [0, 100] (times the key's running std)"),
    "salt": (lambda v: 0 <= v <= 1, "a replacement probability in [0, 1]"),
    "dropout": (lambda v: 0 <= v <= 1, "a drop probability in [0, 1]"),
    "dropout_episode": (lambda v: 0 <= v <= 1, "a drop probability in [0, 1] (per episode)"),
    "stale": (lambda v: v >= 1 and float(v).is_integer(), "a whole number of steps >= 1"),
    "noisy_tv": (lambda v: 0 < v <= 1, "the share of the key in (0, 1]"),
}
CORRUPTION_WHEN = ("train", "eval", "both")


@dataclass
class CorruptionConfig:
    """One ``env.corrupt`` entry: observation ``key`` corrupted by ``kind`` at ``level`` during training, evaluation
    or both (:mod:`freamer_rl.run.corruption` says what each kind and level mean). ``channels: [start, stop]``
    restricts it to ``key[..., start:stop]`` (one sensor site of a concatenated vector, e.g. the health env's hand
    IMU ``imu[0:12]``); the key may carry the slice itself, ``key: "imu[0:12]"`` (the CLI's form)."""

    key: str = ""
    kind: str = "gaussian"
    level: float = 1.0
    when: str = "both"
    channels: list[int] | None = None  # [start, stop) of the key's last dim; None: the whole key


@dataclass
class EnvConfig:
    """Which environment to train on. ``adapter`` is an entry point of the ``freamer_rl.envs`` group."""

    adapter: str = "minigrid"
    # Modules imported before the env is built (e.g. a user's package that registers gymnasium ids); gymnasium's
    # ``module:EnvId`` form of ``id`` imports ``module`` the same way.
    imports: list[str] = field(default_factory=list)
    # modality corruption (freamer_rl.run.corruption), e.g. [{key: pixels, kind: gaussian, level: 1.0, when: eval}]
    corrupt: list[CorruptionConfig] = field(default_factory=list)
    # second sensors of one observation, {new_key: source_key} (a float32 copy, written before any corruption), so a
    # benchmark can corrupt one of two redundant views: {grid2: grid} (freamer_rl.run.corruption.SensorCopy)
    copies: dict[str, str] = field(default_factory=dict)
    # observations to keep a clean copy of, <key>_clean (same spec, written before any corruption; no policy reads
    # it unless told to): the target of FreamerV1's paired denoising (model.flow.targets=paired)
    clean_copies: list[str] = field(default_factory=list)
    # observations whose <key>_present flag (float, 1 = present) every env of the run writes: 0 where a dropout
    # corruption dropped the key, 1 otherwise (freamer_rl.run.corruption.PresenceFlag; model.presence_keys reads it)
    presence: list[str] = field(default_factory=list)
    id: str = "MiniGrid-MultiRoom-N2-S4-v0"
    num_envs: int = 8
    reward_history: int = 8
    max_mission_tokens: int = 16
    # adapters whose reset is costly (Crafter's world generation) prepare the next episode in this many worker
    # processes while the current one runs; 0: inline. An adapter without the option refuses a value > 0
    reset_workers: int = 0
    # keyword options of the adapter's env factory, for adapters that declare them (EnvAdapter.option_names), e.g.
    # the health env's {subjects: [101, 102], episode_length: 120, rate_hz: 0.2}; another name is refused
    options: dict[str, Any] = field(default_factory=dict)
    # options that replace env.options in evaluation envs (every evaluator's episodes): e.g. {subjects: [104]} to
    # evaluate on a subject left out of training (leave-one-subject-out)
    eval_options: dict[str, Any] = field(default_factory=dict)


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
    # a return level (e.g. CartPole's 475) whose first reaching by the windowed mean return the summary records
    return_target: float | None = None
    progress_bar: bool = True


@dataclass
class RunConfig:
    seed: int = 0
    total_frames: int = 100_000
    output_dir: str = "runs"
    name: str | None = None
    threads: int = 1
    # torch threads while learning (advantages and updates; None: run.threads), back to run.threads for collection:
    # e.g. 2 on a 2-core machine whose second core generates Crafter worlds during collection (env.reset_workers)
    update_threads: int | None = None
    device: str = "cpu"
    stop_at_success: float | None = None  # stop early once the windowed success rate reaches this
    # Transfer: start a fresh run from the model weights of another run (its directory, or a checkpoint file), e.g.
    # a simpler env of a curriculum. Only the weights: optimiser, frames and statistics start anew. The model
    # sections of both configs must match; a run resuming its own checkpoint ignores this.
    init_from: str | None = None


@dataclass
class OptimConfig:
    """The main optimiser of every trainer (Adam): ``optim.lr``, ``optim.eps``, ``optim.max_grad_norm``,
    ``optim.lr_schedule``. Auxiliary optimisers (the curiosity model's) have their own settings in their section."""

    lr: float = 1e-4
    # "constant", or "linear": decays to 0 at run.total_frames (as in SB3/RL-Zoo's PPO recipes); the rate follows the
    # frames done, so a resume continues the decay, and raising run.total_frames on resume stretches it
    lr_schedule: str = "constant"
    eps: float = 1e-5
    max_grad_norm: float = 1.0


@dataclass
class PPOConfig:
    """PPO's algorithm section (paper Table A20 defaults), shared by FreamerV1 and the PPO baseline."""

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


#: Ranges of the shared sections' numbers (every other int must be >= 1 and every float finite).
BASE_RANGES: dict[str, Range] = {
    "env.reward_history": (NON_NEGATIVE, ">= 0 (0: no reward history)"),
    "env.reset_workers": (lambda v: 0 <= v <= 64, "in [0, 64] (0: resets inline)"),
    "run.seed": (lambda v: 0 <= v < 2**32, "in [0, 2**32 - 1]"),
    "run.stop_at_success": (UNIT_INTERVAL, "in (0, 1]"),
    "env.num_envs": size_range(4_096),
    "optim.lr": (POSITIVE, "> 0"),
    "optim.eps": (POSITIVE, "> 0"),
    "optim.max_grad_norm": (POSITIVE, "> 0"),
    "collector.ray_collector_cpus": (POSITIVE, "> 0"),
}

PPO_RANGES: dict[str, Range] = {
    "ppo.frames_per_batch": size_range(16 * BATCH_LIMIT),
    "ppo.minibatch_size": size_range(16 * BATCH_LIMIT),
    "ppo.sequence_length": size_range(BATCH_LIMIT),
    "ppo.epochs": size_range(1_000),
    "ppo.clip_epsilon": (POSITIVE, "> 0"),
    "ppo.gamma": (UNIT_INTERVAL, "in (0, 1]"),
    "ppo.gae_lambda": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "ppo.entropy_coeff": (NON_NEGATIVE, ">= 0"),
    "ppo.critic_coeff": (NON_NEGATIVE, ">= 0"),
}

#: Keys of earlier releases, refused with the key that replaced them (``freamer_rl.config.loader``).
BASE_RENAMED: dict[str, str] = {
    **{
        f"ppo.{old}": f"optim.{new}"
        for old, new in (
            ("lr", "lr"),
            ("adam_eps", "eps"),
            ("max_grad_norm", "max_grad_norm"),
            ("lr_schedule", "lr_schedule"),
        )
    },
}


@dataclass
class BaseConfig:
    """``env``, ``collector``, ``logging``, ``run``, ``optim``: what the run infrastructure reads."""

    env: EnvConfig = field(default_factory=EnvConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    run: RunConfig = field(default_factory=RunConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)

    #: number ranges of this schema (a subclass composes the tables of its sections)
    RANGES: ClassVar[dict[str, Range]] = BASE_RANGES
    #: old dotted keys -> their replacement, refused with a message naming the new key
    RENAMED: ClassVar[dict[str, str]] = BASE_RENAMED

    def reads_observation(self, key: str) -> bool:
        """Whether this trainer's model reads observation ``key``: env adapters skip costly observations nobody reads
        (MiniGrid renders pixels only when asked). A schema with a model says which keys it reads."""
        return False


#: suffix of the clean copy ``env.clean_copies`` writes beside an observation
CLEAN_SUFFIX = "_clean"


def clean_key(key: str) -> str:
    """The key of ``key``'s clean copy (``env.clean_copies``)."""
    return f"{key}{CLEAN_SUFFIX}"


def check_base(cfg: BaseConfig) -> None:
    """Every number against the schema's ``RANGES`` table, then names and choices of the shared sections: run name
    and device, optim schedule, collector, logging."""
    check_numbers(cfg)
    # the run directory is run.output_dir/run.name: a name with separators or '..' would write elsewhere
    if cfg.run.name and (problem := run_name_problem(cfg.run.name)):
        raise ConfigError(f"run.name: {problem}")
    check_device_name(cfg.run.device)
    if cfg.optim.lr_schedule not in ("constant", "linear"):
        raise ConfigError(f"optim.lr_schedule: expected 'constant' or 'linear', got {cfg.optim.lr_schedule!r}")
    check_collector(cfg.collector)
    check_logging(cfg.logging)
    check_corruption(cfg.env.corrupt)
    for new, source in cfg.env.copies.items():
        if problem := run_name_problem(new) if new else "an empty key":
            raise ConfigError(f"env.copies: {new!r} is no observation key name ({problem})")
        if new == source:
            raise ConfigError(f"env.copies.{new}: a key cannot be a copy of itself")
    if len(set(cfg.env.clean_copies)) != len(cfg.env.clean_copies):
        raise ConfigError(f"env.clean_copies: a key is named twice in {cfg.env.clean_copies}")
    if len(set(cfg.env.presence)) != len(cfg.env.presence):
        raise ConfigError(f"env.presence: a key is named twice in {cfg.env.presence}")
    for key in cfg.env.presence:
        if problem := run_name_problem(key) if key else "an empty key":
            raise ConfigError(f"env.presence: {key!r} is no observation key name ({problem})")
    for key in cfg.env.clean_copies:
        if problem := run_name_problem(key) if key else "an empty key":
            raise ConfigError(f"env.clean_copies: {key!r} is no observation key name ({problem})")
        if cfg.reads_observation(clean_key(key)):
            raise ConfigError(
                f"env.clean_copies: the model reads {clean_key(key)!r}, the clean copy of {key!r}: a policy must not "
                "see the uncorrupted value (the copy is a training target only)"
            )


def check_corruption_kind(kind: str, level: Any, where: str) -> None:
    """``kind`` is one of :data:`CORRUPTION_KINDS` and ``level`` a number it takes; one ConfigError line otherwise."""
    if kind not in CORRUPTION_KINDS:
        raise ConfigError(f"{where}.kind: expected one of {', '.join(CORRUPTION_KINDS)}, got {kind!r}")
    ok, expected = CORRUPTION_KINDS[kind]
    if not (isinstance(level, (int, float)) and math.isfinite(level) and ok(level)):
        raise ConfigError(f"{where}.level: {kind} needs {expected}, got {level!r}")


def check_corruption(entries: list[CorruptionConfig]) -> None:
    """Every ``env.corrupt`` entry's kind, level and phase (whether the key exists and fits the kind is checked when
    the env is built)."""
    for i, c in enumerate(entries):
        check_corruption_entry(c, f"env.corrupt[{i}]")


_KEY_SLICE = re.compile(r"^(?P<key>[^\[\]]+)\[(?P<start>-?\d+):(?P<stop>-?\d+)\]$")


def corruption_target(c: CorruptionConfig, where: str) -> tuple[str, tuple[int, int] | None]:
    """``(key, (start, stop) or None)`` of an entry: ``channels`` or the key's own ``[start:stop]`` suffix (both
    given must agree). Checks the slice's form (two integers, ``0 <= start < stop``); whether ``stop`` fits the key's
    last dim is checked when the env is built."""
    key, channels = c.key, c.channels
    if "[" in key or "]" in key:
        found = _KEY_SLICE.fullmatch(key)
        if found is None:
            raise ConfigError(f"{where}.key: {key!r}: expected KEY or KEY[start:stop] (e.g. imu[0:12])")
        key, sliced = found["key"], [int(found["start"]), int(found["stop"])]
        if channels is not None and list(channels) != sliced:
            raise ConfigError(f"{where}.channels: {list(channels)} disagrees with the key's slice {sliced}")
        channels = sliced
    if channels is None:
        return key, None
    if (
        not isinstance(channels, (list, tuple))
        or len(channels) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in channels)
    ):
        raise ConfigError(f"{where}.channels: expected [start, stop], two integers, got {channels!r}")
    start, stop = channels
    if not 0 <= start < stop:
        raise ConfigError(f"{where}.channels: expected 0 <= start < stop, got [{start}, {stop}]")
    return key, (start, stop)


def check_corruption_entry(c: CorruptionConfig, where: str) -> None:
    """One corruption entry's key (and slice), kind, level and phase; ``where`` names it in the error
    (``env.corrupt[0]``)."""
    if not c.key:
        raise ConfigError(f"{where}.key: name the observation key to corrupt (e.g. pixels, grid, mission_tokens)")
    corruption_target(c, where)
    check_corruption_kind(c.kind, c.level, where)
    if c.when not in CORRUPTION_WHEN:
        raise ConfigError(f"{where}.when: expected train, eval or both, got {c.when!r}")


def check_ppo_layout(cfg: Any) -> None:
    """``ppo`` batch layout: frames per batch, sequences and minibatches must tile the collected ``[envs, T]``."""
    p = cfg.ppo
    envs_total = cfg.env.num_envs * cfg.collector.num_collectors
    if p.frames_per_batch % envs_total:
        raise ConfigError(
            f"ppo.frames_per_batch ({p.frames_per_batch}) must be divisible by env.num_envs * "
            f"collector.num_collectors ({envs_total})"
        )
    steps = p.frames_per_batch // envs_total
    if steps % p.sequence_length:
        raise ConfigError(
            f"ppo.sequence_length ({p.sequence_length}) must divide the steps per env per batch ({steps}"
            " = ppo.frames_per_batch / (env.num_envs * collector.num_collectors))"
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
