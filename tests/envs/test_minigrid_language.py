"""R_lang of MiniGrid (envs/minigrid_language.py): closed-form checks on scripted DoorKey / MultiRoom trajectories,
a hand-built grid, and the ``language_reward`` option of MiniGridEnv / MiniGridVecEnv."""

from __future__ import annotations

import functools
import pickle
from types import SimpleNamespace

import gymnasium
import minigrid  # noqa: F401  (registers the MiniGrid ids)
import numpy as np
import pytest
import torch
from minigrid.core.constants import COLOR_NAMES, COLOR_TO_IDX, OBJECT_TO_IDX
from minigrid.core.grid import Grid
from minigrid.core.world_object import Goal, Lava, Wall
from torchrl.envs import SerialEnv
from torchrl.envs.utils import check_env_specs

import freamer_rl_envs.minigrid_language as lang_mod
from freamer_rl.machinery.mission import make_mission_parser
from freamer_rl.machinery.mission.types import ParsedMission, Target
from freamer_rl.trainers.minigrid_ppo import FreamerConfig
from freamer_rl_envs.minigrid import MiniGridEnv, make_minigrid_env
from freamer_rl_envs.minigrid_language import (
    MINIGRID_MISSION_VOCAB,
    LanguageRewardTracker,
    check_language_option,
    distance_field,
    language_reward_option,
)
from freamer_rl_envs.minigrid_vec import MiniGridVecEnv

DOORKEY, MULTIROOM = "MiniGrid-DoorKey-5x5-v0", "MiniGrid-MultiRoom-N2-S4-v0"
LEFT, RIGHT, FORWARD, PICKUP, TOGGLE = 0, 1, 2, 3, 5
R, G, P = 0.01, 1.0, 0.1  # r_scale, goal_bonus, proximity_bonus: distinct scales keep the terms apart
OPTION = {"parser": "regex", "r_scale": R, "goal_bonus": G, "proximity_bonus": P}

# DoorKey-5x5, seed 1: agent (1, 2) facing down onto the key (1, 3); locked yellow door (2, 2) to its east; goal (3, 3).
DOORKEY_SCRIPT = [PICKUP, LEFT, TOGGLE, FORWARD, FORWARD, RIGHT, FORWARD]
# MultiRoom-N2-S4, seed 1: agent (11, 12) facing left; closed door (12, 11); goal (11, 9), 5 cells away.
MULTIROOM_SCRIPT = [RIGHT, RIGHT, FORWARD, LEFT, TOGGLE, FORWARD, FORWARD, LEFT, FORWARD, RIGHT, FORWARD]
MULTIROOM_DISTANCES = [5, 5, 4, 4, 4, 3, 2, 2, 1, 1, None]  # to the goal after each step (None: reached)

KEY_DOOR_GOAL = ParsedMission(Target("goal"), (Target("key"), Target("door")), ("use", "open", "get"))
GOAL_ONLY = ParsedMission(Target("goal"), (), ("traverse", "get"))


def _gym(env_id: str, seed: int):
    env = gymnasium.make(env_id)
    obs, _ = env.reset(seed=seed)
    return env, env.unwrapped, obs


def _run(tracker: LanguageRewardTracker, env, obs, actions: list[int]) -> list[float]:
    out = [tracker.reset(env.unwrapped, obs["image"])]
    for a in actions:
        obs, *_ = env.step(a)
        out.append(tracker.step(env.unwrapped, obs["image"]))
    return out


def _tracker(parsed: ParsedMission, **kw) -> LanguageRewardTracker:
    return LanguageRewardTracker(parsed, **{"r_scale": R, "goal_bonus": G, "proximity_bonus": P, **kw})


# ------------------------------------------------------------------------------------------------------------------
# tracker
# ------------------------------------------------------------------------------------------------------------------
def test_vocabulary_stays_within_minigrid():
    vocab = MINIGRID_MISSION_VOCAB
    assert {"goal", "key", "door", "ball", "box"} <= set(vocab.objects) <= set(OBJECT_TO_IDX)
    assert set(vocab.colors) == set(COLOR_NAMES)
    assert {"go", "get", "pick", "open", "unlock", "put", "traverse"} <= set(vocab.actions)


