"""MiniGrid adapter (envs/minigrid.py) and the word tokenizer (freamer_rl.data.text)."""

from __future__ import annotations

import functools
import pickle

import pytest
import torch
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX
from tensordict import TensorDict
from torchrl.envs import EnvCreator, InitTracker, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from freamer_rl.data.text import PAD_ID, UNK_ID, WordTokenizer
from freamer_rl_envs.minigrid import MINIGRID_VOCAB, MiniGridEnv, make_minigrid_env

EMPTY = "MiniGrid-Empty-5x5-v0"
# Empty-5x5: the agent starts at (1, 1) facing right, the goal is at (3, 3).
# forward, forward, turn right, forward, forward -> goal on the 5th step, reward 1 - 0.9 * 5 / 100 = 0.955.
EMPTY_SOLUTION = [2, 2, 1, 2, 2]


class ScriptedPolicy:
    """Plays a fixed action list (then repeats ``fill``)."""

    def __init__(self, actions: list[int], fill: int = 0) -> None:
        self.actions = list(actions)
        self.fill = fill
        self.t = 0

    def __call__(self, td: TensorDict) -> TensorDict:
        a = self.actions[self.t] if self.t < len(self.actions) else self.fill
        self.t += 1
        td.set("action", torch.full(td.batch_size, a, dtype=torch.int64))
        return td


# ------------------------------------------------------------------------------------------------------------------
# specs
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "env_id, pixels",
    [
        ("MiniGrid-MultiRoom-N2-S4-v0", False),
        ("MiniGrid-MultiRoom-N2-S4-v0", True),
        (EMPTY, False),
        ("MiniGrid-DoorKey-5x5-v0", False),
        ("MiniGrid-DoorKey-5x5-v0", True),
    ],
)
def test_check_env_specs(env_id, pixels):
    env = make_minigrid_env(env_id, seed=0, pixels=pixels)
    check_env_specs(env, seed=0)
    spec = env.observation_spec
    assert spec["grid"].shape == (7, 7, 3) and spec["grid"].dtype == torch.int64
    assert spec["direction"].shape == () and spec["direction"].dtype == torch.int64
    assert spec["mission_tokens"].shape == (16,) and spec["mission_tokens"].dtype == torch.int64
    assert spec["reward_history"].shape == (8,) and spec["reward_history"].dtype == torch.float32
    assert "mission" in spec.keys()
    assert ("pixels" in spec.keys()) == pixels
    assert env.action_spec.n == 7
    assert env.reward_spec.shape == (1,) and env.reward_spec.dtype == torch.float32
    for key in ("done", "terminated", "truncated"):
        assert env.full_done_spec[key].shape == (1,) and env.full_done_spec[key].dtype == torch.bool
    high = spec["grid"].space.high
    assert high[..., 0].max() == max(OBJECT_TO_IDX.values())
    assert high[..., 1].max() == max(COLOR_TO_IDX.values())
    assert high[..., 2].max() == max(STATE_TO_IDX.values())

    td = env.rollout(5)
    assert td["grid"].max() > 1, "grid must hold raw MiniGrid indices (walls = 2), not normalised values"
    assert td["mission"][0] == env._env.unwrapped.mission
    if pixels:
        assert td["pixels"].shape == (5, 56, 56, 3) and td["pixels"].dtype == torch.uint8
        assert td["pixels"].float().std() > 0
    env.close()


def test_options_shape_the_specs():
    env = make_minigrid_env(EMPTY, reward_history=3, max_mission_tokens=5, include_mission=False)
    td = env.reset()
    assert td["reward_history"].shape == (3,) and td["mission_tokens"].shape == (5,)
    assert "mission" not in td.keys() and "mission" not in env.observation_spec.keys()
    check_env_specs(env)
    env = make_minigrid_env(EMPTY, reward_history=0)
    assert "reward_history" not in env.reset().keys()
    with pytest.raises(ValueError, match="max_mission_tokens"):
        make_minigrid_env(EMPTY, max_mission_tokens=0)
    with pytest.raises(ValueError, match="reward_history"):
        make_minigrid_env(EMPTY, reward_history=-1)


def test_mission_tokens_match_mission():
    env = make_minigrid_env("MiniGrid-MultiRoom-N2-S4-v0", seed=0)
    td = env.reset()
    assert td["mission"] == "traverse the rooms to get to the goal"
    assert env.tokenizer.decode(td["mission_tokens"]) == td["mission"]
    assert (td["mission_tokens"] != UNK_ID).all()


