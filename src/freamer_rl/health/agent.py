"""The health agent: the real env, the world model with its encoder, the actor-value pair, the online posterior
filter that acts in the real env (:class:`HealthPolicy`) and the agent checkpoint (``checkpoint.pt``).

Sizes come from the env: the observation sizes of :data:`~freamer_rl.health.config.OBS_KEYS` and the number of
actions are read from the env's specs (:func:`env_dims`), not repeated here.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import Categorical, Unbounded
from torchrl.envs import Compose, EnvBase, InitTracker, TransformedEnv
from torchrl.envs.transforms import TensorDictPrimer, Transform
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator

from freamer_rl.config.loader import config_from_dict
from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.health.config import (
    NUM_ACTIONS,
    OBS_KEYS,
    HealthConfig,
    HealthEncoderConfig,
    health_config_to_dict,
)
from freamer_rl.health.config import explore_probs as _explore_probs
from freamer_rl.health.encoders import HealthEncoder, make_health_encoder
from freamer_rl.layers.tdmodule import KeyedModule
from freamer_rl.run import env_registry
from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint, save_checkpoint
from freamer_rl.run.params import parameter_rows
from freamer_rl.world_model.functional import gaussian_kl
from freamer_rl.world_model.heads import TwoHotHead
from freamer_rl.world_model.rssm import WorldModel

__all__ = [
    "CHECKPOINT_NAME",
    "CHECKPOINT_FORMAT",
    "env_options",
    "env_dims",
    "make_health_env",
    "build_world_model",
    "build_actor_value",
    "HealthPolicy",
    "HealthAgent",
    "build_agent",
    "load_agent",
    "save_agent",
    "logits_net",
    "parameter_table",
]

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "freamer_rl.health/1"
_STATE = "wm_filter"  # root of the policy's recurrent state keys in the real env


# ----------------------------------------------------------------------------------------------------------------------
# env
# ----------------------------------------------------------------------------------------------------------------------
def env_options(cfg: HealthConfig) -> dict[str, Any]:
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
    cfg: HealthConfig,
    *,
    num_envs: int | None = None,
    seed: int | None = None,
    primer: TensorDictPrimer | None = None,
    corrupt: Sequence[Transform] = (),
    **overrides: Any,
) -> EnvBase:
    """The real env through the ``freamer_rl.envs`` registry (``env.adapter``, default ``health``), batch
    ``[num_envs]``, wrapped with ``InitTracker`` (+ ``primer``, the policy's recurrent state, + ``corrupt``, the
    training corruptions: :func:`freamer_rl.health.evaluation.corruption_for`). ``overrides`` replace adapter options
    (e.g. ``episode_length``)."""
    options = {**env_options(cfg), **overrides}
    base = env_registry.make_env(
        cfg.env.adapter, cfg.env.id, seed=seed, batch_size=num_envs or cfg.env.num_envs, **options
    )
    transforms = [InitTracker()]
    if primer is not None:
        transforms.append(primer)
    transforms.extend(corrupt)
    return TransformedEnv(base, Compose(*transforms))


@functools.lru_cache(maxsize=16)
def _spec_dims(adapter: str, env_id: str, options: tuple) -> tuple[dict[str, int], int]:
    env = env_registry.make_env(adapter, env_id, seed=0, batch_size=1, **dict(options))
    try:
        obs = env.observation_spec
        missing = [k for k in OBS_KEYS if k not in obs.keys()]
        if missing:
            raise ConfigError(f"env.id {env_id!r}: observation spec lacks {missing} (has {sorted(obs.keys())})")
        dims = {k: int(obs[k].shape[-1]) for k in OBS_KEYS}
        if not isinstance(env.action_spec, Categorical):
            raise ConfigError(
                f"env.id {env_id!r}: expected a Categorical action spec, got {type(env.action_spec).__name__}"
            )
        return dims, int(env.action_spec.n)
    finally:
        env.close()


def env_dims(cfg: HealthConfig) -> tuple[dict[str, int], int]:
    """``({obs key: size}, number of actions)`` read from the configured env's specs (one probe env per config)."""
    options = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in env_options(cfg).items()))
    dims, n_actions = _spec_dims(cfg.env.adapter, cfg.env.id, options)
    if n_actions != NUM_ACTIONS:
        raise ConfigError(
            f"env.id {cfg.env.id!r}: {n_actions} actions, the health schema (collect.explore_probs, "
            f"action names) expects {NUM_ACTIONS}"
        )
    return dims, n_actions


# ----------------------------------------------------------------------------------------------------------------------
# models
# ----------------------------------------------------------------------------------------------------------------------
def _encoder_kwargs(cfg: HealthEncoderConfig) -> dict[str, Any]:
    if cfg.kind == "mlp":
        return {"hidden": cfg.hidden, "layers": cfg.mlp_layers}
    if cfg.kind == "cnn":
        return {"channels": cfg.cnn_channels, "hidden": cfg.hidden}
    common = {"dim": cfg.dim, "heads": cfg.heads, "hr_tokens": cfg.hr_tokens, "hidden": cfg.hidden}
    if cfg.kind == "slotattn":
        return common
    return {
        **common,
        "fm_hidden": cfg.fm_hidden,
        "fm_steps": cfg.fm_steps,
        "gate_init": dict(cfg.gate_init),
        "fm_noise_std": cfg.fm_noise_std,
        "fno_modes": cfg.fno_modes,
        "fno_residual_scale": cfg.fno_residual_scale,
        "memory_slots": cfg.memory_slots,
        "memory_width": cfg.memory_width,
    }