def test_distance_field_on_a_hand_built_grid():
    """7x5 room, a wall column at x=3 with a gap at y=3, lava at (2, 2): shortest paths detour through the gap."""
    grid = Grid(7, 5)
    grid.wall_rect(0, 0, 7, 5)
    grid.set(3, 1, Wall())
    grid.set(3, 2, Wall())
    grid.set(2, 2, Lava())
    grid.set(5, 1, Goal())
    dist = distance_field(grid, lambda o: o is not None and o.type == "goal")

    def at(x, y):
        return dist[y * grid.width + x]

    assert at(5, 1) == 0 and at(4, 1) == 1 and at(3, 3) == 4  # (5,1)->(4,1)->(4,2)->(4,3)->(3,3)
    assert at(2, 3) == 5 and at(1, 3) == 6 and at(1, 2) == 7 and at(1, 1) == 8 and at(2, 1) == 9  # around the lava
    assert at(2, 2) == -1 and at(3, 1) == -1 and at(0, 0) == -1  # lava and walls are never entered
    assert distance_field(grid, lambda o: o is not None and o.type == "key") is None


@pytest.mark.parametrize("distance", ["observed", "oracle"])
def test_doorkey_script_pays_every_term_in_closed_form(distance):
    """key picked up -> door opened -> goal reached: b_goal once each, s_match while the target is in view,
    b_prox = P per cell gained towards the goal (3 -> 2 -> 1), 0 on the steps the target changes. Both distances
    agree here: the goal becomes current when the door opens, and is seen through it on that step, with the walls
    next to the door, so the seen map's shortest path is the true one."""
    env, u, obs = _gym(DOORKEY, 1)
    tracker = _tracker(KEY_DOOR_GOAL, distance=distance)
    values = [tracker.reset(u, obs["image"])]
    targets = [tracker.current_target]
    for a in DOORKEY_SCRIPT:
        obs, reward, terminated, *_ = env.step(a)
        values.append(tracker.step(u, obs["image"]))
        targets.append(tracker.current_target)
    assert terminated and reward > 0
    expected = [0.0, G + R, R, G + R, R + P, R + P, R, G]  # the door stays in view; then the goal (through it)
    assert values == pytest.approx(expected)
    assert targets == [Target("key"), *[Target("door")] * 2, *[Target("goal")] * 4, None]
    assert tracker.achieved == 3


def test_targets_advance_in_mission_order():
    """Parsed as 'door, then key': picking the key up first pays nothing; opening the door then pays, and the key,
    already carried, is achieved on the next step."""
    env, u, obs = _gym(DOORKEY, 1)
    tracker = _tracker(ParsedMission(Target("goal"), (Target("door"), Target("key"))), r_scale=0.0, proximity_bonus=0.0)
    values = _run(tracker, env, obs, DOORKEY_SCRIPT[:3])
    assert values == pytest.approx([0.0, 0.0, 0.0, 2 * G])  # door, then the carried key on the same step
    assert tracker.current_target == Target("goal")


def test_colour_must_match():
    env, u, obs = _gym(DOORKEY, 1)  # the key is yellow
    red = _tracker(ParsedMission(Target("goal"), (Target("key", "red"),)), proximity_bonus=0.0)
    assert _run(red, env, obs, [PICKUP]) == [0.0, 0.0]
    env, u, obs = _gym(DOORKEY, 1)
    yellow = _tracker(ParsedMission(Target("goal"), (Target("key", "yellow"),)), proximity_bonus=0.0)
    values = _run(yellow, env, obs, [PICKUP])
    assert values == pytest.approx([0.0, G])  # the goal, now current, hides behind the locked door
    assert yellow.current_target == Target("goal")


def test_s_match_follows_the_target_into_view_and_b_prox_the_distance():
    """MultiRoom, oracle distance (the full map): the goal enters the view when the door opens; each step's R_lang
    is R * [goal in view] + P * (distance decrease) until the goal pays G. (The observed distance of the same
    script: tests/envs/test_minigrid_language_observed.py.)"""
    env, u, obs = _gym(MULTIROOM, 1)
    tracker = _tracker(GOAL_ONLY, distance="oracle")
    assert tracker.reset(u, obs["image"]) == 0.0 and tracker.distance(u) == 5
    d_prev = 5
    for t, (a, d) in enumerate(zip(MULTIROOM_SCRIPT, MULTIROOM_DISTANCES)):
        obs, reward, terminated, *_ = env.step(a)
        value = tracker.step(u, obs["image"])
        assert tracker.distance(u) == d, t
        if d is None:  # on the goal: the bonus, nothing else
            assert terminated and reward > 0 and value == pytest.approx(G)
            continue
        in_view = bool((obs["image"][:, :, 0] == OBJECT_TO_IDX["goal"]).any())
        assert in_view == (t >= 4), t  # hidden behind the closed door until it opens on step 4
        assert value == pytest.approx(R * in_view + P * (d_prev - d)), t
        d_prev = d


