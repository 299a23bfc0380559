"""Health-domain run: real-env collection -> RSSM world model -> imagination PPO -> real-env evaluation (Section 5,
Appendix J), plus the anomaly report of Appendix J.5 / Fig. 4.

One call of :func:`run_health` owns one run directory::

    <run_dir>/config.yaml        resolved :class:`HealthConfig`
    <run_dir>/run_info.json      git commit, versions, command
    <run_dir>/progress.csv       one row per iteration (frames, training episodes, world-model and PPO losses,
                                 FM gates, evaluation columns when evaluated)
    <run_dir>/summary.json       final figures (real-env return / violations / length, reconstruction MSE,
                                 imagination horizon, parameter counts, wall time)
    <run_dir>/checkpoint.pt      world model + actor + value + config (:func:`load_agent`)

Loop (``collect.iterations`` times, after ``collect.prefill_frames`` frames of random actions drawn from
``collect.explore_probs``, uniform when null)::

    1. collect collect.frames_per_iter real-env frames with a TorchRL Collector and the current policy
       (HealthPolicy: filters the world-model posterior online and acts on the latent; with probability
       collect.random_action_prob a random action from collect.explore_probs instead) -> replay buffer
       (LazyTensorStorage + SliceSampler over ("collector", "traj_ids"))
    2. world_model.train_steps steps of Eq. A27 on [batch_size, seq_len] slices,
       + lambda_FM * L_FM + lambda_s * L_smooth for the foundation encoder (Table A20: lambda_FM(WM) = 0.1)
    3. imagination.updates ImaginationPPO updates (ClipPPOLoss + GAE on horizon-15 imagined rollouts seeded with
       posterior latents of replayed slices)

Evaluation (every ``eval.every`` iterations and at the end), in the **real** env with a fresh env of
``eval.num_envs`` episodes (env seed ``eval.seed``: the same episodes for every evaluation, run and encoder): the
policy acts (mode of the categorical when ``eval.deterministic``) on the posterior-mean latent; per episode the
return, the number of steps with heart rate > 160 bpm (violations) and the length, read at each env's first
``done``.

Reconstruction MSE: ``(36 mse_imu + 16 mse_hr_features) / 52`` in raw observation units (the mean squared error per
feature), averaged over ``eval.mse_windows`` windows of ``world_model.seq_len`` steps cut from the evaluation
episodes (held-out data the world model never trained on).

Imagination horizon (``eval.horizon_*``): for each of ``eval.horizon_windows`` held-out windows of ``C + H_max``
steps (``C = eval.horizon_context``, ``H_max = eval.horizon_max``) from the evaluation episodes, the posterior is
filtered over the first ``C`` transitions (posterior means), then the prior is rolled open loop with the *recorded*
actions (prior means). At imagined step ``k = 1..H_max`` the reward head's prediction is compared with the real
reward of that step. The horizon of a window is the number of imagined steps before the first step where
``|r_hat - r| > eval.horizon_reward_tol`` or where the continuation head predicts a termination (``c < 0.5``) that
did not happen; ``H_max`` if neither occurs. Reported: mean and std over windows.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Categorical, LazyTensorStorage, ReplayBuffer, SliceSampler, Unbounded
from torchrl.envs import Compose, EnvBase, ExplorationType, InitTracker, TransformedEnv, set_exploration_type
from torchrl.envs.transforms import TensorDictPrimer
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator

from freamer_rl import env_registry
from freamer_rl.checkpoint import read_checkpoint, remove_stale_temps, save_checkpoint
from freamer_rl.config import ConfigError, _build, apply_overrides
from freamer_rl.errors import CheckpointError
from freamer_rl.rundir import RunDirLock, run_name_problem
from freamer_rl.health.encoders import ENCODER_KINDS, MODALITIES, make_health_encoder
from freamer_rl.world_model.anomaly import detect_anomalies, plot_anomaly_timeline
from freamer_rl.world_model.imagination import ImaginationPPO, RSSMWorldModelEnv
from freamer_rl.world_model.rssm import WorldModel, as_sequences, gaussian_kl

logger = logging.getLogger(__name__)

__all__ = [
    "HealthEnvConfig",
    "HealthEncoderConfig",
    "HealthWorldModelConfig",
    "HealthImaginationConfig",
    "HealthCollectConfig",
    "HealthEvalConfig",
    "HealthRunConfig",
    "HealthConfig",
    "load_health_config",
    "health_config_from_dict",
    "health_config_to_dict",
    "HealthAgent",
    "HealthPolicy",
    "build_agent",
    "load_agent",
    "save_agent",
    "make_health_env",
    "train_world_model_step",
    "evaluate_policy",
    "rollout_metrics",
    "reconstruction_mse",
    "imagination_horizon",
    "run_health",
    "record_episode",
    "anomaly_report",
]

OBS_DIMS = {"imu": 36, "hr_features": 16}
NUM_ACTIONS = 5
CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "freamer_rl.health/1"
_STATE = "wm_filter"  # root of the policy's recurrent state keys in the real env


# ----------------------------------------------------------------------------------------------------------------------
# config
# ----------------------------------------------------------------------------------------------------------------------
@dataclass
class HealthEnvConfig:
    """Real health env (``freamer_rl_envs.health.make_health_env`` through the ``health`` adapter entry point)."""

    adapter: str = "health"
    id: str = "pamap2-health"
    data_dir: str | None = None  # PAMAP2 root or Protocol folder; None = embedded synthetic subjects
    subjects: list[int] | None = None
    num_envs: int = 8  # batch of the training env (simultaneous subjects)
    episode_length: int = 120  # steps (0.2 Hz: 10 minutes)
    rate_hz: float = 0.2  # 5 s a step, so that the imagination horizon spans the heart-rate dynamics
    reward_weights: list[float] = field(default_factory=lambda: [2.0, 1.0, 0.5])  # Eq. A11
    synthetic_duration_s: float = 1800.0
    data_seed: int = 0


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
    done_mode: str = "threshold"  # threshold | sample | never
    policy_hidden: int = 128


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
    buffer_capacity: int = 200_000


@dataclass
class HealthEvalConfig:
    num_envs: int = 8  # evaluation episodes (one per env)
    every: int = 0  # evaluate every N iterations (0: only at the end)
    deterministic: bool = True  # act with the mode of the policy
    seed: int = 12345  # env seed of the evaluation episodes: the same episodes for every run, seed and encoder
    mse_windows: int = 64
    horizon_context: int = 8
    horizon_max: int = 48
    horizon_reward_tol: float = 0.5
    horizon_windows: int = 64


@dataclass
class HealthRunConfig:
    seed: int = 0
    threads: int = 1
    output_dir: str = "runs"
    name: str | None = None
    progress_bar: bool = True


@dataclass
class HealthConfig:
    env: HealthEnvConfig = field(default_factory=HealthEnvConfig)
    encoder: HealthEncoderConfig = field(default_factory=HealthEncoderConfig)
    world_model: HealthWorldModelConfig = field(default_factory=HealthWorldModelConfig)
    imagination: HealthImaginationConfig = field(default_factory=HealthImaginationConfig)
    collect: HealthCollectConfig = field(default_factory=HealthCollectConfig)
    eval: HealthEvalConfig = field(default_factory=HealthEvalConfig)
    run: HealthRunConfig = field(default_factory=HealthRunConfig)


def validate_health_config(cfg: HealthConfig) -> None:
    """Cross-field checks (types and unknown keys are checked while building)."""
    if cfg.run.name and (problem := run_name_problem(cfg.run.name)):  # run dir = run.output_dir/run.name
        raise ConfigError(f"run.name: {problem}")
    if cfg.encoder.kind not in ENCODER_KINDS:
        raise ConfigError(f"encoder.kind: expected one of {', '.join(ENCODER_KINDS)}, got {cfg.encoder.kind!r}")
    for m in cfg.encoder.gate_init:
        if m not in MODALITIES:
            raise ConfigError(f"encoder.gate_init: unknown modality {m!r} (known: {', '.join(MODALITIES)})")
    if cfg.imagination.done_mode not in ("threshold", "sample", "never"):
        raise ConfigError(f"imagination.done_mode: expected threshold, sample or never, got "
                          f"{cfg.imagination.done_mode!r}")  # fmt: skip
    if len(cfg.env.reward_weights) != 3:
        raise ConfigError(f"env.reward_weights: expected 3 numbers (w_safe, w_target, w_fatigue), got "
                          f"{cfg.env.reward_weights!r}")  # fmt: skip
    positive = {
        "env.num_envs": cfg.env.num_envs, "env.episode_length": cfg.env.episode_length, "env.rate_hz": cfg.env.rate_hz,
        "encoder.embed_dim": cfg.encoder.embed_dim, "encoder.hidden": cfg.encoder.hidden,
        "encoder.dim": cfg.encoder.dim,
        "world_model.deter_dim": cfg.world_model.deter_dim, "world_model.stoch_dim": cfg.world_model.stoch_dim,
        "world_model.hidden": cfg.world_model.hidden, "world_model.lr": cfg.world_model.lr,
        "world_model.batch_size": cfg.world_model.batch_size, "world_model.seq_len": cfg.world_model.seq_len,
        "imagination.horizon": cfg.imagination.horizon, "imagination.lr": cfg.imagination.lr,
        "imagination.num_seeds": cfg.imagination.num_seeds, "imagination.epochs": cfg.imagination.epochs,
        "imagination.num_minibatches": cfg.imagination.num_minibatches,
        "collect.frames_per_iter": cfg.collect.frames_per_iter, "collect.buffer_capacity": cfg.collect.buffer_capacity,
        "eval.num_envs": cfg.eval.num_envs, "eval.horizon_max": cfg.eval.horizon_max,
        "eval.horizon_context": cfg.eval.horizon_context, "eval.mse_windows": cfg.eval.mse_windows,
        "eval.horizon_windows": cfg.eval.horizon_windows, "run.threads": cfg.run.threads,
    }  # fmt: skip
    for name, value in positive.items():
        if value <= 0:
            raise ConfigError(f"{name}: must be positive, got {value}")
    non_negative = {
        "collect.iterations": cfg.collect.iterations, "collect.prefill_frames": cfg.collect.prefill_frames,
        "world_model.train_steps": cfg.world_model.train_steps, "imagination.updates": cfg.imagination.updates,
        "world_model.prefill_train_steps": cfg.world_model.prefill_train_steps, "eval.every": cfg.eval.every,
    }  # fmt: skip
    for name, value in non_negative.items():
        if value < 0:
            raise ConfigError(f"{name}: must be >= 0, got {value}")
    n = cfg.env.num_envs
    for name, frames in (("collect.frames_per_iter", cfg.collect.frames_per_iter),
                         ("collect.prefill_frames", cfg.collect.prefill_frames)):  # fmt: skip
        if frames % n:
            raise ConfigError(f"{name} ({frames}) must be a multiple of env.num_envs ({n})")
    if cfg.collect.frames_per_iter // n < cfg.world_model.seq_len:
        raise ConfigError(
            f"collect.frames_per_iter / env.num_envs ({cfg.collect.frames_per_iter // n} steps per env per batch) "
            f"must be >= world_model.seq_len ({cfg.world_model.seq_len}): slices are cut inside one batch"
        )
    if cfg.env.episode_length < cfg.world_model.seq_len:
        raise ConfigError(f"env.episode_length ({cfg.env.episode_length}) must be >= world_model.seq_len "
                          f"({cfg.world_model.seq_len})")  # fmt: skip
    if cfg.eval.horizon_context + cfg.eval.horizon_max > cfg.env.episode_length:
        raise ConfigError(
            f"eval.horizon_context + eval.horizon_max ({cfg.eval.horizon_context + cfg.eval.horizon_max}) must be "
            f"<= env.episode_length ({cfg.env.episode_length}): windows are cut from evaluation episodes"
        )
    if not 0.0 <= cfg.collect.random_action_prob <= 1.0:
        raise ConfigError(f"collect.random_action_prob: expected a probability in [0, 1], got "
                          f"{cfg.collect.random_action_prob}")  # fmt: skip
    try:
        _explore_probs(cfg.collect.explore_probs, NUM_ACTIONS, "collect.explore_probs")
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if cfg.collect.prefill_frames == 0 and cfg.collect.iterations == 0:
        raise ConfigError("collect: prefill_frames and iterations are both 0 (nothing to train on)")


def health_config_from_dict(data: dict | None) -> HealthConfig:
    """Build and validate a :class:`HealthConfig`; unknown keys and wrong types raise :class:`ConfigError`
    naming the dotted field."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"a health recipe must be a YAML mapping, got {type(data).__name__}")
    cfg = _build(HealthConfig, data)
    validate_health_config(cfg)
    return cfg


