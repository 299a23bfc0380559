"""A user's own gymnasium env (Dict observations included) and a MiniGrid id through the ``gym`` adapter train from
the CLI: ``env.imports: [module]`` or gymnasium's ``module:EnvId`` form of ``env.id``."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
import yaml

from freamer_rl import cli
from freamer_rl.errors import EnvSetupError
from freamer_rl.run import env_registry
from freamer_rl_envs.gym import make_gym_env

# a Dict-observation env the way a user writes one: its own module registers its id on import
ENV_MODULE = '''
import gymnasium as gym
import numpy as np
from gymnasium import spaces


class DictEnv(gym.Env):
    """Reward 1 for action 1; 10 steps an episode; a Dict of two plain vectors and a text entry."""

    def __init__(self):
        self.observation_space = spaces.Dict({
            "pos": spaces.Box(-1.0, 1.0, (3,), np.float32),
            "vel": spaces.Box(-1.0, 1.0, (2,), np.float32),
            "note": spaces.Text(8),
        })
        self.action_space = spaces.Discrete(2)
        self.t = 0

    def _obs(self):
        return {"pos": self.np_random.uniform(-1, 1, 3).astype(np.float32), "vel": np.zeros(2, np.float32),
                "note": "hi"}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        return self._obs(), float(action), self.t >= 10, False, {}


gym.register("{env_id}", entry_point="{module}:DictEnv")
'''

TINY = {
    "env": {"adapter": "gym", "num_envs": 2},
    "model": {
        "embed_dim": 32,
        "head_hidden": 32,
        "flow": {"hidden": 32, "steps": 2},
        "fno": {"modes": 8},
        "dnc": {"memory_slots": 8, "memory_width": 16},
        "state": {"channels": 8, "modes": 6},
    },
    "ppo": {"frames_per_batch": 64, "sequence_length": 8, "minibatch_size": 32, "epochs": 1},
    "run": {"total_frames": 128},
    "logging": {"checkpoint_every_frames": 128, "progress_bar": False},
}


def _user_module(tmp_path: Path, monkeypatch, module: str, env_id: str) -> None:
    (tmp_path / f"{module}.py").write_text(
        textwrap.dedent(ENV_MODULE).replace("{module}", module).replace("{env_id}", env_id)
    )
    monkeypatch.syspath_prepend(str(tmp_path))


def _train(tmp_path: Path, env: dict, model: dict) -> dict:
    recipe = {**TINY, "env": {**TINY["env"], **env}, "model": {**TINY["model"], **model}}
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    run = tmp_path / "run"
    assert cli.main(["train", str(path), "--run-dir", str(run)]) == 0
    return json.loads((run / "summary.json").read_text())


VECTORS = {"modalities": ["vector"], "observation_keys": {"vector": ["pos", "vel"]}}


def test_a_dict_env_of_the_users_module_trains_through_env_imports(tmp_path, monkeypatch):
    _user_module(tmp_path, monkeypatch, "byo_env_imports", "ByoDictImports-v0")
    summary = _train(tmp_path, {"id": "ByoDictImports-v0", "imports": ["byo_env_imports"]}, VECTORS)
    assert summary["frames"] == 128 and summary["episodes"] == 12  # 10-step episodes, 2 envs x 64 steps
    assert summary["final_return_mean"] >= 0 and set(summary["gates"]) == {"vector"}


def test_module_colon_env_id_imports_the_module(tmp_path, monkeypatch):
    _user_module(tmp_path, monkeypatch, "byo_env_colon", "ByoDictColon-v0")
    summary = _train(tmp_path, {"id": "byo_env_colon:ByoDictColon-v0"}, VECTORS)
    assert summary["frames"] == 128 and summary["env"] == "byo_env_colon:ByoDictColon-v0"


def test_entries_without_a_torchrl_spec_are_left_out(tmp_path, monkeypatch):
    _user_module(tmp_path, monkeypatch, "byo_env_text", "ByoDictText-v0")
    env = make_gym_env("byo_env_text:ByoDictText-v0", seed=0)
    assert set(env.observation_spec.keys()) == {"pos", "vel"}  # the Text entry "note" has no TorchRL spec
    assert env.rollout(3)["next", "pos"].shape == (3, 3)


def test_a_minigrid_id_through_the_gym_adapter_trains(tmp_path):
    """MiniGrid's mission (a MissionSpace) is left out; its image and direction feed the state modality."""
    env = make_gym_env("minigrid:MiniGrid-Empty-5x5-v0")
    assert set(env.observation_spec.keys()) == {"image", "direction"}
    summary = _train(
        tmp_path,
        {"id": "minigrid:MiniGrid-Empty-5x5-v0"},
        {"modalities": ["state"], "observation_keys": {"state": ["image", "direction"]}},
    )
    assert summary["frames"] == 128 and set(summary["gates"]) == {"state"}


def test_a_module_that_cannot_be_imported_is_one_line():
    with pytest.raises(
        EnvSetupError, match=r"env.id 'no_such_user_module:X-v0' .*module 'no_such_user_module'"
    ) as info:
        env_registry.make_env("gym", "no_such_user_module:X-v0")
    assert "\n" not in str(info.value)