def test_reset_starts_the_targets_again():
    env, u, obs = _gym(DOORKEY, 1)
    tracker = _tracker(KEY_DOOR_GOAL)
    _run(tracker, env, obs, DOORKEY_SCRIPT)
    assert tracker.current_target is None
    obs, _ = env.reset(seed=1)
    assert tracker.reset(u, obs["image"]) == 0.0
    assert tracker.current_target == Target("key") and tracker.achieved == 0 and tracker.distance(u) == 1
    obs, *_ = env.step(PICKUP)
    assert tracker.step(u, obs["image"]) == pytest.approx(G + R)  # the key pays again in the new episode


def test_go_to_a_pickable_final_target_is_reached_by_facing_it():
    """'go to the key' (no take verb): facing the key achieves it; 'pick up the key': only carrying it does."""
    env, u, obs = _gym(DOORKEY, 1)  # the agent starts facing the key
    go_to = _tracker(ParsedMission(Target("key"), (), ("go",)), r_scale=0.0, proximity_bonus=0.0)
    assert _run(go_to, env, obs, [LEFT, RIGHT]) == [0.0, 0.0, G]  # turned away, then facing it again
    env, u, obs = _gym(DOORKEY, 1)
    pick = _tracker(ParsedMission(Target("key"), (), ("pick",)), r_scale=0.0, proximity_bonus=0.0)
    assert _run(pick, env, obs, [LEFT, RIGHT, PICKUP]) == [0.0, 0.0, 0.0, G]


def test_go_to_a_door_is_reached_by_facing_it_and_open_the_door_by_opening_it():
    env, u, obs = _gym(DOORKEY, 1)  # the locked door is to the agent's left (east)
    go_to = _tracker(ParsedMission(Target("door"), (), ("go",)), r_scale=0.0, proximity_bonus=0.0)
    assert _run(go_to, env, obs, [LEFT]) == [0.0, G]
    env, u, obs = _gym(DOORKEY, 1)
    unlock = _tracker(ParsedMission(Target("door"), (), ("unlock",)), r_scale=0.0, proximity_bonus=0.0)
    assert _run(unlock, env, obs, [PICKUP, LEFT, TOGGLE]) == [0.0, 0.0, 0.0, G]


def test_s_match_agrees_with_a_mask_of_the_view():
    """The byte search of s_match == a plain numpy mask over random views, for every object type and colour."""
    gen = np.random.default_rng(0)
    images = np.stack([gen.integers(0, high + 1, (200, 7, 7), dtype=np.uint8) for high in (10, 5, 2)], axis=-1)
    for kind in ("goal", "key", "door", "ball", "box", "lava"):
        for color in (None, *COLOR_NAMES):
            tracker = _tracker(ParsedMission(Target(kind, color)))
            for image in images:
                hit = image[:, :, 0] == OBJECT_TO_IDX[kind]
                if color is not None:
                    hit &= image[:, :, 1] == COLOR_TO_IDX[color]
                hit[3, 6] = False  # the agent's own cell
                assert tracker._visible(image) == bool(hit.any())


def test_unknown_target_is_refused():
    with pytest.raises(ValueError, match="minigrid does not know"):
        _tracker(ParsedMission(Target("goal", "magenta")))


# ------------------------------------------------------------------------------------------------------------------
# env option
# ------------------------------------------------------------------------------------------------------------------
class _FixedParser:
    """Stands in for freamer_rl.machinery.mission's parser: every mission parses to ``parsed``."""

    def __init__(self, parsed: ParsedMission) -> None:
        self.parsed = parsed
        self.calls: list[str] = []

    def parse(self, mission: str) -> ParsedMission:
        self.calls.append(mission)
        return self.parsed


@pytest.fixture
def fixed_parser(monkeypatch):
    parser = _FixedParser(KEY_DOOR_GOAL)
    monkeypatch.setattr(lang_mod, "_make_parser", lambda kind, llm_path: parser)
    return parser