def test_vocab_covers_missions():
    tok = WordTokenizer(MINIGRID_VOCAB, max_len=64)
    import gymnasium

    for env_id in (
        "MiniGrid-Fetch-5x5-N2-v0",
        "MiniGrid-PutNear-6x6-N2-v0",
        "MiniGrid-LockedRoom-v0",
        "MiniGrid-GoToDoor-5x5-v0",
        "MiniGrid-LavaGapS5-v0",
        "MiniGrid-MemoryS7-v0",
        "MiniGrid-RedBlueDoors-6x6-v0",
        "BabyAI-GoToLocal-v0",
        "BabyAI-PutNextLocal-v0",
    ):
        env = gymnasium.make(env_id)
        for seed in range(3):
            mission = env.reset(seed=seed)[0]["mission"]
            assert tok.unknown_words(mission) == [], (env_id, mission)
        env.close()


# ------------------------------------------------------------------------------------------------------------------
# dynamics: reward history, seeding
# ------------------------------------------------------------------------------------------------------------------
def test_reward_history():
    env = make_minigrid_env(EMPTY, seed=0, reward_history=4)
    td = env.rollout(8, ScriptedPolicy(EMPTY_SOLUTION), break_when_any_done=False)
    reward = td["next", "reward"].squeeze(-1)
    done = td["next", "done"].squeeze(-1)
    assert done.tolist() == [False] * 4 + [True] + [False] * 3
    assert reward[4] == pytest.approx(1 - 0.9 * 5 / 100)
    assert td["next", "terminated"][4].item() and reward[4] > 0  # success = terminated with reward > 0
    hist, next_hist = td["reward_history"], td["next", "reward_history"]
    assert torch.equal(hist[0], torch.zeros(4))
    for t in range(8):
        assert next_hist[t, -1] == reward[t], "the reward of step t is the last entry of next reward_history"
        assert torch.equal(next_hist[t, :-1], hist[t, 1:]), "history shifts left by one per step"
    assert torch.equal(next_hist[4], torch.tensor([0.0, 0.0, 0.0, reward[4].item()]))
    # after the (automatic) reset the history starts from zeros again
    assert torch.equal(hist[5], torch.zeros(4))
    assert torch.equal(next_hist[5], torch.zeros(4))


def _grids(env, actions, seed=None):
    if seed is not None:
        env.set_seed(seed)
    return env.rollout(len(actions), ScriptedPolicy(actions), break_when_any_done=False)["next", "grid"]


def test_seeding_reproducible():
    actions = torch.randint(0, 7, (60,), generator=torch.Generator().manual_seed(1)).tolist()
    env_id = "MiniGrid-MultiRoom-N2-S4-v0"
    a = _grids(make_minigrid_env(env_id, seed=3), actions)
    b = _grids(make_minigrid_env(env_id, seed=3), actions)
    assert torch.equal(a, b)
    # reseeding an existing env replays the same episodes
    env = make_minigrid_env(env_id)
    first = _grids(env, actions, seed=3)
    _grids(env, actions)  # advance its random stream
    again = _grids(env, actions, seed=3)
    assert torch.equal(first, a) and torch.equal(again, a)
    # another seed gives other layouts
    assert not torch.equal(_grids(make_minigrid_env(env_id, seed=4), actions), a)


# ------------------------------------------------------------------------------------------------------------------
# batched envs and transforms
# ------------------------------------------------------------------------------------------------------------------
def test_factory_pickles():
    fn = pickle.loads(pickle.dumps(functools.partial(make_minigrid_env, EMPTY, pixels=True)))
    assert fn().reset()["pixels"].shape == (56, 56, 3)


def test_serial_env_with_init_tracker():
    fn = functools.partial(make_minigrid_env, "MiniGrid-DoorKey-5x5-v0", reward_history=4)
    env = TransformedEnv(SerialEnv(2, fn), InitTracker())
    env.set_seed(0)
    check_env_specs(env)
    td = env.rollout(6, break_when_any_done=False)
    assert td.batch_size == (2, 6)
    assert td["grid"].shape == (2, 6, 7, 7, 3)
    assert td["direction"].shape == (2, 6)
    assert td["mission_tokens"].shape == (2, 6, 16)
    assert td["reward_history"].shape == (2, 6, 4)
    assert td["next", "reward"].shape == (2, 6, 1)
    assert td["is_init"].shape == (2, 6, 1) and td["is_init"][:, 0].all()
    assert td[1, 3]["mission"] == "use the key to open the door and then get to the goal"
    env.close()