def load_health_config(path: str | Path | None = None, overrides: list[str] | None = None) -> HealthConfig:
    """Load a YAML recipe (``recipes/health/health_*.yaml``; defaults when ``path`` is None) and apply dotted overrides
    (``["collect.iterations=5", "run.seed=1"]``)."""
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"recipe file not found: {path}")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            mark = getattr(err, "problem_mark", None)
            where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
            raise ConfigError(f"{where}: invalid YAML ({getattr(err, 'problem', err)})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: a recipe must be a YAML mapping")
    data = apply_overrides(data, overrides or [])
    return health_config_from_dict(data)


def health_config_to_dict(cfg: HealthConfig) -> dict:
    return dataclasses.asdict(cfg)


# ----------------------------------------------------------------------------------------------------------------------
# env, models, policy
# ----------------------------------------------------------------------------------------------------------------------
def _env_options(cfg: HealthConfig) -> dict[str, Any]:
    e = cfg.env
    return {
        "data_dir": e.data_dir,
        "subjects": e.subjects,
        "episode_length": e.episode_length,
        "rate_hz": e.rate_hz,
        "reward_weights": tuple(e.reward_weights),
        "synthetic_duration_s": e.synthetic_duration_s,
        "data_seed": e.data_seed,
    }


def make_health_env(
    cfg: HealthConfig, *, num_envs: int | None = None, seed: int | None = None, primer: TensorDictPrimer | None = None,
    **overrides: Any,
) -> EnvBase:  # fmt: skip
    """The real env through the ``freamer_rl.envs`` registry (``env.adapter``, default ``health``), batch
    ``[num_envs]``, wrapped with ``InitTracker`` (+ ``primer``, the policy's recurrent state). ``overrides`` replace
    adapter options (e.g. ``episode_length``)."""
    options = {**_env_options(cfg), **overrides}
    base = env_registry.make_env(cfg.env.adapter, cfg.env.id, seed=seed,
                                 batch_size=num_envs or cfg.env.num_envs, **options)  # fmt: skip
    transforms = [InitTracker()]
    if primer is not None:
        transforms.append(primer)
    return TransformedEnv(base, Compose(*transforms))