def _script_rewards(env, actions: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    td = env.reset()
    first = td["lang_reward"].clone()
    values = []
    for a in actions:
        td.set("action", torch.full(env.batch_size, a, dtype=torch.int64))
        td = env.step(td)
        values.append(td["next", "lang_reward"].clone())
        td = td["next"]
    return first, torch.stack(values)


def test_env_writes_lang_reward(monkeypatch):
    """The real regex parser ('use the key to open the door and then get to the goal' -> key, door, goal) through
    MiniGridEnv gives the closed-form values of the tracker test; the mission is parsed once per change."""
    calls = []

    def counting_parser(kind, llm_path):
        parser = make_mission_parser(kind, MINIGRID_MISSION_VOCAB, llm_path)
        return SimpleNamespace(parse=lambda mission: calls.append(mission) or parser.parse(mission))

    monkeypatch.setattr(lang_mod, "_make_parser", counting_parser)
    env = MiniGridEnv(DOORKEY, seed=1, language_reward=OPTION)
    spec = env.observation_spec["lang_reward"]
    assert spec.shape == (1,) and spec.dtype == torch.float32
    first, values = _script_rewards(env, DOORKEY_SCRIPT)
    assert first.tolist() == [0.0]
    expected = [G + R, R, G + R, R + P, R + P, R, G]
    assert values.squeeze(-1).tolist() == pytest.approx(expected)
    env.reset()
    env.reset()
    assert calls == ["use the key to open the door and then get to the goal"]  # parsed once
    assert "lang_reward" not in MiniGridEnv(DOORKEY).observation_spec.keys()


@pytest.mark.parametrize("env_id", [DOORKEY, MULTIROOM])
def test_check_env_specs_with_the_option(env_id):  # the real regex parser
    check_env_specs(make_minigrid_env(env_id, seed=0, language_reward=OPTION), seed=0)
    vec = MiniGridVecEnv(env_id, 3, language_reward=OPTION)
    check_env_specs(vec, seed=0)
    assert vec.observation_spec["lang_reward"].shape == (3, 1)
    vec.close()


def test_vec_env_gives_the_serial_env_lang_reward(fixed_parser, scripted_rollout):
    """Same seed, same random actions: MiniGridVecEnv and SerialEnv of single envs agree on every key, through
    episode ends (MultiRoom-N2-S4 parsed as 'door, then goal'; random turn / move / pickup / toggle)."""
    fixed_parser.parsed = ParsedMission(Target("goal"), (Target("door"),))
    n, steps = 3, 150
    make = functools.partial(make_minigrid_env, MULTIROOM, include_mission=False, language_reward=OPTION)
    actions = torch.tensor([LEFT, RIGHT, FORWARD, PICKUP, TOGGLE])[
        torch.randint(0, 5, (steps, n), generator=torch.Generator().manual_seed(0))
    ]
    envs = (SerialEnv(n, make), MiniGridVecEnv(MULTIROOM, n, language_reward=OPTION))
    a, b = (scripted_rollout(env, actions, seed=3) for env in envs)
    assert bool(a["next", "done"].any())
    lang = a["next", "lang_reward"]
    assert bool((lang >= G).any()) and bool(((lang > 0) & (lang < G)).any())  # door bonuses and dense terms
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a[key], b[key]), key


def test_option_is_checked_and_picklable():
    assert check_language_option({}) == {
        "parser": "regex",
        "llm_path": None,
        "r_scale": 0.1,
        "goal_bonus": 1.0,
        "proximity_bonus": 0.1,
        "distance": "observed",
    }
    with pytest.raises(ValueError, match="unknown keys"):
        check_language_option({"scale": 1.0})
    with pytest.raises(ValueError, match="'regex' or 'llm'"):
        check_language_option({"parser": "gpt"})
    with pytest.raises(ValueError, match="llm_path"):
        check_language_option({"parser": "llm"})
    with pytest.raises(ValueError, match=r"language_reward\['distance'\]: expected one of observed, oracle, none"):
        check_language_option({"distance": "magic"})
    factory = functools.partial(make_minigrid_env, DOORKEY, language_reward=dict(OPTION))
    assert pickle.loads(pickle.dumps(factory)).keywords["language_reward"] == OPTION


def test_language_reward_option_from_the_config():
    cfg = FreamerConfig()
    assert language_reward_option(cfg) is None  # weight 0: off
    cfg.shaping.language.weight = 0.2
    cfg.shaping.language.r_scale = 0.5
    assert language_reward_option(cfg) == {**check_language_option({}), "r_scale": 0.5}
    cfg.shaping.language.distance = "none"
    assert language_reward_option(cfg)["distance"] == "none"
