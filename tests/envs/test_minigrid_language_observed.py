"""R_lang's distance term without privileged information (envs/minigrid_language.py, ``distance`` option): the seen
map is placed exactly where MiniGrid's own view is, closed-form distances on a hand-built grid (unseen cells
passable, revealed walls neither pay nor cost), a target never seen pays no b_prox, the oracle keeps the values of
the code before the option existed, ``none`` runs no BFS."""

from __future__ import annotations

import logging

import gymnasium
import minigrid  # noqa: F401  (registers the MiniGrid ids)
import numpy as np
import pytest
import torch
from minigrid.core.constants import OBJECT_TO_IDX
from minigrid.core.grid import Grid
from minigrid.core.mission import MissionSpace
from minigrid.core.world_object import Goal, Wall
from minigrid.minigrid_env import MiniGridEnv as GymMiniGridEnv

import freamer_rl_envs.minigrid_language as lang_mod
from freamer_rl.machinery.mission.types import ParsedMission, Target
from freamer_rl_envs.minigrid import MiniGridEnv
from freamer_rl_envs.minigrid_language import LanguageRewardTracker, ObservedMap, _bfs, check_language_option

LEFT, RIGHT, FORWARD, PICKUP, TOGGLE = 0, 1, 2, 3, 5
R, G, P = 0.01, 1.0, 0.1
MULTIROOM = "MiniGrid-MultiRoom-N2-S4-v0"
# MultiRoom-N2-S4, seed 1: agent (11, 12) facing left; closed door (12, 11); goal (11, 9) behind it, unseen until the
# door opens on step 4 (same script as tests/envs/test_minigrid_language.py)
MULTIROOM_SCRIPT = [RIGHT, RIGHT, FORWARD, LEFT, TOGGLE, FORWARD, FORWARD, LEFT, FORWARD, RIGHT, FORWARD]
GOAL_ONLY = ParsedMission(Target("goal"), (), ("traverse", "get"))
KEY_DOOR_GOAL = ParsedMission(Target("goal"), (Target("key"), Target("door")), ("use", "open", "get"))
DOOR_GOAL = ParsedMission(Target("goal"), (Target("door"),), ("open", "get"))
RANDOM_ACTIONS = [LEFT, RIGHT, FORWARD, FORWARD, FORWARD, PICKUP, TOGGLE]  # forward-heavy: the agent gets around


def _tracker(parsed: ParsedMission, **kw) -> LanguageRewardTracker:
    return LanguageRewardTracker(parsed, **{"r_scale": R, "goal_bonus": G, "proximity_bonus": P, **kw})


def _random_steps(env_id: str, steps: int, seed: int):
    """``(env, obs)`` after every step of a seeded random walk, resetting (seed + episode) at episode ends; yields
    ``(obs, reset)`` with ``reset`` True right after a reset."""
    env = gymnasium.make(env_id)
    rng = np.random.default_rng(seed)
    episode = seed
    obs, _ = env.reset(seed=episode)
    yield env, obs, True
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(int(rng.choice(RANDOM_ACTIONS)))
        if terminated or truncated:
            episode += 1
            obs, _ = env.reset(seed=episode)
            yield env, obs, True
        else:
            yield env, obs, False