@pytest.mark.parametrize(
    "start_method",
    # spawn is what training uses (and what needs picklable factories); its workers import torch, which takes
    # 10-20 s on a loaded 2-core machine, hence "slow". fork checks the same data path in under a second.
    ["fork", pytest.param("spawn", marks=pytest.mark.slow)],
)
def test_parallel_env(start_method):
    fn = functools.partial(make_minigrid_env, EMPTY, reward_history=4)
    env = ParallelEnv(2, EnvCreator(fn), mp_start_method=start_method)
    try:
        env.set_seed(0)
        td = env.rollout(5, ScriptedPolicy(EMPTY_SOLUTION), break_when_any_done=False)
        assert td.batch_size == (2, 5)
        assert td["grid"].shape == (2, 5, 7, 7, 3)
        assert td[0, 0]["mission"] == "get to the green goal square"
        assert td["next", "terminated"][:, 4].all()
        assert torch.allclose(td["next", "reward_history"][:, 4, -1], torch.full((2,), 0.955))
        assert td[1, 4]["next", "mission"] == "get to the green goal square"
    finally:
        env.close()


# ------------------------------------------------------------------------------------------------------------------
# errors
# ------------------------------------------------------------------------------------------------------------------
def test_unknown_env_id():
    with pytest.raises(ValueError) as err:
        make_minigrid_env("MiniGrid-MultiRoom-N2-S4-v9")
    msg = str(err.value)
    assert "\n" not in msg
    assert "'MiniGrid-MultiRoom-N2-S4-v9'" in msg and "gymnasium.envs.registry" in msg
    assert "MiniGrid-MultiRoom-N2-S4-v0" in msg  # close match suggested


def test_non_minigrid_id():
    with pytest.raises(ValueError, match="not a MiniGrid env"):
        MiniGridEnv("CartPole-v1")


# ------------------------------------------------------------------------------------------------------------------
# tokenizer
# ------------------------------------------------------------------------------------------------------------------
def test_tokenizer_round_trip_and_padding():
    tok = WordTokenizer(["go", "to", "the", "red", "ball"], max_len=8)
    assert tok.vocab_size == len(tok) == 7
    ids = tok.encode("Go to the RED ball!")
    assert ids.dtype == torch.int64 and ids.shape == (8,)
    assert ids.tolist() == [2, 3, 4, 5, 6, PAD_ID, PAD_ID, PAD_ID]
    assert tok.decode(ids) == "go to the red ball"
    assert tok.decode([2, 3]) == "go to"
    assert tok.encode("").tolist() == [PAD_ID] * 8


def test_tokenizer_unknown_and_truncation():
    tok = WordTokenizer(["go", "to", "the"], max_len=3)
    assert tok.encode("go to the purple box").tolist() == [2, 3, 4]  # truncated
    assert tok.encode("go, fetch").tolist() == [2, UNK_ID, PAD_ID]
    assert tok.decode(tok.encode("go fetch")) == "go <unk>"
    assert tok.unknown_words("go fetch the box") == ["fetch", "box"]


def test_tokenizer_errors():
    with pytest.raises(ValueError, match="duplicate"):
        WordTokenizer(["a", "b", "a"], max_len=4)
    with pytest.raises(ValueError, match="vocab"):
        WordTokenizer(["pick up"], max_len=4)
    with pytest.raises(ValueError, match="max_len"):
        WordTokenizer(["a"], max_len=0)
    tok = WordTokenizer(["a"], max_len=2)
    with pytest.raises(ValueError, match="outside the vocabulary"):
        tok.decode([5])
    with pytest.raises(ValueError, match="1-D"):
        tok.decode(torch.zeros(2, 2, dtype=torch.int64))


def test_minigrid_vocab_is_valid():
    tok = WordTokenizer(MINIGRID_VOCAB, max_len=16)
    assert tok.vocab_size == len(MINIGRID_VOCAB) + 2
    assert tok.unknown_words("use the key to open the door and then get to the goal") == []
