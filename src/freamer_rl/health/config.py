"""Typed configuration of the health domain (:class:`HealthConfig`, recipes ``recipes/health/health_*.yaml``).

Loaded by the one loader of :mod:`freamer_rl.config.loader` (``load_config(path, overrides, schema=HealthConfig)``, or with no
``schema`` from a recipe holding ``trainer: health``); this module only declares the schema, registers its cross-field
validator and keeps the domain's constants in one place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import torch

from freamer_rl.config.checks import (
    BATCH_LIMIT,
    LAYERS_LIMIT,
    WIDTH_LIMIT,
    check_logging,
    check_numbers,
    run_name_problem,
    size_range,
)
from freamer_rl.config.loader import VALIDATORS, config_from_dict, load_config
from freamer_rl.config.sections import BASE_RANGES, CorruptionConfig, LoggingConfig, RunConfig, check_corruption
from freamer_rl.data import PROTOCOL_SUBJECTS
from freamer_rl.errors import ConfigError
from freamer_rl.health.encoders import ENCODER_KINDS, MODALITIES
from freamer_rl.world_model.heads import REWARD_HEADS
from freamer_rl.world_model.imagination import RETURN_NORMS

__all__ = [
    "ACTION_NAMES",
    "REFERENCE_POLICIES",
    "HealthEnvConfig",
    "HealthEncoderConfig",
    "HealthWorldModelConfig",
    "HealthImaginationConfig",
    "HealthCollectConfig",
    "HealthEvalConfig",
    "HealthLoggingConfig",
    "HealthRunConfig",
    "HealthConfig",
    "validate_health_config",
    "check_subjects",
    "load_health_config",
    "health_config_from_dict",
    "health_config_to_dict",
    "explore_probs",
    "NUM_ACTIONS",
    "OBS_KEYS",
]

#: Observation keys the world model reads and reconstructs (their sizes are read from the env's observation spec).
OBS_KEYS: tuple[str, ...] = ("imu", "hr_features")
#: Number of actions the schema validates ``collect.explore_probs`` against; :func:`~freamer_rl.health.agent.env_dims`
#: checks it against the env's action spec when an agent is built.
NUM_ACTIONS = 5
#: env id of synthetic subjects with their own activity plans (``freamer_rl_envs.health.VARIED_ENV_ID``)
VARIED_ENV_ID = "pamap2-health-varied"


# ----------------------------------------------------------------------------------------------------------------------
# schema
# ----------------------------------------------------------------------------------------------------------------------
#: action names of the health env, in index order (``freamer_rl_envs.health.HEALTH_ACTIONS``; the library does not
#: import envs); the reference policies of :mod:`freamer_rl.health.reference` that ``eval.references`` may name
ACTION_NAMES: tuple[str, ...] = ("continue", "rest", "increase", "change", "alert")
REFERENCE_POLICIES: tuple[str, ...] = (*ACTION_NAMES, "random", "hr_threshold", "hr_controller", "oracle")


@dataclass
class HealthEnvConfig:
    """Real health env (``freamer_rl_envs.health.make_health_env`` through the ``health`` adapter entry point)."""

    adapter: str = "health"
    id: str = "pamap2-health"  # pamap2-health-varied: synthetic subjects with their own activity plans
    data_dir: str | None = None  # PAMAP2 root or Protocol folder; None = embedded synthetic subjects
    subjects: list[int] | None = None  # training subjects (101-109); None: all files found (real) or 101-103
    num_envs: int = 8  # batch of the training env (simultaneous subjects)
    episode_length: int = 120  # steps (0.2 Hz: 10 minutes)
    rate_hz: float = 0.2  # 5 s a step, so that the imagination horizon spans the heart-rate dynamics
    reward_weights: list[float] = field(default_factory=lambda: [2.0, 1.0, 0.5])  # Eq. A11
    synthetic_duration_s: float = 1800.0
    data_seed: int = 0
    # sensor corruption (freamer_rl.run.corruption, the same entries as every trainer's env.corrupt) of the keys the
    # world model reads, imu (one site: imu[0:12] hand, imu[12:24] chest, imu[24:36] ankle) or hr_features:
    # when train corrupts the collected data, eval the final evaluation, both both; freamer-rl health corruption /
    # eval --corrupt corrupt a trained run's evaluation on their own
    corrupt: list[CorruptionConfig] = field(default_factory=list)


@dataclass
class HealthEncoderConfig:
    """Observation encoder (Table 15 rows); fields not used by ``kind`` are ignored."""

    kind: str = "foundation"  # mlp | cnn | slotattn | foundation
    embed_dim: int = 128  # E, the RSSM's o_t^embed size
    hidden: int = 128  # MLP / HR-MLP width
    mlp_layers: int = 2  # mlp
    cnn_channels: int = 32  # cnn
    dim: int = 64  # slotattn / foundation: modality width d
    heads: int = 4
    hr_tokens: int = 4
    fm_hidden: int = 128  # foundation: velocity MLP width (Table A20)
    fm_steps: int = 4  # Euler steps (Table A20)
    gate_init: dict[str, float] = field(default_factory=lambda: {"imu": -1.0, "heart_rate": -1.0})
    fm_noise_std: float = 1.0
    fno_modes: int = 16
    fno_residual_scale: float = 0.1
    memory_slots: int = 32
    memory_width: int = 64


@dataclass
class HealthWorldModelConfig:
    """RSSM world model (Appendix J.1/J.3, Table A20) and its training."""

    deter_dim: int = 256
    stoch_dim: int = 64
    hidden: int = 256
    beta: float = 1.0  # J.3 (Table A20 lists 0.5)
    free_nats: float = 1.0
    lr: float = 1e-4
    adam_eps: float = 1e-5
    grad_clip: float = 1.0
    batch_size: int = 16  # slices per gradient step
    seq_len: int = 32  # steps per slice (the loss sees T + 1 = 33 observations)
    train_steps: int = 50  # gradient steps per iteration
    prefill_train_steps: int = 0  # extra gradient steps right after the random prefill
    kl_balance: float | None = None  # None: the paper's KL(q || p); alpha: alpha KL(sg(q)||p) + (1-alpha) KL(q||sg(p))
    recon_norm: bool = True  # standardised reconstruction targets (WorldModel.recon_norm: keeps the HR features)
    reward_scale: float = 1.0  # weight of L_rew in Eq. A27
    # mse: an MLP trained by MSE (the paper); twohot: DreamerV3's symlog two-hot (255 bins on [-20, 20] in symlog
    # space, cross-entropy; the prediction is symexp of the expected bin) -- freamer_rl.world_model.heads
    reward_head: str = "mse"
    ensemble: int = 1  # K reward heads (independent inits); their spread feeds imagination.uncertainty_penalty
    lambda_fm: float = 0.1  # lambda_FM(WM), Table A20 (foundation encoder only)
    lambda_smooth: float = 1e-3  # lambda_s of Eq. A16 (foundation encoder only)


@dataclass
class HealthImaginationConfig:
    """Policy learning in imagination (Appendix J.4; Table A20 PPO settings)."""

    horizon: int = 15
    lr: float = 1e-4
    adam_eps: float = 1e-5
    clip_epsilon: float = 0.2
    epochs: int = 4
    num_minibatches: int = 4
    gamma: float = 0.99
    lmbda: float = 0.95
    entropy_coeff: float = 0.01
    critic_coeff: float = 0.5
    max_grad_norm: float = 1.0
    num_seeds: int = 256  # posterior latents per update (imagined rollouts: num_seeds x horizon)
    updates: int = 4  # ImaginationPPO updates per iteration
    lambda_return_actor_critic: bool = False
    # the continuation head (trained in Eq. A27 by BCE on 1 - terminated; the env terminates at HR >= 200 bpm) ends an
    # imagined rollout: threshold (c < 0.5) | sample (Bernoulli) | never; GAE stops bootstrapping at a predicted
    # termination and the steps after it are dropped from the loss (valid_imagination_mask)
    done_mode: str = "threshold"
    policy_hidden: int = 128
    value_head: str = "mse"  # mse (ClipPPOLoss's L2 critic) | twohot (symlog two-hot critic, cross-entropy)
    # none: PPO standardises advantages per minibatch; percentile: DreamerV3's advantages / max(1, P95 - P5) of the
    # lambda-returns (EMA 0.99), no standardisation
    return_norm: str = "none"
    # imagined reward = mean - uncertainty_penalty * std over the world_model.ensemble reward heads (needs K >= 2)
    uncertainty_penalty: float = 0.0


@dataclass
class HealthCollectConfig:
    iterations: int = 20
    prefill_frames: int = 2048  # uniformly random actions first
    frames_per_iter: int = 512
    # epsilon of the collection policy after the prefill: keeps every action in the replay data so that the world
    # model keeps learning what each intervention does (without it the data collapses onto the policy's action)
    random_action_prob: float = 0.0
    # distribution of the random actions (prefill and epsilon), over (Continue, Rest, Increase, Change, Alert);
    # null = uniform. Uniform random data is ~98 % Alert-hold / level <= 0.25 (an Alert every 5 steps on average,
    # each holding the level <= 0.25 for 30 s): the world model then never sees the planned intensity
    explore_probs: list[float] | None = None
    # random actions (prefill after its first batch, and the epsilon ones) drawn with p(a) proportional to
    # 1 / (1 + count of a in the replay buffer) instead of explore_probs: more data for the rarely taken actions
    balance_actions: bool = False
    buffer_capacity: int = 200_000


@dataclass
class HealthEvalConfig:
    num_envs: int = 8  # evaluation episodes (one per env)
    every: int = 0  # evaluate every N iterations (0: only at the end)
    deterministic: bool = True  # act with the mode of the policy
    seed: int = 12345  # env seed of the evaluation episodes: the same episodes for every run, seed and encoder
    # held-out subjects of the evaluation (leave-one-subject-out: the subject env.subjects leaves out); None: the
    # training subjects. The reference policies and the oracle (freamer_rl.health.reference) read the same field
    subjects: list[int] | None = None
    # reference policies evaluated on the same episodes after training (freamer_rl.health.reference): summary.json gets
    # eval_ref_<name>_return, and eval_fraction_of_oracle / eval_vs_hr_threshold when oracle / hr_threshold are listed
    # (the oracle planner takes ~15 s on 16 episodes of 120 steps); [] evaluates none
    references: list[str] = field(default_factory=lambda: ["oracle", "hr_threshold", "continue"])
    mse_windows: int = 64
    horizon_context: int = 8
    horizon_max: int = 48
    horizon_reward_tol: float = 0.5
    horizon_windows: int = 64


@dataclass
class HealthLoggingConfig:
    """The shared ``logging`` section's fields that a health run reads (same keys, same defaults, same checks);
    health logs once per iteration and checkpoints after every one, so the other fields do not apply."""

    backend: str = LoggingConfig.backend  # TorchRL logger of metrics/attempt_NN: csv | wandb | tensorboard
    progress_bar: bool = LoggingConfig.progress_bar


@dataclass
class HealthRunConfig:
    """The shared ``run`` section's fields that a health run reads (same keys and defaults); a health run's length is
    ``collect.*`` and it trains on the CPU, so ``total_frames`` / ``device`` / ``init_from`` do not apply."""

    seed: int = RunConfig.seed
    threads: int = RunConfig.threads
    output_dir: str = RunConfig.output_dir
    name: str | None = RunConfig.name


@dataclass
class HealthConfig:
    env: HealthEnvConfig = field(default_factory=HealthEnvConfig)
    encoder: HealthEncoderConfig = field(default_factory=HealthEncoderConfig)
    world_model: HealthWorldModelConfig = field(default_factory=HealthWorldModelConfig)
    imagination: HealthImaginationConfig = field(default_factory=HealthImaginationConfig)
    collect: HealthCollectConfig = field(default_factory=HealthCollectConfig)
    eval: HealthEvalConfig = field(default_factory=HealthEvalConfig)
    logging: HealthLoggingConfig = field(default_factory=HealthLoggingConfig)
    run: HealthRunConfig = field(default_factory=HealthRunConfig)

    #: keys of earlier releases, refused with the key that replaced them (one key per setting across trainers)
    RENAMED: ClassVar[dict[str, str]] = {"run.logger": "logging.backend", "run.progress_bar": "logging.progress_bar"}


def _in(lo: float, hi: float, lo_open: bool = False):
    return lambda v: (lo < v if lo_open else lo <= v) and v <= hi


_POS, _NONNEG = (lambda v: v > 0, "> 0"), (lambda v: v >= 0, ">= 0")
#: Number ranges of the health schema for :func:`freamer_rl.config.checks.check_numbers` (elsewhere ints must be
#: >= 1 and floats finite).
HEALTH_RANGES = {
    "run.seed": BASE_RANGES["run.seed"],
    **{
        k: size_range(WIDTH_LIMIT)
        for k in (
            "encoder.embed_dim",
            "encoder.hidden",
            "encoder.cnn_channels",
            "encoder.dim",
            "encoder.fm_hidden",
            "encoder.memory_slots",
            "encoder.memory_width",
            "world_model.deter_dim",
            "world_model.stoch_dim",
            "world_model.hidden",
            "imagination.policy_hidden",
        )
    },
    **{
        k: size_range(BATCH_LIMIT)
        for k in (
            "env.num_envs",
            "eval.num_envs",
            "world_model.batch_size",
            "world_model.seq_len",
            "imagination.num_seeds",
            "imagination.horizon",
        )
    },
    **{
        k: size_range(LAYERS_LIMIT)
        for k in ("encoder.mlp_layers", "encoder.heads", "encoder.fm_steps", "world_model.ensemble")
    },
    **{
        k: _NONNEG
        for k in (
            "env.data_seed",
            "eval.seed",
            "collect.iterations",
            "collect.prefill_frames",
            "world_model.train_steps",
            "world_model.prefill_train_steps",
            "imagination.updates",
            "eval.every",
            "encoder.fm_noise_std",
            "world_model.beta",
            "world_model.free_nats",
            "world_model.reward_scale",
            "world_model.lambda_fm",
            "world_model.lambda_smooth",
            "imagination.entropy_coeff",
            "imagination.critic_coeff",
            "imagination.uncertainty_penalty",
        )
    },
    **{
        k: _POS
        for k in (
            "env.rate_hz",
            "env.synthetic_duration_s",
            "world_model.lr",
            "world_model.adam_eps",
            "world_model.grad_clip",
            "imagination.lr",
            "imagination.adam_eps",
            "imagination.clip_epsilon",
            "imagination.max_grad_norm",
            "eval.horizon_reward_tol",
        )
    },
    "world_model.kl_balance": (_in(0, 1), "in [0, 1]"),
    "imagination.gamma": (_in(0, 1, lo_open=True), "in (0, 1]"),
    "imagination.lmbda": (_in(0, 1), "in [0, 1]"),
    "collect.random_action_prob": (_in(0, 1), "in [0, 1]"),
}


def validate_health_config(cfg: HealthConfig) -> None:
    """Number ranges (:data:`HEALTH_RANGES`) and cross-field checks (types and unknown keys are checked while
    building)."""
    check_numbers(cfg)
    check_corruption(cfg.env.corrupt)  # the keys against the world model's inputs: evaluation.corruption_for
    if cfg.run.name and (problem := run_name_problem(cfg.run.name)):  # run dir = run.output_dir/run.name
        raise ConfigError(f"run.name: {problem}")
    check_logging(cfg.logging)
    check_subjects(cfg)
    if cfg.encoder.kind not in ENCODER_KINDS:
        raise ConfigError(f"encoder.kind: expected one of {', '.join(ENCODER_KINDS)}, got {cfg.encoder.kind!r}")
    for m in cfg.encoder.gate_init:
        if m not in MODALITIES:
            raise ConfigError(f"encoder.gate_init: unknown modality {m!r} (known: {', '.join(MODALITIES)})")
    check_options(cfg)
    if cfg.imagination.done_mode not in ("threshold", "sample", "never"):
        raise ConfigError(
            f"imagination.done_mode: expected threshold, sample or never, got {cfg.imagination.done_mode!r}"
        )
    if len(cfg.env.reward_weights) != 3:
        raise ConfigError(
            f"env.reward_weights: expected 3 numbers (w_safe, w_target, w_fatigue), got {cfg.env.reward_weights!r}"
        )
    if cfg.encoder.kind in ("slotattn", "foundation") and cfg.encoder.dim % cfg.encoder.heads:
        raise ConfigError(
            f"encoder.dim: got {cfg.encoder.dim}, must be divisible by encoder.heads ({cfg.encoder.heads})"
        )
    n = cfg.env.num_envs
    for name, frames in (
        ("collect.frames_per_iter", cfg.collect.frames_per_iter),
        ("collect.prefill_frames", cfg.collect.prefill_frames),
    ):
        if frames % n:
            raise ConfigError(f"{name} ({frames}) must be a multiple of env.num_envs ({n})")
    if cfg.collect.frames_per_iter // n < cfg.world_model.seq_len:
        raise ConfigError(
            f"collect.frames_per_iter / env.num_envs ({cfg.collect.frames_per_iter // n} steps per env per batch) "
            f"must be >= world_model.seq_len ({cfg.world_model.seq_len}): slices are cut inside one batch"
        )
    if cfg.env.episode_length < cfg.world_model.seq_len:
        raise ConfigError(
            f"env.episode_length ({cfg.env.episode_length}) must be >= world_model.seq_len ({cfg.world_model.seq_len})"
        )
    if cfg.eval.horizon_context + cfg.eval.horizon_max > cfg.env.episode_length:
        raise ConfigError(
            f"eval.horizon_context + eval.horizon_max ({cfg.eval.horizon_context + cfg.eval.horizon_max}) must be "
            f"<= env.episode_length ({cfg.env.episode_length}): windows are cut from evaluation episodes"
        )
    if not 0.0 <= cfg.collect.random_action_prob <= 1.0:
        raise ConfigError(
            f"collect.random_action_prob: expected a probability in [0, 1], got {cfg.collect.random_action_prob}"
        )
    try:
        explore_probs(cfg.collect.explore_probs, NUM_ACTIONS, "collect.explore_probs")
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if cfg.collect.prefill_frames == 0 and cfg.collect.iterations == 0:
        raise ConfigError("collect: prefill_frames and iterations are both 0 (nothing to train on)")


def check_options(cfg: HealthConfig) -> None:
    """The world-model / imagination options of issue 22 part 2: choices and the pairs that need each other; the
    reference policies of ``eval.references``."""
    refs = cfg.eval.references
    if not isinstance(refs, list) or any(r not in REFERENCE_POLICIES for r in refs) or len(set(refs)) != len(refs):
        raise ConfigError(
            f"eval.references: expected a list of distinct names from {', '.join(REFERENCE_POLICIES)}, got {refs!r}"
        )
    for name, value, choices in (
        ("world_model.reward_head", cfg.world_model.reward_head, REWARD_HEADS),
        ("imagination.value_head", cfg.imagination.value_head, REWARD_HEADS),
        ("imagination.return_norm", cfg.imagination.return_norm, RETURN_NORMS),
    ):
        if value not in choices:
            raise ConfigError(f"{name}: expected one of {', '.join(choices)}, got {value!r}")
    if cfg.imagination.uncertainty_penalty > 0 and cfg.world_model.ensemble < 2:
        raise ConfigError(
            f"imagination.uncertainty_penalty ({cfg.imagination.uncertainty_penalty}) needs world_model.ensemble >= 2 "
            f"(got {cfg.world_model.ensemble}): one reward head has no spread to penalise"
        )
    if cfg.collect.balance_actions and cfg.collect.random_action_prob == 0 and cfg.collect.prefill_frames == 0:
        raise ConfigError(
            "collect.balance_actions: no random actions to balance (collect.random_action_prob and "
            "collect.prefill_frames are both 0)"
        )


def _subject_list_problem(subjects: list[int]) -> str | None:
    if not subjects:
        return "an empty list (null for the default subjects)"
    bad = [s for s in subjects if s not in PROTOCOL_SUBJECTS]
    if bad:
        return f"expected PAMAP2 subject numbers in {PROTOCOL_SUBJECTS[0]}..{PROTOCOL_SUBJECTS[-1]}, got {bad}"
    if len(set(subjects)) != len(subjects):
        return f"a subject is listed twice in {subjects}"
    return None


def check_subjects(cfg: HealthConfig) -> None:
    """``env.subjects`` / ``eval.subjects``: PAMAP2 numbers (101-109), each once; held-out evaluation subjects need
    an explicit training list that does not contain them (a subject in both is a leak, refused in one line)."""
    for name, subjects in (("env.subjects", cfg.env.subjects), ("eval.subjects", cfg.eval.subjects)):
        if subjects is not None and (problem := _subject_list_problem(subjects)):
            raise ConfigError(f"{name}: {problem}")
    if cfg.env.id == VARIED_ENV_ID and cfg.env.data_dir is not None:
        raise ConfigError(
            f"env.id {VARIED_ENV_ID!r} varies the synthetic subjects' activities, env.data_dir "
            f"{cfg.env.data_dir!r} reads real ones: use env.id pamap2-health with real data"
        )
    held_out = cfg.eval.subjects
    if held_out is None:
        return
    if cfg.env.subjects is None:
        raise ConfigError(
            f"eval.subjects {held_out} needs env.subjects listed: null trains on every subject found (real data) or "
            "on 101-103 (synthetic), so the held-out subjects may be trained on"
        )
    leak = sorted(set(held_out) & set(cfg.env.subjects))
    if leak:
        raise ConfigError(
            f"eval.subjects {held_out} and env.subjects {cfg.env.subjects} share {leak}: a held-out subject that is "
            "trained on is a leak (leave eval.subjects null to evaluate on the training subjects)"
        )


def explore_probs(probs: list[float] | None, num_actions: int, name: str) -> torch.Tensor:
    """Normalised exploration distribution ``[num_actions]`` (uniform when ``probs`` is None)."""
    if probs is None:
        return torch.full((num_actions,), 1.0 / num_actions)
    p = torch.as_tensor(list(probs), dtype=torch.float32)
    if p.shape != (num_actions,) or not bool(torch.isfinite(p).all()) or bool((p < 0).any()) or float(p.sum()) <= 0:
        raise ValueError(f"{name}: expected {num_actions} non-negative weights with a positive sum, got {probs!r}")
    return p / p.sum()


HealthConfig.RANGES = HEALTH_RANGES  # the loader checks every number against the schema's table
VALIDATORS[HealthConfig] = validate_health_config


def health_config_from_dict(data: dict | None) -> HealthConfig:
    """Build and validate a :class:`HealthConfig` (the shared loader, :func:`freamer_rl.config.loader.config_from_dict`)."""
    return config_from_dict(data, HealthConfig)


def load_health_config(path: str | Path | None = None, overrides: list[str] | None = None) -> HealthConfig:
    """``load_config(path, overrides, schema=HealthConfig)``: a recipe (defaults when ``path`` is None) plus dotted
    overrides (``["collect.iterations=5", "run.seed=1"]``)."""
    return load_config(path, overrides, schema=HealthConfig)


def health_config_to_dict(cfg: HealthConfig) -> dict:
    """Plain mapping of ``cfg`` with ``trainer: health`` first (a run's ``config.yaml`` is a recipe again)."""
    return {"trainer": "health", **dataclasses.asdict(cfg)}
