"""Config schemas of the baselines (light: the trainer registry imports them at start-up).

Each baseline's schema is :class:`freamer_rl.config.FreamerConfig` (env, ppo, collector, logging, run: the one
config loader and run layout) plus its own sections; each registers its validator in ``freamer_rl.config.VALIDATORS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from freamer_rl.config import VALIDATORS, ConfigError, FreamerConfig, validate

__all__ = ["NetworkConfig", "check_network", "PPOBaselineConfig"]


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