def _encoder_kwargs(cfg: HealthEncoderConfig) -> dict[str, Any]:
    if cfg.kind == "mlp":
        return {"hidden": cfg.hidden, "layers": cfg.mlp_layers}
    if cfg.kind == "cnn":
        return {"channels": cfg.cnn_channels, "hidden": cfg.hidden}
    common = {"dim": cfg.dim, "heads": cfg.heads, "hr_tokens": cfg.hr_tokens, "hidden": cfg.hidden}
    if cfg.kind == "slotattn":
        return common
    return {
        **common, "fm_hidden": cfg.fm_hidden, "fm_steps": cfg.fm_steps, "gate_init": dict(cfg.gate_init),
        "fm_noise_std": cfg.fm_noise_std, "fno_modes": cfg.fno_modes, "fno_residual_scale": cfg.fno_residual_scale,
        "memory_slots": cfg.memory_slots, "memory_width": cfg.memory_width,
    }  # fmt: skip


def build_world_model(cfg: HealthConfig) -> WorldModel:
    """WorldModel (same RSSM core for every encoder) with the configured encoder."""
    enc = make_health_encoder(cfg.encoder.kind, cfg.encoder.embed_dim, **_encoder_kwargs(cfg.encoder))
    w = cfg.world_model
    return WorldModel(OBS_DIMS, NUM_ACTIONS, encoder=enc, embed_dim=cfg.encoder.embed_dim, deter_dim=w.deter_dim,
                      stoch_dim=w.stoch_dim, hidden=w.hidden, beta=w.beta, free_nats=w.free_nats,
                      kl_balance=w.kl_balance, recon_norm=w.recon_norm, reward_scale=w.reward_scale)  # fmt: skip


def build_actor_value(latent_dim: int, hidden: int) -> tuple[ProbabilisticActor, ValueOperator]:
    """Categorical actor and value MLPs on ``"latent"`` ``[*B, D + S]``."""
    actor = ProbabilisticActor(
        TensorDictModule(MLP(in_features=latent_dim, out_features=NUM_ACTIONS, num_cells=[hidden, hidden],
                             activation_class=nn.SiLU), in_keys=["latent"], out_keys=["logits"]),  # fmt: skip
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
        spec=Categorical(NUM_ACTIONS),
    )
    value = ValueOperator(MLP(in_features=latent_dim, out_features=1, num_cells=[hidden, hidden],
                              activation_class=nn.SiLU), in_keys=["latent"])  # fmt: skip
    return actor, value


def _explore_probs(probs: list[float] | None, num_actions: int, name: str) -> torch.Tensor:
    """Normalised exploration distribution ``[num_actions]`` (uniform when ``probs`` is None)."""
    if probs is None:
        return torch.full((num_actions,), 1.0 / num_actions)
    p = torch.as_tensor(list(probs), dtype=torch.float32)
    if p.shape != (num_actions,) or not bool(torch.isfinite(p).all()) or bool((p < 0).any()) or float(p.sum()) <= 0:
        raise ValueError(f"{name}: expected {num_actions} non-negative weights with a positive sum, got {probs!r}")
    return p / p.sum()


