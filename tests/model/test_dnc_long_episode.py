"""A long episode must not degrade the DNC memory (issue 21): the CartPole recipe's policy module, built by the factory,
run over the 1,200 observations of one CartPole episode (memory reset only at its start)."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.libs.gym import GymWrapper
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode

from freamer_rl.config.loader import load_config
from freamer_rl.errors import ConfigError
from freamer_rl.model.weights import load_model_state
from freamer_rl.trainers.minigrid_ppo import FreamerConfig, build_modules

RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "gym" / "cartpole.yaml"
STEPS = 1_200
#: a linear controller on (x, x_dot, theta, theta_dot) that keeps CartPole up for 3,000+ steps (seeds 0-4 checked),
#: so the episode (and the memory's life) really lasts STEPS steps whatever the untrained policy would do
_CONTROLLER = torch.tensor([0.5, 1.0, 10.0, 2.0])


def _modules(write: str, *overrides: str):
    torch.manual_seed(0)
    cfg = load_config(RECIPE, [f"model.dnc.write={write}", *overrides], schema=FreamerConfig)
    return build_modules(cfg)


def _small_erase(modules) -> None:
    """Erase logits near -5 (e ~ 0.007): the additive write's fixed point a / e is then ~150, far past the clamp."""
    dnc = modules.dnc.dnc
    w = dnc.memory_width
    with torch.no_grad():
        dnc.interface.weight[w + 1 : 2 * w + 1] *= 0.1
        dnc.interface.bias[w + 1 : 2 * w + 1] = -5.0


def _episode_observations(steps: int) -> torch.Tensor:
    """The observations ``[steps, 4]`` of one CartPole episode driven by :data:`_CONTROLLER` (it must not end)."""
    env = gymnasium.make("CartPole-v1", max_episode_steps=steps + 1)
    obs, _ = env.reset(seed=0)
    rows = []
    for t in range(steps):
        rows.append(torch.as_tensor(obs, dtype=torch.float32))
        obs, _, terminated, truncated, _ = env.step(int(rows[-1] @ _CONTROLLER > 0))
        assert not (terminated or truncated), f"the episode ended at step {t + 1}"
    env.close()
    return torch.stack(rows)


def _long_episode(modules, steps: int = STEPS) -> tuple[torch.Tensor, torch.Tensor]:
    """The recipe's policy module over one ``steps``-step CartPole episode as a ``[1, T]`` sequence (recurrent mode:
    the memory is threaded through all T steps from the zero memory at ``is_init``, the same maths as stepping, see
    tests/layers/test_dnc.py); returns ``(max |M| [T], ||M||_F [T])`` of the memory after each step."""
    obs = _episode_observations(steps).unsqueeze(0)
    is_init = torch.zeros(1, steps, 1, dtype=torch.bool)
    is_init[:, 0] = True
    td = TensorDict(
        {
            "observation": obs,
            "is_init": is_init,
            ("dnc", "memory"): torch.zeros(1, steps, *modules.dnc.dnc.memory_shape),
        },
        [1, steps],
    )
    with torch.no_grad(), set_recurrent_mode(True), set_exploration_type(ExplorationType.RANDOM):
        memory = modules.policy(td)["next", "dnc", "memory"][0]  # [T, N, W]
    return memory.abs().amax(dim=(-2, -1)), memory.flatten(1).norm(dim=-1)


def test_recipe_memory_stays_bounded_over_a_long_episode():
    modules = _modules("bounded")
    dnc = modules.dnc.dnc
    peaks, norms = _long_episode(modules)
    n, w = dnc.memory_shape
    assert peaks.max() <= 1.0 + 1e-6 and dnc.clip_events == 0
    assert norms.max() <= (n * w) ** 0.5 + 1e-4  # |M_ij| <= 1 for all N * W entries
    assert norms[-200:].min() > 0.1  # the memory is written to all along (a bound on a zero memory proves nothing)


@pytest.mark.parametrize("write", ["additive", "bounded"])
def test_small_erase_saturates_only_the_additive_write(write):
    modules = _modules(write)
    _small_erase(modules)
    dnc = modules.dnc.dnc
    peaks, _ = _long_episode(modules, steps=600)
    if write == "additive":
        assert peaks.max() == dnc.memory_clip and dnc.clip_events > 0  # today's saturation, reproduced
    else:
        assert peaks.max() <= 1.0 + 1e-6 and dnc.clip_events == 0


def test_write_and_output_norm_choices_reach_the_trunk():
    modules = _modules("bounded", "model.dnc.output_norm=true")
    assert modules.dnc.dnc.write_mode == "bounded" and modules.dnc.dnc.out_norm is not None
    assert _modules("additive").dnc.dnc.out_norm is None
    with pytest.raises(ConfigError, match="model.dnc.write: expected one of additive, bounded, got 'sum'"):
        load_config(RECIPE, ["model.dnc.write=sum"], schema=FreamerConfig)


def test_a_checkpoint_of_before_the_choice_loads_as_additive(tmp_path):
    """Today's checkpoints hold no write_code (and their config no model.dnc.write): they were trained with the
    additive write, and load as additive into a model built with the bounded one."""
    old = _modules("additive")
    state = {k: v for k, v in old.actor_value.state_dict().items() if not k.endswith("write_code")}
    new = _modules("bounded")
    load_model_state(new, state, tmp_path / "checkpoint.pt")
    assert new.dnc.dnc.write_mode == "additive"
    td = old.policy(_reset_td(old))
    torch.testing.assert_close(new.policy(_reset_td(new))["logits"], td["logits"])


def _reset_td(modules):
    base = GymWrapper(gymnasium.make("CartPole-v1"), categorical_action_encoding=True)
    env = TransformedEnv(base, Compose(InitTracker(), *modules.primers()))
    env.set_seed(0)
    td = env.reset()
    env.close()
    return td
