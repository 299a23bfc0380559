"""Config schemas of the baselines (light: the trainer registry imports them at start-up).

Each baseline's schema is :class:`freamer_rl.config.FreamerConfig` (env, ppo, collector, logging, run: the one
config loader and run layout) plus its own sections; each registers its validator in ``freamer_rl.config.VALIDATORS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from freamer_rl.config import VALIDATORS, ConfigError, FreamerConfig, validate

__all__ = ["NetworkConfig", "check_network", "PPOBaselineConfig", "ImpalaSection", "ImpalaConfig"]


@dataclass
class NetworkConfig:
    kind: str = "mlp"  # mlp | cnn
    observation_keys: list[str] = field(default_factory=lambda: ["grid", "direction"])
    hidden: int = 256  # width of the encoder's last layer and of the heads' hidden layer
    shared: bool = False  # one trunk for actor and critic (true) or one encoder each (false)
    cnn_channels: list[int] = field(default_factory=lambda: [32, 64, 64])


def check_network(net: NetworkConfig) -> None:
    """Every ``network`` field, named in the error."""
    if net.kind not in ("mlp", "cnn"):
        raise ConfigError(f"network.kind: expected 'mlp' or 'cnn', got {net.kind!r}")
    if not net.observation_keys:
        raise ConfigError("network.observation_keys: expected at least one observation key, got []")
    if len(set(net.observation_keys)) != len(net.observation_keys):
        raise ConfigError(f"network.observation_keys: duplicate keys in {net.observation_keys}")
    if net.hidden < 1:
        raise ConfigError(f"network.hidden: expected an int >= 1, got {net.hidden}")
    if len(net.cnn_channels) != 3 or min(net.cnn_channels) < 1:
        raise ConfigError(f"network.cnn_channels: expected 3 positive ints (one per conv layer), got "
                          f"{net.cnn_channels}")


@dataclass
class PPOBaselineConfig(FreamerConfig):
    network: NetworkConfig = field(default_factory=NetworkConfig)


def validate_ppo_baseline(cfg: PPOBaselineConfig) -> None:
    validate(cfg)
    check_network(cfg.network)


VALIDATORS[PPOBaselineConfig] = validate_ppo_baseline


@dataclass
class ImpalaSection:
    """IMPALA-only settings (``impala:``); the shared ones come from ``ppo`` (see :class:`ImpalaConfig`)."""

    rho_clip: float = 1.0  # rho-bar: clip of the importance ratio in the V-trace TD errors and the policy gradient
    c_clip: float = 1.0  # c-bar: clip of the traces c_t (<= rho_clip, the paper's assumption)
    optimizer: str = "adam"  # adam | rmsprop (the IMPALA paper's, with rmsprop_alpha; ppo.adam_eps is its eps)
    rmsprop_alpha: float = 0.99
    minibatches: int = 1  # gradient steps per collected batch, on random splits of its frames (1: the paper's)


@dataclass
class ImpalaConfig(FreamerConfig):
    """``trainer: impala``: the env / collector / logging / run sections, ``network`` (as the PPO baseline's) and
    ``impala``. From ``ppo`` it reads ``lr``, ``lr_schedule``, ``adam_eps``, ``max_grad_norm``, ``gamma``,
    ``entropy_coeff``, ``critic_coeff`` and ``frames_per_batch`` (a batch = ``frames_per_batch`` frames of one actor
    process, ``[env.num_envs, T]``); the PPO-only ones (clip, epochs, GAE lambda, minibatch size) are unused.

    Optimiser: Adam by default, not the paper's RMSprop -- the same optimiser, lr and grad clip as the PPO-MLP baseline
    it is compared with, so the comparison isolates V-trace + asynchronous actors; ``impala.optimizer: rmsprop``
    gives the paper's (and TorchRL's IMPALA example's) choice.
    """

    network: NetworkConfig = field(default_factory=NetworkConfig)
    impala: ImpalaSection = field(default_factory=ImpalaSection)


def validate_impala(cfg: ImpalaConfig) -> None:
    validate(cfg)
    check_network(cfg.network)
    s = cfg.impala
    if not s.rho_clip > 0:
        raise ConfigError(f"impala.rho_clip: expected a number > 0, got {s.rho_clip}")
    if not 0 < s.c_clip <= s.rho_clip:
        raise ConfigError(f"impala.c_clip: expected a number in (0, impala.rho_clip={s.rho_clip}], got {s.c_clip}")
    if s.optimizer not in ("adam", "rmsprop"):
        raise ConfigError(f"impala.optimizer: expected 'adam' or 'rmsprop', got {s.optimizer!r}")
    if not 0 <= s.rmsprop_alpha < 1:
        raise ConfigError(f"impala.rmsprop_alpha: expected a number in [0, 1), got {s.rmsprop_alpha}")
    if cfg.ppo.frames_per_batch % s.minibatches:
        raise ConfigError(f"impala.minibatches: got {s.minibatches}, must divide ppo.frames_per_batch "
                          f"({cfg.ppo.frames_per_batch})")  # fmt: skip


VALIDATORS[ImpalaConfig] = validate_impala