# ------------------------------------------------------------------------------------------------------------------
# the seen map
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", [MULTIROOM, "MiniGrid-DoorKey-8x8-v0", "MiniGrid-LavaCrossingS9N1-v0"])
def test_observed_map_places_each_view_where_minigrid_does(env_id):
    """One update from one view marks exactly the cells MiniGrid's visibility mask shows (its own world -> view map
    ``relative_coords`` and ``gen_obs_grid``'s mask; the agent's cell left out), with the world's encoding there.
    Random walks cover all four directions and views hanging over the map's edge."""
    directions = set()
    for env, obs, _ in _random_steps(env_id, 60, seed=0):
        u = env.unwrapped
        seen = ObservedMap(u.width, u.height, u.agent_view_size)
        seen.update(u, obs["image"])
        _, vis_mask = u.gen_obs_grid()
        agent_cell = (u.agent_view_size // 2, u.agent_view_size - 1)
        directions.add(int(u.agent_dir))
        for y in range(u.height):
            for x in range(u.width):
                view = u.relative_coords(x, y)
                visible = view is not None and bool(vis_mask[view]) and view != agent_cell
                assert (seen.types[y, x] != 0) == visible, (x, y)
                if visible:
                    obj = u.grid.get(x, y)
                    code = (OBJECT_TO_IDX["empty"], 0) if obj is None else obj.encode()[:2]
                    assert (seen.types[y, x], seen.colors[y, x]) == code, (x, y)
                    assert tuple(obs["image"][view][:2]) == code
    assert directions == {0, 1, 2, 3}


class _HandBuilt(GymMiniGridEnv):
    """9x7 room (outer walls), inner walls at (4, 4), (5, 2..4) and (4, 5), the goal at (6, 5); the agent starts at
    (4, 3) facing east (direction 0)."""

    def __init__(self) -> None:
        super().__init__(mission_space=MissionSpace(mission_func=lambda: "get to the goal"), width=9, height=7)

    def _gen_grid(self, width: int, height: int) -> None:
        self.grid = Grid(width, height)
        self.grid.wall_rect(0, 0, width, height)
        for cell in ((4, 4), (5, 2), (5, 3), (5, 4), (4, 5)):
            self.grid.set(*cell, Wall())
        self.grid.set(6, 5, Goal())
        self.agent_pos, self.agent_dir = (4, 3), 0
        self.mission = "get to the goal"


def _picture(seen: ObservedMap) -> list[str]:
    chars = {0: "?", OBJECT_TO_IDX["empty"]: ".", OBJECT_TO_IDX["wall"]: "#", OBJECT_TO_IDX["goal"]: "G"}
    return ["".join(chars[int(t)] for t in row) for row in seen.types]


def test_hand_built_grid_distances_in_closed_form():
    """The agent sees ahead (east) and, through the gap at (5, 1), the goal; it has not seen behind itself nor,
    hidden by the wall at (4, 4), the cells (4, 5) and (5, 5). Unseen cells are passable, so the observed distance
    is 6, west and round the bottom through them: (3,3) (3,4) (3,5) (4,5) (5,5) (6,5); the seen detour over the
    top is 8: (4,2) (4,1) (5,1) (6,1) (6,2) (6,3) (6,4) (6,5), and (4, 5) is in truth a wall: the oracle says 8.
    Turning twice (west) reveals the cells behind; one step west gains a cell on the assumed path (+P); turning
    south there reveals the wall at (4, 5): the distance jumps 5 -> 9 (back over the top), and that step pays 0."""
    env = _HandBuilt()
    obs, _ = env.reset(seed=0)
    tracker = _tracker(GOAL_ONLY, r_scale=0.0)
    oracle = _tracker(GOAL_ONLY, r_scale=0.0, distance="oracle")
    assert tracker.reset(env, obs["image"]) == 0.0 and oracle.reset(env, obs["image"]) == 0.0
    assert _picture(tracker.observed_map) == [
        "????#####",
        "????....#",
        "????.#..#",
        "?????#..#",  # the agent's own cell (4, 3) is not seen: its view shows what it carries
        "????##..#",
        "??????G.#",
        "??????###",
    ]
    assert tracker.distance(env) == 6 and oracle.distance(env) == 8
    values, distances, oracle_distances = [], [], []
    for action in (LEFT, LEFT, FORWARD, LEFT):
        obs, *_ = env.step(action)
        values.append(tracker.step(env, obs["image"]))
        oracle.step(env, obs["image"])
        distances.append(tracker.distance(env))
        oracle_distances.append(oracle.distance(env))
    assert tuple(env.agent_pos) == (3, 3) and env.agent_dir == 1
    assert distances == [6, 6, 5, 9] and oracle_distances == [8, 8, 9, 9]
    assert values == pytest.approx([0.0, 0.0, P, 0.0])
    assert _picture(tracker.observed_map) == [
        "#########",
        "#.......#",
        "#....#..#",
        "#....#..#",  # (4, 3), the start (unseen while the agent stood on it), is now on its left
        "#...##..#",
        "#...#?G.#",
        "#####?###",
    ]


def test_a_target_never_seen_pays_no_b_prox():
    """MultiRoom seed 1: the goal is behind a closed door. Observed: no distance and no b_prox until the door opens
    (step 4), where the goal appears without paying; then the seen path through the door is the true one. The
    oracle pays P for step 2, a move towards the goal the agent cannot see."""
    env = gymnasium.make(MULTIROOM)
    obs, _ = env.reset(seed=1)
    u = env.unwrapped
    observed, oracle = _tracker(GOAL_ONLY), _tracker(GOAL_ONLY, distance="oracle")
    observed.reset(u, obs["image"])
    oracle.reset(u, obs["image"])
    assert observed.distance(u) is None and oracle.distance(u) == 5
    rows = []
    for action in MULTIROOM_SCRIPT:
        obs, *_ = env.step(action)
        rows.append((observed.step(u, obs["image"]), oracle.step(u, obs["image"]), observed.distance(u)))
    values, oracle_values, distances = map(list, zip(*rows))
    assert distances == [None, None, None, None, 4, 3, 2, 2, 1, 1, None]
    assert values == pytest.approx([0, 0, 0, 0, R, R + P, R + P, R, R + P, R, G])
    assert oracle_values == pytest.approx([0, 0, P, 0, R, R + P, R + P, R, R + P, R, G])


def test_revealing_cells_neither_pays_nor_costs():
    """On seeded random walks, a step that leaves the agent on its cell (turn, pick up, toggle) pays no b_prox, even
    when it changed the distance from that cell (the target first seen; a wall or a way revealed); the lazily kept
    field equals a fresh BFS on the seen map after every step, while far fewer fields are computed than steps."""
    first_seen = changed = 0  # stays with the distance None -> d, d -> d' (the walks below have both)
    for env_id, parsed in [
        (MULTIROOM, DOOR_GOAL),
        ("MiniGrid-DoorKey-8x8-v0", KEY_DOOR_GOAL),
        ("MiniGrid-FourRooms-v0", GOAL_ONLY),
    ]:
        tracker = _tracker(parsed, r_scale=0.0, goal_bonus=0.0)
        steps = 0
        prev_pos = None
        for env, obs, reset in _random_steps(env_id, 500, seed=1):
            u = env.unwrapped
            pos = (int(u.agent_pos[0]), int(u.agent_pos[1]))
            if reset:
                tracker.reset(u, obs["image"])
            else:
                index = tracker.achieved
                before = tracker._lookup(pos)  # the field known before the step, at the cell the agent stays on
                value = tracker.step(u, obs["image"])
                if pos == prev_pos and tracker.achieved == index:
                    assert value == 0.0, env_id
                    after = tracker.distance(u)
                    first_seen += before is None and after is not None
                    changed += before is not None and after is not None and after != before
                steps += 1
            prev_pos = pos
            seen = tracker.observed_map
            if tracker.current_target is not None:
                code = tracker._codes[tracker.achieved]
                fresh = _bfs(seen.width, (~seen.blocked()).tolist(), np.flatnonzero(seen.matches(*code)).tolist())
                here = -1 if fresh is None else fresh[pos[1] * seen.width + pos[0]]
                assert tracker.distance(u) == (None if here < 0 else here), env_id
        assert tracker.field_updates < steps / 3, env_id
    assert first_seen > 0 and changed > 0  # the property was exercised


# ------------------------------------------------------------------------------------------------------------------
# oracle and none
# ------------------------------------------------------------------------------------------------------------------
def _fingerprint(env_id: str, parsed: ParsedMission, distance: str) -> tuple[float, float, int, int]:
    """(sum, sum of squares, non-zero count, length) of R_lang along a 600-step seeded random walk."""
    tracker = _tracker(parsed, distance=distance)
    env = gymnasium.make(env_id)
    u = env.unwrapped
    rng = np.random.default_rng(0)
    episode = 0
    obs, _ = env.reset(seed=episode)
    values = [tracker.reset(u, obs["image"])]
    for _ in range(600):
        obs, _, terminated, truncated, _ = env.step(int(rng.choice([0, 1, 2, 2, 2, 3, 5])))
        values.append(tracker.step(u, obs["image"]))
        if terminated or truncated:
            episode += 1
            obs, _ = env.reset(seed=episode)
            values.append(tracker.reset(u, obs["image"]))
    v = np.array(values)
    return round(float(v.sum()), 10), round(float((v * v).sum()), 10), int((v != 0).sum()), len(v)


@pytest.mark.parametrize(
    "env_id, parsed, expected",
    [
        (MULTIROOM, DOOR_GOAL, (10.76, 6.7726, 346, 616)),
        ("MiniGrid-DoorKey-8x8-v0", KEY_DOOR_GOAL, (5.84, 4.0614, 234, 602)),
    ],
)
def test_oracle_keeps_the_full_map_values(env_id, parsed, expected):
    """The oracle's R_lang on two random walks equals that of the code before the option existed (commit 43b086a,
    where the full-map BFS was the only distance); the observed distance gives other values on the same walks."""
    assert _fingerprint(env_id, parsed, "oracle") == expected
    assert _fingerprint(env_id, parsed, "observed") != expected


def test_none_pays_no_b_prox_and_runs_no_bfs():
    """DoorKey-5x5 seed 1, the script of tests/envs/test_minigrid_language.py: the same s_match and b_goal, no P."""
    env = gymnasium.make("MiniGrid-DoorKey-5x5-v0")
    obs, _ = env.reset(seed=1)
    u = env.unwrapped
    tracker = _tracker(KEY_DOOR_GOAL, distance="none")
    values = [tracker.reset(u, obs["image"])]
    for action in (PICKUP, LEFT, TOGGLE, FORWARD, FORWARD, RIGHT, FORWARD):
        obs, *_ = env.step(action)
        values.append(tracker.step(u, obs["image"]))
        assert tracker.distance(u) is None
    assert values == pytest.approx([0.0, G + R, R, G + R, R, R, R, G])  # the oracle / observed add P on steps 4, 5
    assert tracker.field_updates == 0 and tracker.observed_map is None


# ------------------------------------------------------------------------------------------------------------------
# env option
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("distance", ["observed", "oracle", "none"])
def test_env_option_passes_the_distance_through(monkeypatch, distance):
    """MiniGridEnv(language_reward={"distance": ...}) writes the tracker's values of that distance."""
    monkeypatch.setattr(
        lang_mod, "_make_parser", lambda kind, llm_path: type("P", (), {"parse": lambda s, m: GOAL_ONLY})()
    )
    option = {"r_scale": R, "goal_bonus": G, "proximity_bonus": P, "distance": distance}
    env = MiniGridEnv(MULTIROOM, seed=1, language_reward=option)
    td = env.reset()
    gym_env = gymnasium.make(MULTIROOM)
    obs, _ = gym_env.reset(seed=1)
    tracker = _tracker(GOAL_ONLY, distance=distance)
    tracker.reset(gym_env.unwrapped, obs["image"])
    for action in MULTIROOM_SCRIPT:
        td.set("action", torch.tensor(action))
        td = env.step(td)
        obs, *_ = gym_env.step(action)
        expected = tracker.step(gym_env.unwrapped, obs["image"])
        assert td["next", "lang_reward"].item() == pytest.approx(expected)
        td = td["next"]


def test_oracle_logs_one_privileged_warning(monkeypatch, caplog):
    monkeypatch.setattr(lang_mod, "_ORACLE_WARNED", False)
    with caplog.at_level(logging.WARNING, logger=lang_mod.__name__):
        check_language_option({})
        check_language_option({"distance": "none"})
        assert not caplog.records
        check_language_option({"distance": "oracle"})
        check_language_option({"distance": "oracle"})
    assert len(caplog.records) == 1
    assert "distance=oracle" in caplog.text and "privileged" in caplog.text