def build_world_model(cfg: HealthConfig) -> WorldModel:
    """WorldModel (same RSSM core for every encoder) with the configured encoder."""
    obs_dims, n_actions = env_dims(cfg)
    enc = make_health_encoder(cfg.encoder.kind, cfg.encoder.embed_dim, **_encoder_kwargs(cfg.encoder))
    w = cfg.world_model
    return WorldModel(
        obs_dims,
        n_actions,
        encoder=enc,
        embed_dim=cfg.encoder.embed_dim,
        deter_dim=w.deter_dim,
        stoch_dim=w.stoch_dim,
        hidden=w.hidden,
        beta=w.beta,
        free_nats=w.free_nats,
        kl_balance=w.kl_balance,
        recon_norm=w.recon_norm,
        reward_scale=w.reward_scale,
        reward_head_kind=w.reward_head,
        ensemble=w.ensemble,
    )


def build_actor_value(
    latent_dim: int, hidden: int, num_actions: int = NUM_ACTIONS, value_head: str = "mse"
) -> tuple[ProbabilisticActor, ValueOperator]:
    """Categorical actor (``num_actions`` logits) and value MLPs on ``"latent"`` ``[*B, D + S]``; ``value_head``
    ``"twohot"`` makes the value a :class:`~freamer_rl.world_model.heads.TwoHotHead` (``imagination.value_head``)."""
    actor = ProbabilisticActor(
        KeyedModule(
            MLP(in_features=latent_dim, out_features=num_actions, num_cells=[hidden, hidden], activation_class=nn.SiLU),
            in_keys=["latent"],
            out_keys=["logits"],
        ),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
        spec=Categorical(num_actions),
    )
    if value_head == "twohot":
        net: nn.Module = TwoHotHead(latent_dim, hidden, layers=2)
    else:
        net = MLP(in_features=latent_dim, out_features=1, num_cells=[hidden, hidden], activation_class=nn.SiLU)
    value = ValueOperator(net, in_keys=["latent"])
    return actor, value


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

    def __init__(
        self,
        world_model: WorldModel,
        actor: TensorDictModuleBase,
        *,
        sample_latent: bool = True,
        random_actions: bool = False,
        random_action_prob: float = 0.0,
        explore_probs: list[float] | None = None,
    ) -> None:
        super().__init__()
        if not 0.0 <= random_action_prob <= 1.0:
            raise ValueError(f"random_action_prob: expected a probability in [0, 1], got {random_action_prob}")
        enc = world_model.encoder
        if not isinstance(enc, HealthEncoder):
            raise TypeError(
                f"HealthPolicy: the world model's encoder {type(enc).__name__} does not implement the "
                "HealthEncoder protocol (freamer_rl.health.encoders)"
            )
        self.explore_probs = _explore_probs(explore_probs, world_model.action_dim, "explore_probs")
        self.world_model = world_model
        self.actor = actor
        self.sample_latent = sample_latent
        self.random_actions = random_actions
        self.random_action_prob = random_action_prob
        self._enc_shapes = dict(enc.state_shapes())
        self.obs_keys = list(world_model.obs_dims)
        self.state_keys = {
            "deter": (_STATE, "deter"),
            "stoch": (_STATE, "stoch"),
            "prev_action": (_STATE, "prev_action"),
        }
        self.enc_keys = {n: (_STATE, "enc", n) for n in self._enc_shapes}
        self.in_keys = [*self.obs_keys, "is_init", *self.state_keys.values(), *self.enc_keys.values()]
        self.out_keys = [
            "latent",
            "kl",
            "logits",
            "action",
            "action_log_prob",
            *[("next", *k) for k in (*self.state_keys.values(), *self.enc_keys.values())],
        ]

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
        missing = [
            k
            for k in (*self.state_keys.values(), *self.enc_keys.values())
            if k not in tensordict.keys(include_nested=True)
        ]
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
        state = {n: tensordict.get(k) for n, k in self.enc_keys.items()}
        embed, new_state = wm.encoder.step(obs, state, first)
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
    ic = cfg.imagination
    actor, value = build_actor_value(wm.latent_dim, ic.policy_hidden, wm.action_dim, ic.value_head)
    return HealthAgent(cfg, wm, actor, value)


def load_agent(path: str | Path) -> HealthAgent:
    """Load a health agent: ``checkpoint.pt`` (:func:`save_agent`), a resume checkpoint of the health trainer, or
    a run directory (its ``checkpoint.pt``, else its latest resume checkpoint)."""
    path = Path(path)
    if path.is_dir():
        final = path / CHECKPOINT_NAME
        path = final if final.is_file() else (latest_checkpoint(path) or final)
    payload = read_checkpoint(path, fmt=CHECKPOINT_FORMAT)  # weights_only: a crafted file cannot run code
    try:
        agent = build_agent(config_from_dict(payload["config"], HealthConfig, migrate=True))
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


def logits_net(actor: ProbabilisticActor) -> nn.Module:
    """The ``latent -> logits`` network inside a :func:`build_actor_value` actor."""
    inner = actor.module[0]
    if not isinstance(inner, TensorDictModule) or list(inner.out_keys) != ["logits"]:
        raise TypeError("expected an actor built by build_actor_value (TensorDictModule latent -> logits first)")
    return inner.module


def parameter_table(agent: HealthAgent) -> list[dict]:
    """Rows ``{"component", "trainable", "frozen"}`` (encoder, RSSM + heads + decoder, actor, value) and ``Total``
    (:func:`freamer_rl.run.params.parameter_rows`, the format of ``format_parameter_table``)."""
    wm = agent.world_model
    return parameter_rows(
        {
            f"encoder ({agent.cfg.encoder.kind})": wm.encoder,
            "RSSM, decoder, reward/continue heads": wm,  # the encoder's parameters are already counted above
            "actor": agent.actor,
            "value": agent.value,
        }
    )