class HealthPolicy(TensorDictModuleBase):
    """Acting in the real env: filter the world-model posterior online, then sample the actor on the latent.

    Stateful module in TorchRL's pattern. Reads the observations (``"imu"``, ``"hr_features"``), ``"is_init"``
    (``InitTracker``) and the recurrent state at the root -- ``("wm_filter", "deter") [*B, D]``,
    ``("wm_filter", "stoch") [*B, S]``, ``("wm_filter", "prev_action") [*B, A]`` (one-hot of the action that led
    to this observation) and the encoder's state ``("wm_filter", "enc", name)`` (the foundation encoder's DNC
    memory ``[*B, N, W]``); declare them with :meth:`make_tensordict_primer`. Per step (``is_init`` zeroes the
    state; a zero state is exactly the reset state)::

        e_t = encoder.step(o_t)                     h_t = GRU(h_{t-1}, [z_{t-1}; a_{t-1}])       (Eq. A23)
        z_t ~ q(z | h_t, e_t) (mean if not sample_latent)                                         (Eq. A25)
        a_t ~ pi(a | [h_t; z_t])   (a_t ~ explore_probs (default uniform) when random_actions, or with
                                    probability random_action_prob)

    Writes ``"latent"``, ``"kl"`` (``KL(q || p)`` of this step, ``[*B, 1]``, J.5), the actor's ``"logits"``,
    ``"action"``, ``"action_log_prob"`` and the new state under ``("next", "wm_filter", ...)``. Runs under
    ``no_grad``.
    """

    def __init__(self, world_model: WorldModel, actor: TensorDictModuleBase, *, sample_latent: bool = True,
                 random_actions: bool = False, random_action_prob: float = 0.0,
                 explore_probs: list[float] | None = None) -> None:  # fmt: skip
        super().__init__()
        if not 0.0 <= random_action_prob <= 1.0:
            raise ValueError(f"random_action_prob: expected a probability in [0, 1], got {random_action_prob}")
        self.explore_probs = _explore_probs(explore_probs, world_model.action_dim, "explore_probs")
        self.world_model = world_model
        self.actor = actor
        self.sample_latent = sample_latent
        self.random_actions = random_actions
        self.random_action_prob = random_action_prob
        enc = world_model.encoder
        self._enc_shapes = dict(enc.state_shapes()) if hasattr(enc, "state_shapes") else {}
        self.obs_keys = list(world_model.obs_dims)
        self.state_keys = {"deter": (_STATE, "deter"), "stoch": (_STATE, "stoch"),
                           "prev_action": (_STATE, "prev_action")}  # fmt: skip
        self.enc_keys = {n: (_STATE, "enc", n) for n in self._enc_shapes}
        self.in_keys = [*self.obs_keys, "is_init", *self.state_keys.values(), *self.enc_keys.values()]
        self.out_keys = ["latent", "kl", "logits", "action", "action_log_prob",
                         *[("next", *k) for k in (*self.state_keys.values(), *self.enc_keys.values())]]  # fmt: skip

    def make_tensordict_primer(self) -> TensorDictPrimer:
        wm = self.world_model
        specs = {
            self.state_keys["deter"]: Unbounded(shape=(wm.deter_dim,), dtype=torch.float32),
            self.state_keys["stoch"]: Unbounded(shape=(wm.stoch_dim,), dtype=torch.float32),
            self.state_keys["prev_action"]: Unbounded(shape=(wm.action_dim,), dtype=torch.float32),
        }
        for n, shape in self._enc_shapes.items():
            specs[self.enc_keys[n]] = Unbounded(shape=tuple(shape), dtype=torch.float32)
        return TensorDictPrimer(specs, expand_specs=True)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        wm = self.world_model
        bs = tensordict.batch_size
        missing = [k for k in (*self.state_keys.values(), *self.enc_keys.values())
                   if k not in tensordict.keys(include_nested=True)]  # fmt: skip
        if missing:
            raise KeyError(
                f"HealthPolicy: recurrent state {missing} missing from the tensordict; declare it on the env with "
                "TransformedEnv(env, Compose(InitTracker(), policy.make_tensordict_primer()))"
            )
        is_init = tensordict.get("is_init", None)
        first = (torch.zeros(bs, dtype=torch.bool) if is_init is None else is_init.reshape(bs)).bool()
        h = tensordict.get(self.state_keys["deter"])
        z = tensordict.get(self.state_keys["stoch"])
        a = tensordict.get(self.state_keys["prev_action"])
        obs = {k: tensordict.get(k) for k in self.obs_keys}
        enc = wm.encoder
        if hasattr(enc, "step"):
            state = {n: tensordict.get(k) for n, k in self.enc_keys.items()}
            embed, new_state = enc.step(obs, state, first)
        else:  # a plain stateless encoder
            embed, new_state = wm.embed(obs), {}
        out = wm.rssm.obs_step(h, z, a, embed, is_first=first, sample=self.sample_latent)
        kl = gaussian_kl(out["post_mean"], out["post_std"], out["prior_mean"], out["prior_std"])
        tensordict.set("latent", torch.cat([out["h"], out["z"]], dim=-1))
        tensordict.set("kl", kl.unsqueeze(-1))
        tensordict = self.actor(tensordict)
        if self.random_actions or self.random_action_prob > 0.0:
            n = max(1, bs.numel())
            random = torch.multinomial(self.explore_probs, n, replacement=True).reshape(bs).to(h.device)
            if not self.random_actions:
                explore = torch.rand(bs, device=h.device) < self.random_action_prob
                random = torch.where(explore, random, tensordict.get("action"))
            tensordict.set("action", random)
        action = wm.action_to_onehot(tensordict.get("action"), len(bs))
        tensordict.set(("next", *self.state_keys["deter"]), out["h"])
        tensordict.set(("next", *self.state_keys["stoch"]), out["z"])
        tensordict.set(("next", *self.state_keys["prev_action"]), action)
        for n, k in self.enc_keys.items():
            tensordict.set(("next", *k), new_state[n])
        return tensordict


@dataclass
class HealthAgent:
    """Everything a trained health run produced: config, world model, actor, value."""

    cfg: HealthConfig
    world_model: WorldModel
    actor: ProbabilisticActor
    value: ValueOperator

    def policy(self, **kwargs: Any) -> HealthPolicy:
        return HealthPolicy(self.world_model, self.actor, **kwargs)

    def state_dict(self) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "config": health_config_to_dict(self.cfg),
            "world_model": self.world_model.state_dict(),
            "actor": self.actor.state_dict(),
            "value": self.value.state_dict(),
        }


def build_agent(cfg: HealthConfig) -> HealthAgent:
    wm = build_world_model(cfg)
    actor, value = build_actor_value(wm.latent_dim, cfg.imagination.policy_hidden)
    return HealthAgent(cfg, wm, actor, value)


