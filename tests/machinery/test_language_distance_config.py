"""``shaping.language.distance`` (observed | oracle | none): checked as a choice naming the field, passed to the
env option, and the oracle reported as privileged information."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from freamer_rl.errors import ConfigError
from freamer_rl.machinery.checks import privileged_information
from freamer_rl.trainers.registry import load_config
from freamer_rl_envs.minigrid_language import language_reward_option


def test_default_is_observed():
    cfg = load_config(None, ["shaping.language.weight=0.2"])
    assert cfg.shaping.language.distance == "observed"
    assert language_reward_option(cfg)["distance"] == "observed"
    assert privileged_information(cfg) == []


@pytest.mark.parametrize("trainer", ["minigrid_ppo", "ppo_baseline"])
def test_unknown_distance_is_one_line_naming_the_field(trainer):
    with pytest.raises(ConfigError) as info:
        load_config(None, [f"trainer={trainer}", "shaping.language.distance=magic"])
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith("shaping.language.distance: expected one of observed, oracle, none")
    assert "'magic'" in msg


@pytest.mark.parametrize("distance", ["observed", "oracle", "none"])
def test_each_choice_reaches_the_env_option(distance):
    cfg = load_config(None, ["shaping.language.weight=0.2", f"shaping.language.distance={distance}"])
    assert language_reward_option(cfg)["distance"] == distance


@pytest.mark.parametrize(
    "overrides, expected",
    [
        (["shaping.language.weight=0.2", "shaping.language.distance=oracle"], ["shaping.language.distance=oracle"]),
        (["shaping.language.weight=0", "shaping.language.distance=oracle"], []),  # R_lang off: nothing read
        (["shaping.language.weight=0.2", "shaping.language.distance=observed"], []),
        (["shaping.language.weight=0.2", "shaping.language.distance=none"], []),
        (
            ["trainer=ppo_baseline", "shaping.language.weight=0.2", "shaping.language.distance=oracle"],
            ["shaping.language.distance=oracle"],
        ),
    ],
)
def test_privileged_information(overrides, expected):
    assert privileged_information(load_config(None, overrides)) == expected


def test_privileged_information_of_a_schema_without_shaping():
    assert privileged_information(SimpleNamespace(env=SimpleNamespace())) == []
