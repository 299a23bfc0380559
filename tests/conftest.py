import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def _scripted_rollout(env, actions: torch.Tensor, seed: int):
    """``actions [steps, *batch]`` played from ``env.set_seed(seed)``; the step tensordicts stacked along time
    (dim 1), auto-resetting finished rows. Closes the env."""
    env.set_seed(seed)
    td = env.reset()
    rows = []
    for step_actions in actions:
        td.set("action", step_actions)
        step_td, td = env.step_and_maybe_reset(td)
        rows.append(step_td.exclude("action").clone())
    env.close()
    return torch.stack(rows, dim=1)


@pytest.fixture
def scripted_rollout():
    """The same actions through two envs give comparable data: ``scripted_rollout(env, actions, seed)``."""
    return _scripted_rollout