def load_agent(path: str | Path) -> HealthAgent:
    """Load a :func:`run_health` checkpoint (the file, or the run directory holding ``checkpoint.pt``)."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    payload = read_checkpoint(path, fmt=CHECKPOINT_FORMAT)  # weights_only: a crafted file cannot run code
    try:
        agent = build_agent(health_config_from_dict(payload["config"]))
        agent.world_model.load_state_dict(payload["world_model"])
        agent.actor.load_state_dict(payload["actor"])
        agent.value.load_state_dict(payload["value"])
    except (KeyError, ConfigError, RuntimeError, TypeError) as err:  # incomplete, foreign or mismatched payload
        detail = f"missing entry {err}" if isinstance(err, KeyError) else str(err).splitlines()[0][:200]
        raise CheckpointError(f"health checkpoint {path} cannot be loaded: {detail}") from err
    return agent


def save_agent(agent: HealthAgent, run_dir: Path, **progress: Any) -> Path:
    """Write ``run_dir/checkpoint.pt`` through the shared atomic writer: a kill leaves the previous good file.

    ``progress`` (``iteration``, ``frames``) is stored beside the weights; :func:`load_agent` ignores it.
    """
    return save_checkpoint(run_dir, {**agent.state_dict(), **progress}, filename=CHECKPOINT_NAME)


# ----------------------------------------------------------------------------------------------------------------------
# training pieces
# ----------------------------------------------------------------------------------------------------------------------
def train_world_model_step(
    world_model: WorldModel, batch: TensorDictBase, optimizer: torch.optim.Optimizer, *, lambda_fm: float = 0.1,
    lambda_smooth: float = 1e-3, grad_clip: float | None = 1.0,
) -> dict[str, float]:  # fmt: skip
    """One gradient step of Eq. A27 on a ``[N, T]`` slice, plus the encoder's auxiliary losses when it has them
    (foundation: ``lambda_fm * loss_fm + lambda_smooth * loss_smooth``). Returns float metrics (``total`` includes
    the auxiliary terms; ``grad_norm``; ``skipped`` = 1.0 for a non-finite gradient, whose update is skipped)."""
    world_model.train()
    losses = world_model.loss(batch)
    total = losses["total"]
    enc = world_model.encoder
    aux = enc.aux_loss() if hasattr(enc, "aux_loss") else {}
    if "loss_fm" in aux:
        total = total + lambda_fm * aux["loss_fm"]
    if "loss_smooth" in aux:
        total = total + lambda_smooth * aux["loss_smooth"]
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    params = [p for g in optimizer.param_groups for p in g["params"]]
    gn = torch.nn.utils.clip_grad_norm_(params, grad_clip if grad_clip is not None else math.inf)
    skipped = not torch.isfinite(gn)
    if skipped:
        logger.warning("world model: non-finite gradient norm; update skipped")
    else:
        optimizer.step()
    if hasattr(enc, "clear_cache"):
        enc.clear_cache()
    out = {k: float(v.detach()) for k, v in losses.items()}
    out.update({k: float(v.detach()) for k, v in aux.items()})
    out["total"] = float(total.detach())
    out["grad_norm"] = float(gn)
    out["skipped"] = float(skipped)
    return out


@torch.no_grad()
def seed_latents(world_model: WorldModel, batch: TensorDictBase, num: int) -> TensorDict:
    """Posterior latents of replayed slices ``[N, T]`` (samples, as in training), ``num`` of them drawn at random
    from the ``N (T + 1)`` positions: ``TensorDict(deter=[num, D], stoch=[num, S])``."""
    out, _ = world_model.observe(batch)
    h = out["h"].reshape(-1, world_model.deter_dim)
    z = out["z"].reshape(-1, world_model.stoch_dim)
    idx = torch.randperm(h.shape[0])[:num]
    return TensorDict({"deter": h[idx], "stoch": z[idx]}, batch_size=[idx.numel()])


_STORE_KEYS = (
    "imu", "hr_features", "action", ("next", "imu"), ("next", "hr_features"), ("next", "reward"), ("next", "done"),
    ("next", "terminated"), ("next", "truncated"), ("collector", "traj_ids"),
)  # fmt: skip


def _episode_stats(data: TensorDictBase) -> dict[str, float]:
    """Mean return / violations / length of the episodes that ended in ``data`` (``nan`` when none)."""
    done = data.get(("next", "done")).squeeze(-1)
    n = int(done.sum())
    if n == 0:
        return {"episodes": 0, "return": float("nan"), "violations": float("nan"), "length": float("nan")}
    ep = data.get(("next", "episode"))[done]
    return {
        "episodes": n,
        "return": float(ep["return"].float().mean()),
        "violations": float(ep["violations"].float().mean()),
        "length": float(ep["length"].float().mean()),
    }


# ----------------------------------------------------------------------------------------------------------------------
# evaluation
# ----------------------------------------------------------------------------------------------------------------------
def rollout_metrics(traj: TensorDictBase) -> dict[str, float]:
    """Per-episode metrics of a real-env rollout ``[n, L]`` (``break_when_any_done=False``, ``L`` >= the episode
    length), read at each env's first ``("next", "done")``: ``return_mean``/``return_std`` (over episodes),
    ``violations_mean``, ``length_mean``, ``episodes``. Raises ``ValueError`` when an env never finished."""
    if traj.batch_dims != 2:
        raise ValueError(f"rollout_metrics: expected a rollout [num_envs, steps], got batch shape {tuple(traj.shape)}")
    n = traj.shape[0]
    done = traj.get(("next", "done")).reshape(n, -1)  # [n, L]
    if not bool(done.any(-1).all()):
        raise ValueError(f"rollout_metrics: {int((~done.any(-1)).sum())} of {n} envs never reached done in "
                         f"{traj.shape[1]} steps; roll at least env.episode_length steps")  # fmt: skip
    first = done.float().argmax(dim=-1)
    ep = traj.get(("next", "episode"))[torch.arange(n), first]
    ret = ep["return"].float().squeeze(-1)
    return {
        "return_mean": float(ret.mean()),
        "return_std": float(ret.std(unbiased=False)),
        "violations_mean": float(ep["violations"].float().mean()),
        "length_mean": float(ep["length"].float().mean()),
        "episodes": n,
    }


@torch.no_grad()
def evaluate_policy(agent: HealthAgent, *, num_envs: int | None = None, seed: int = 10_000,
                    deterministic: bool = True) -> tuple[dict[str, float], TensorDictBase]:  # fmt: skip
    """Roll the policy in the real env: ``num_envs`` episodes of ``env.episode_length`` steps (one per env, from a
    fresh env with ``seed``). Returns (metrics, rollout ``[num_envs, episode_length]``).

    Metrics: ``return_mean``/``return_std`` (over episodes), ``violations_mean`` (steps with heart rate > 160
    bpm per episode), ``length_mean``, ``episodes``; read at each env's first ``("next", "done")``.
    """
    cfg = agent.cfg
    n = num_envs or cfg.eval.num_envs
    policy = agent.policy(sample_latent=False)
    env = make_health_env(cfg, num_envs=n, seed=seed, primer=policy.make_tensordict_primer())
    agent.world_model.eval()
    etype = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    with set_exploration_type(etype):
        traj = env.rollout(cfg.env.episode_length, policy, break_when_any_done=False)
    env.close()
    metrics = rollout_metrics(traj)
    actions = traj.get("action").reshape(-1)
    for i in range(NUM_ACTIONS):
        metrics[f"action_frac_{i}"] = float((actions == i).float().mean())
    keep = [k for k in _STORE_KEYS if k != ("collector", "traj_ids")] + [("next", "heart_rate"), "kl"]
    return metrics, traj.select(*keep, strict=False)


def _windows(traj: TensorDictBase, length: int, count: int, generator: torch.Generator) -> TensorDictBase | None:
    """``count`` random windows ``[count, length]`` of ``traj [E, L]`` without a ``done`` before their last step."""
    E, L = traj.shape
    if L < length:
        return None
    done = traj.get(("next", "done")).reshape(E, L).int()
    # window [s, s + length) is valid when no done in [s, s + length - 1)
    csum = torch.cat([torch.zeros(E, 1, dtype=torch.long), done.cumsum(-1)], dim=-1)  # [E, L + 1]
    starts = torch.arange(L - length + 1)
    bad = (csum[:, starts + length - 1] - csum[:, starts]) > 0  # [E, S]
    valid = (~bad).nonzero()
    if valid.shape[0] == 0:
        return None
    pick = valid[torch.randint(valid.shape[0], (count,), generator=generator)]
    idx = pick[:, 1:2] + torch.arange(length)  # [count, length]
    return traj[pick[:, 0:1].expand_as(idx), idx]


@torch.no_grad()
def reconstruction_mse(world_model: WorldModel, windows: TensorDictBase) -> dict[str, float]:
    """Raw-unit reconstruction MSE on ``windows [N, T]``: per key and ``recon_mse = sum_k d_k mse_k / sum_k d_k``."""
    world_model.eval()
    losses = world_model.loss(windows)
    out = {}
    num = 0.0
    for k, d in world_model.obs_dims.items():
        name = k if isinstance(k, str) else "_".join(k)
        v = float(losses[f"mse_{name}"])
        out[f"recon_mse_{name}"] = v
        num += d * v
    out["recon_mse"] = num / sum(world_model.obs_dims.values())
    return out


@torch.no_grad()
def imagination_horizon(world_model: WorldModel, windows: TensorDictBase, context: int,
                        reward_tol: float) -> torch.Tensor:  # fmt: skip
    """Open-loop reward-prediction horizon of each window (module docstring): ``windows [N, C + H_max]`` ->
    ``[N]`` float (number of imagined steps before the first reward error ``> reward_tol`` or false predicted
    termination; ``H_max`` when none)."""
    world_model.eval()
    N, L = windows.shape
    H = L - context
    if context < 1 or H < 1:
        raise ValueError(f"imagination_horizon: need context >= 1 and a window longer than it; got context "
                         f"{context}, window {L}")  # fmt: skip
    out, _ = world_model.observe(windows[:, :context], sample=False)
    h, z = out["h"][:, -1], out["post_mean"][:, -1]
    actions = world_model.action_to_onehot(windows.get("action")[:, context:], 2)
    real_r = windows.get(("next", "reward")).reshape(N, L)[:, context:]
    real_term = windows.get(("next", "terminated")).reshape(N, L)[:, context:]
    fail = torch.zeros(N, H, dtype=torch.bool)
    for k in range(H):
        h, _, z = world_model.rssm.imagine_step(h, z, actions[:, k], sample=False)
        feat = world_model.features(h, z)
        r_hat = world_model.reward_head(feat).squeeze(-1)
        pred_term = torch.sigmoid(world_model.continue_head(feat).squeeze(-1)) < 0.5
        fail[:, k] = ((r_hat - real_r[:, k]).abs() > reward_tol) | (pred_term & ~real_term[:, k])
    any_fail = fail.any(-1)
    first = fail.float().argmax(-1)
    return torch.where(any_fail, first, torch.full_like(first, H)).float()


def _world_model_metrics(agent: HealthAgent, traj: TensorDictBase, seed: int) -> dict[str, float]:
    cfg = agent.cfg
    g = torch.Generator().manual_seed(seed)
    out: dict[str, float] = {}
    w = _windows(traj, cfg.world_model.seq_len, cfg.eval.mse_windows, g)
    if w is not None:
        out.update(reconstruction_mse(agent.world_model, w))
    ctx, hmax = cfg.eval.horizon_context, cfg.eval.horizon_max
    w = _windows(traj, ctx + hmax, cfg.eval.horizon_windows, g)
    if w is not None:
        hz = imagination_horizon(agent.world_model, w, ctx, cfg.eval.horizon_reward_tol)
        out["imagination_horizon"] = float(hz.mean())
        out["imagination_horizon_std"] = float(hz.std(unbiased=False))
    return out


def _evaluate(agent: HealthAgent) -> dict[str, float]:
    cfg = agent.cfg
    metrics, traj = evaluate_policy(agent, seed=cfg.eval.seed, deterministic=cfg.eval.deterministic)
    metrics.update(_world_model_metrics(agent, traj, cfg.eval.seed))
    return metrics


# ----------------------------------------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------------------------------------
def _git_info() -> dict[str, Any]:
    from freamer_rl.train import git_commit

    return git_commit()


def _write_run_files(cfg: HealthConfig, run_dir: Path) -> None:
    import tensordict
    import torchrl

    (run_dir / "config.yaml").write_text(yaml.safe_dump(health_config_to_dict(cfg), sort_keys=False))
    info = {
        **_git_info(),
        "command": sys.argv,
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "tensordict": tensordict.__version__,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    (run_dir / "run_info.json").write_text(json.dumps(info, indent=2))


def _write_progress(path: Path, rows: list[dict]) -> None:
    fields: list[str] = []
    for r in rows:
        fields += [k for k in r if k not in fields]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for r in rows:
            writer.writerow(r)


def _mean_rows(rows: list[dict[str, float]], prefix: str) -> dict[str, float]:
    if not rows:
        return {}
    keys = rows[0].keys()
    return {f"{prefix}{k}": float(np.mean([r[k] for r in rows if k in r])) for k in keys}


def _param_count(m: nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def default_run_dir(cfg: HealthConfig) -> Path:
    name = cfg.run.name or f"health-{cfg.encoder.kind}-s{cfg.run.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    return Path(cfg.run.output_dir) / name


def run_health(cfg: HealthConfig, run_dir: str | Path | None = None) -> dict[str, Any]:
    """Train a health agent (collect -> world model -> imagination PPO, repeated) and evaluate it in the real env.

    Writes ``config.yaml``, ``run_info.json``, ``progress.csv``, ``summary.json`` and ``checkpoint.pt`` into
    ``run_dir`` (default ``<run.output_dir>/<run.name or health-<kind>-s<seed>-<time>>``) and returns the summary:
    ``eval_return_mean``/``_std``, ``eval_violations_mean``, ``eval_length_mean``, ``recon_mse`` (+ per key),
    ``imagination_horizon`` (+ ``_std``), ``frames``, ``wall_time_s``, parameter counts, FM gates (foundation).
    """
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir(cfg)
    with RunDirLock(run_dir):  # a second run on the same directory is refused with a line naming this one
        remove_stale_temps(run_dir)  # temporary files of a killed checkpoint write
        return _run_health(cfg, run_dir)


def _run_health(cfg: HealthConfig, run_dir: Path) -> dict[str, Any]:
    """:func:`run_health`'s body, run while holding the run directory's lock."""
    from tqdm.auto import tqdm

    torch.set_num_threads(cfg.run.threads)
    torch.manual_seed(cfg.run.seed)
    np.random.seed(cfg.run.seed)
    _write_run_files(cfg, run_dir)
    t_start = time.perf_counter()

    agent = build_agent(cfg)
    wm = agent.world_model
    wc, ic, cc = cfg.world_model, cfg.imagination, cfg.collect
    policy = agent.policy(sample_latent=True, random_actions=True, explore_probs=cc.explore_probs)
    env = make_health_env(cfg, seed=cfg.run.seed, primer=policy.make_tensordict_primer())
    collector = Collector(env, policy, frames_per_batch=cc.frames_per_iter, total_frames=-1,
                          auto_register_policy_transforms=False)  # fmt: skip
    batches = iter(collector)
    rb = ReplayBuffer(
        storage=LazyTensorStorage(cc.buffer_capacity),
        sampler=SliceSampler(slice_len=wc.seq_len, traj_key=("collector", "traj_ids"), strict_length=True),
        batch_size=wc.batch_size * wc.seq_len,
    )
    wm_opt = torch.optim.Adam(wm.parameters(), lr=wc.lr, eps=wc.adam_eps)
    imag_env = RSSMWorldModelEnv(wm, done_mode=ic.done_mode)
    algo = ImaginationPPO(
        imag_env, agent.actor, agent.value, horizon=ic.horizon, gamma=ic.gamma, lmbda=ic.lmbda,
        clip_epsilon=ic.clip_epsilon, epochs=ic.epochs, num_minibatches=ic.num_minibatches,
        entropy_coeff=ic.entropy_coeff, critic_coeff=ic.critic_coeff, lr=ic.lr, adam_eps=ic.adam_eps,
        max_grad_norm=ic.max_grad_norm, lambda_return_actor_critic=ic.lambda_return_actor_critic,
    )  # fmt: skip
    frames = 0
    rows: list[dict[str, Any]] = []

    def collect() -> dict[str, float]:
        nonlocal frames
        wm.eval()
        data = next(batches)
        frames += data.numel()
        rb.extend(data.select(*_STORE_KEYS).reshape(-1))
        return _episode_stats(data)

    def sample() -> TensorDictBase:
        return as_sequences(rb.sample(), wc.seq_len)

    def train_wm(steps: int) -> dict[str, float]:
        hist = [train_world_model_step(wm, sample(), wm_opt, lambda_fm=wc.lambda_fm, lambda_smooth=wc.lambda_smooth,
                                       grad_clip=wc.grad_clip) for _ in range(steps)]  # fmt: skip
        return _mean_rows(hist, "wm_")

    def train_policy() -> dict[str, float]:
        wm.eval()
        hist = [algo.update(seed_latents(wm, sample(), ic.num_seeds)) for _ in range(ic.updates)]
        return _mean_rows(hist, "ppo_")

    # -- random prefill --------------------------------------------------------------------------------------------
    n_prefill = math.ceil(cc.prefill_frames / cc.frames_per_iter)
    prefill_stats = [collect() for _ in range(n_prefill)]
    if n_prefill:
        row: dict[str, Any] = {"iteration": 0, "frames": frames}
        ep = [s for s in prefill_stats if s["episodes"]]
        row["train_episodes"] = sum(s["episodes"] for s in ep)
        row["train_return"] = float(np.mean([s["return"] for s in ep])) if ep else float("nan")
        row.update(train_wm(wc.prefill_train_steps))
        row["wall_s"] = time.perf_counter() - t_start
        rows.append(row)
        logger.info("prefill: %d random frames, %d world-model steps", frames, wc.prefill_train_steps)
    policy.random_actions = False
    policy.random_action_prob = cc.random_action_prob

    pbar = tqdm(range(1, cc.iterations + 1), desc=f"health[{cfg.encoder.kind}]", disable=not cfg.run.progress_bar)
    for it in pbar:
        stats = collect()
        row = {"iteration": it, "frames": frames, "train_episodes": stats["episodes"],
               "train_return": stats["return"], "train_violations": stats["violations"]}  # fmt: skip
        row.update(train_wm(wc.train_steps))
        row.update(train_policy())
        gates = getattr(wm.encoder, "gates", None)
        if gates:
            row.update({f"gate_{m}": g for m, g in gates.items()})
        if cfg.eval.every and it % cfg.eval.every == 0 and it != cc.iterations:
            row.update({f"eval_{k}": v for k, v in _evaluate(agent).items()})
        row["wall_s"] = time.perf_counter() - t_start
        rows.append(row)
        _write_progress(run_dir / "progress.csv", rows)
        save_agent(agent, run_dir, iteration=it, frames=frames)  # each iteration: a crash keeps a usable agent
        pbar.set_postfix(frames=frames, ret=f"{stats['return']:.1f}", rec=f"{row.get('wm_loss_rec', float('nan')):.2f}")
    collector.shutdown()

    final = _evaluate(agent)
    if rows:
        rows[-1].update({f"eval_{k}": v for k, v in final.items()})
    _write_progress(run_dir / "progress.csv", rows)
    save_agent(agent, run_dir, iteration=cc.iterations, frames=frames)
    wall = time.perf_counter() - t_start
    summary = {
        "encoder": cfg.encoder.kind,
        "seed": cfg.run.seed,
        "iterations": cc.iterations,
        "frames": frames,
        "wall_time_s": wall,
        **{f"eval_{k}": v for k, v in final.items() if not k.startswith(("recon", "imagination"))},
        **{k: v for k, v in final.items() if k.startswith(("recon", "imagination"))},
        "imagination_horizon_definition": {
            "context": cfg.eval.horizon_context, "max": cfg.eval.horizon_max,
            "reward_tol": cfg.eval.horizon_reward_tol, "windows": cfg.eval.horizon_windows,
        },  # fmt: skip
        "params_world_model": _param_count(wm),
        "params_encoder": _param_count(wm.encoder),
        "params_policy": _param_count(agent.actor) + _param_count(agent.value),
        "gates": getattr(wm.encoder, "gates", None),
        "run_dir": str(run_dir),
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    logger.info("health run finished: %s", {k: summary[k] for k in ("eval_return_mean", "recon_mse")
                                             if k in summary})  # fmt: skip
    return summary


# ----------------------------------------------------------------------------------------------------------------------
# anomaly report (J.5, Fig. 4)
# ----------------------------------------------------------------------------------------------------------------------
def _logits_net(actor: ProbabilisticActor) -> nn.Module:
    """The ``latent -> logits`` network inside a :func:`build_actor_value` actor."""
    inner = actor.module[0]
    if not isinstance(inner, TensorDictModule) or list(inner.out_keys) != ["logits"]:
        raise TypeError("expected an actor built by build_actor_value (TensorDictModule latent -> logits first)")
    return inner.module


@torch.no_grad()
def record_episode(
    agent: HealthAgent, steps: int, *, seed: int = 0, deterministic: bool = True, progress_bar: bool = False,
    episode_length: int | None = None,
) -> dict[str, np.ndarray]:  # fmt: skip
    """Run the trained policy for ``steps`` steps in a one-env copy of the real env and record the timeline.

    The same computation as :class:`HealthPolicy` (posterior means fed forward, the mode of the policy when
    ``deterministic``), written as a lean tensor loop around the base env (a TransformedEnv step costs several
    times more, which matters for a 48-hour scenario: 34,560 steps at 0.2 Hz, 172,800 at 1 Hz). The env's
    ``episode_length`` is set to ``max(steps, env.episode_length)``; a termination (heart rate >= 200 bpm) resets
    the env and the filter and the recording goes on.

    Returns numpy arrays of length ``steps``, element ``t`` describing step ``t``: ``heart_rate`` (bpm, observed
    at ``t``), ``activity``, ``action``, ``kl`` (``KL(q || p)`` of the posterior after observation ``t``, J.5),
    ``reward`` and ``done`` (after the action), ``is_first``.
    """
    from tqdm.auto import tqdm

    cfg = agent.cfg
    wm = agent.world_model
    wm.eval()
    enc = wm.encoder
    net = _logits_net(agent.actor)
    length = episode_length or max(steps, cfg.env.episode_length)
    env = env_registry.make_env(cfg.env.adapter, cfg.env.id, seed=seed, batch_size=1,
                                **{**_env_options(cfg), "episode_length": length})  # fmt: skip
    rec = {
        "heart_rate": np.empty(steps, np.float32), "activity": np.empty(steps, np.int64),
        "action": np.empty(steps, np.int64), "kl": np.empty(steps, np.float32), "reward": np.empty(steps, np.float32),
        "done": np.empty(steps, bool), "is_first": np.empty(steps, bool),
    }  # fmt: skip
    h, z = wm.rssm.initial_state((1,))
    prev = torch.zeros(1, wm.action_dim)
    state = enc.initial_state((1,)) if hasattr(enc, "initial_state") else {}
    first = torch.ones(1, dtype=torch.bool)
    td = env.reset()
    for t in tqdm(range(steps), desc="anomaly episode", disable=not progress_bar, mininterval=2.0):
        obs = {k: td.get(k) for k in wm.obs_dims}
        if hasattr(enc, "step"):
            embed, state = enc.step(obs, state, first)
        else:
            embed = wm.embed(obs)
        out = wm.rssm.obs_step(h, z, prev, embed, is_first=first, sample=False)
        h, z = out["h"], out["z"]
        logits = net(torch.cat([h, z], dim=-1))
        action = logits.argmax(-1) if deterministic else torch.distributions.Categorical(logits=logits).sample()
        prev = F.one_hot(action, wm.action_dim).float()
        td.set("action", action)
        nxt = env.step(td).get("next")
        done = bool(nxt.get("done").any())
        rec["heart_rate"][t] = float(td.get("heart_rate").reshape(-1)[0])
        rec["activity"][t] = int(td.get("activity").reshape(-1)[0])
        rec["action"][t] = int(action[0])
        rec["kl"][t] = float(gaussian_kl(out["post_mean"], out["post_std"], out["prior_mean"], out["prior_std"])[0])
        rec["reward"][t] = float(nxt.get("reward").reshape(-1)[0])
        rec["done"][t] = done
        rec["is_first"][t] = bool(first[0])
        if done:
            td = env.reset()
            first = torch.ones(1, dtype=torch.bool)
        else:
            td = nxt
            first = torch.zeros(1, dtype=torch.bool)
    env.close()
    return rec


def anomaly_report(
    checkpoint_or_model: str | Path | HealthAgent,
    run_dir: str | Path,
    hours: float = 48.0,
    *,
    seed: int = 0,
    k_sigma: float = 2.0,
    warmup: int = 20,
    momentum: float | None = None,
    deterministic: bool = True,
    progress_bar: bool = True,
) -> dict[str, Any]:
    """Record one long episode with the trained policy, flag KL anomalies and draw the Fig. 4 picture.

    The scenario lasts ``hours`` at the env's step rate (``env.rate_hz``; 48 h at the recipes' 0.2 Hz = 34,560
    steps, at 1 Hz 172,800; roughly 1.5-8 ms a step on one CPU core, the foundation encoder being the slowest) and is
    recorded by :func:`record_episode` (``episode_length`` set to the whole scenario). The per-step ``KL(q || p)``
    of the online posterior (J.5) goes through :func:`~freamer_rl.world_model.anomaly.detect_anomalies`: a step is
    flagged when ``KL > running mean + k_sigma running std`` (statistics before the step, Welford or EMA with
    ``momentum``; none in the first ``warmup`` steps).

    Writes into ``run_dir``: ``anomaly_timeline.png`` (heart rate with zones, the agent's decisions, KL with flags
    and threshold; :func:`~freamer_rl.world_model.anomaly.plot_anomaly_timeline`), ``anomaly_episode.npz`` (the
    recorded arrays plus ``flag``, ``threshold``, ``time_h``) and ``anomaly_summary.json`` (returned).
    """
    agent = checkpoint_or_model if isinstance(checkpoint_or_model, HealthAgent) else load_agent(checkpoint_or_model)
    cfg = agent.cfg
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    steps = max(2, int(round(hours * 3600.0 * cfg.env.rate_hz)))
    rec = record_episode(agent, steps, seed=seed, deterministic=deterministic, progress_bar=progress_bar)
    flags, thr = detect_anomalies(torch.from_numpy(rec["kl"]), k_sigma=k_sigma, warmup=warmup, momentum=momentum)
    time_h = np.arange(steps, dtype=np.float64) / cfg.env.rate_hz / 3600.0
    hr, act, kl = rec["heart_rate"], rec["action"], rec["kl"]
    png = plot_anomaly_timeline(
        hr, act, kl, flags, run_dir / "anomaly_timeline.png", time_hours=time_h, threshold=thr,
        title=f"{hours:g}-hour scenario, {cfg.encoder.kind} encoder: heart rate, decisions, KL anomalies "
              f"(KL > mean + {k_sigma:g} std)",
    )  # fmt: skip
    fl = flags.numpy()
    np.savez_compressed(run_dir / "anomaly_episode.npz", **rec, flag=fl, threshold=thr.numpy(), time_h=time_h)
    summary = {
        "hours": hours,
        "steps": steps,
        "rate_hz": cfg.env.rate_hz,
        "encoder": cfg.encoder.kind,
        "k_sigma": k_sigma,
        "anomalies": int(fl.sum()),
        "anomaly_fraction": float(fl.mean()),
        "anomaly_hr_mean": float(hr[fl].mean()) if fl.any() else None,
        "hr_mean": float(hr.mean()),
        "hr_max": float(hr.max()),
        "danger_steps": int((hr > 160.0).sum()),
        "danger_steps_flagged": int(((hr > 160.0) & fl).sum()),
        "kl_mean": float(kl.mean()),
        "kl_std": float(kl.std()),
        "action_counts": {name: int((act == i).sum()) for i, name in
                          enumerate(("continue", "rest", "increase", "change", "alert"))},  # fmt: skip
        "return": float(rec["reward"].sum()),
        "terminations": int(rec["done"][:-1].sum()),
        "png": png,
    }
    (run_dir / "anomaly_summary.json").write_text(json.dumps(summary, indent=2))
    return summary
