"""R_lang, the language-grounded reward of MiniGrid (paper App. A.2, Eq. A10; App. G.1).

``R_lang = s_match * r_scale + b_goal + b_prox`` for one env step, from the parsed mission (Eq. A8,
:class:`freamer_rl.machinery.mission.types.ParsedMission`), the agent's view and the env's state:

* the mission's **targets** are ``intermediate_goals + (final_goal,)`` in order; the *current* target is the first
  one not yet achieved in this episode;
* ``s_match`` is 1 when an instance of the current target (its type, and its colour when the mission names one) is
  visible in the agent's ``7x7`` view (the agent's own cell, which shows what it carries, does not count), else 0;
* ``b_goal`` pays ``goal_bonus`` once per target, on the step it is achieved, and the next target becomes current.
  Achieved means: key / ball / box carried (a *final* key / ball / box of a mission without a take verb -- "go to
  the red ball" -- is achieved when the agent faces it instead); door: the agent faces (or stands in) an open
  matching door (a *final* door of a mission without an open verb -- "go to the red door" -- is achieved when the
  agent faces it); goal (and floor): the agent stands on it; wall / lava: the agent faces it;
* ``b_prox = proximity_bonus * (D_t(p_{t-1}) - D_t(p_t))``: the shortest-path distance ``D_t`` (4-neighbour BFS;
  walls and lava block, doors and movable objects pass) to the nearest instance of the current target, on the map
  of the step's option ``distance``:

  - ``"observed"`` (default): the map the agent has **seen so far in the episode** (:class:`ObservedMap`: every cell
    its views showed, with what it showed last). Cells never seen count as passable; only seen target cells are
    targets, so a target never seen has no distance (``b_prox`` 0). Only the map's size comes from the env.
  - ``"oracle"``: the env's full map, computed once per (episode, target): **privileged information** the agent
    cannot observe (a warning is logged; ``freamer_rl.machinery.checks.privileged_information`` names it).
  - ``"none"``: no distance term (``b_prox`` 0, no BFS).

  Both distances are taken on the *same* map, the one known after the step, from the agent's previous cell ``p_{t-1}``
  and its current one ``p_t``: revealing cells (a wall on the assumed path, a shorter way, the target itself)
  neither pays nor costs; only the agent's own move does, valued with what it knows now. (Paying 0 whenever the map
  changed instead would drop ``b_prox`` on most forward moves, which nearly always reveal a row of cells.) On the
  oracle map ``D_t`` is constant per target, so this is the plain ``d_prev - d_now``. ``b_prox`` is 0 on the step the
  target changes and while no instance is reachable.

Once every target is achieved R_lang is 0 for the rest of the episode. A target is never achieved at a reset: a
target already achieved then (the agent starts facing a "go to" target) pays on the first step. Objects hidden in a
box (ObstructedMaze) have no cell: no distance, no ``b_prox`` until they are out.

:class:`LanguageRewardTracker` computes it for one parsed mission; :class:`LanguageReward` is the env-side glue that
``MiniGridEnv(language_reward={...})`` uses (parse each new mission once, one tracker per episode).
"""

from __future__ import annotations

import functools
import logging
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from minigrid.core.constants import COLOR_NAMES, COLOR_TO_IDX, OBJECT_TO_IDX

from freamer_rl.machinery.config import LANGUAGE_DISTANCES
from freamer_rl.machinery.mission.types import MissionVocabulary, ParsedMission, Target

logger = logging.getLogger(__name__)

__all__ = [
    "LANGUAGE_REWARD_DEFAULTS",
    "LanguageReward",
    "LanguageRewardTracker",
    "MINIGRID_MISSION_VOCAB",
    "ObservedMap",
    "check_language_option",
    "distance_field",
    "language_reward_option",
]

#: What a parsed MiniGrid mission may name: every object type a mission can target or mention (minigrid's own
#: names, ``minigrid.core.constants.OBJECT_TO_IDX`` minus unseen / empty / agent), its colours, and the verbs of
#: minigrid 3.x's mission strings.
MINIGRID_MISSION_VOCAB = MissionVocabulary(
    objects=("goal", "key", "door", "ball", "box", "lava", "wall", "floor"),
    colors=tuple(COLOR_NAMES),
    actions=(
        "go",
        "get",
        "fetch",
        "pick",
        "open",
        "unlock",
        "put",
        "traverse",
        "find",
        "reach",
        "use",
        "avoid",
        "toggle",
        "drop",
    ),
)

#: Keys of the ``language_reward`` env option and their defaults (those of ``cfg.shaping.language``).
LANGUAGE_REWARD_DEFAULTS: dict[str, Any] = {
    "parser": "regex",
    "llm_path": None,
    "r_scale": 0.1,
    "goal_bonus": 1.0,
    "proximity_bonus": 0.1,
    "distance": "observed",
}

_PICKABLE = frozenset({"key", "ball", "box"})
_OVERLAPPABLE = frozenset({"goal", "floor"})
_TAKE_VERBS = frozenset({"pick", "get", "fetch"})
_OPEN_VERBS = frozenset({"open", "unlock", "toggle", "use", "traverse"})
_BLOCKING = frozenset({"wall", "lava"})
#: ``type index -> blocks a move`` (walls and lava), for the encoded cells of :class:`ObservedMap`
_BLOCKING_TYPES = np.zeros(256, dtype=bool)
_BLOCKING_TYPES[[OBJECT_TO_IDX[kind] for kind in _BLOCKING]] = True
_UNSEEN = OBJECT_TO_IDX["unseen"]  # 0: what MiniGrid's encoding writes for a cell outside the visibility mask


def _matcher(target: Target) -> Callable[[Any], bool]:
    """``obj -> bool``: is the minigrid ``WorldObj`` (or ``None``) an instance of ``target``?"""
    kind, color = target.object, target.color
    if color is None:
        return lambda obj: obj is not None and obj.type == kind
    return lambda obj: obj is not None and obj.type == kind and obj.color == color


def _criterion(target: Target, is_final: bool, actions: tuple[str, ...]) -> str:
    """How ``target`` is achieved: ``"carry"``, ``"open"``, ``"on"`` or ``"face"`` (see the module docstring)."""
    if target.object == "door":
        return "open" if not is_final or _OPEN_VERBS.intersection(actions) else "face"
    if target.object in _OVERLAPPABLE:
        return "on"
    if target.object in _PICKABLE and (not is_final or _TAKE_VERBS.intersection(actions)):
        return "carry"
    return "face"


def _bfs(width: int, passable: list[bool], sources: list[int]) -> list[int] | None:
    """Multi-source 4-neighbour BFS on a ``width``-wide grid of ``len(passable)`` cells indexed ``y * width + x``.

    Returns the distance of every cell to the nearest source (-1: unreachable; sources are 0 whether or not they
    are passable), or ``None`` when there is no source."""
    if not sources:
        return None
    dist = [-1] * len(passable)
    for idx in sources:
        dist[idx] = 0
    queue: deque[int] = deque(sources)
    while queue:
        idx = queue.popleft()
        d = dist[idx] + 1
        x = idx % width
        neighbours = (
            idx - 1 if x > 0 else -1,
            idx + 1 if x < width - 1 else -1,
            idx - width,
            idx + width if idx + width < len(passable) else -1,
        )
        for n in neighbours:
            if n >= 0 and dist[n] < 0 and passable[n]:
                dist[n] = d
                queue.append(n)
    return dist


def distance_field(grid: Any, is_target: Callable[[Any], bool]) -> list[int] | None:
    """Shortest-path distance of every cell of the env's full map to the nearest ``is_target`` cell (multi-source
    BFS; the ``"oracle"`` distance).

    Args:
        grid: a ``minigrid.core.grid.Grid`` of width ``W`` and height ``H``.
        is_target: ``WorldObj | None -> bool``.

    Returns:
        a flat list of ``W * H`` ints indexed ``y * W + x`` (-1: unreachable), or ``None`` when no cell is a target.
        Moves go between 4-neighbours; walls and lava block, everything else (doors, keys, balls, boxes) passes.
    """
    cells = grid.grid
    sources = [idx for idx, obj in enumerate(cells) if is_target(obj)]
    return _bfs(grid.width, [obj is None or obj.type not in _BLOCKING for obj in cells], sources)


def _pos(env: Any) -> tuple[int, int]:
    """The agent's cell ``(x, y)`` as plain ints (MiniGrid keeps a tuple or a numpy array)."""
    x, y = env.agent_pos
    return int(x), int(y)


@functools.cache
def _view_index(size: int, agent_dir: int) -> np.ndarray:
    """``int [V, V]``: at ``[y, x]``, the flat index ``i * V + j`` of the view cell ``(i, j)`` that shows the world cell
    ``(top_x + x, top_y + y)``, ``(top_x, top_y)`` from ``get_view_exts()``.

    ``gen_obs_grid`` slices that ``V x V`` square (indexed ``[x, y]``) and turns it ``agent_dir + 1`` times with
    ``Grid.rotate_left`` (``new[j, V-1-i] = old[i, j]``, i.e. ``np.rot90(old, -1)``): ``np.rot90(view, dir + 1)`` is
    the slice again, transposed to ``[y, x]``. Turning an index grid once here makes each update one gather instead
    of a ``rot90`` (several numpy calls, half the update's time). Cached: do not write to it."""
    flat = np.arange(size * size).reshape(size, size)
    return np.ascontiguousarray(np.rot90(flat, agent_dir + 1).T)


class ObservedMap:
    """What the agent has seen of the map this episode (the ``"observed"`` distance of b_prox).

    :attr:`types`, :attr:`colors`: ``uint8 [H, W]`` indexed ``[y, x]``, MiniGrid's encoding of what each cell showed
    the last time it was in view (``types == 0``: never seen). :meth:`update` reads the observed ``image``
    ``uint8 [V, V, 3]`` (indexed ``[i, j]``, the agent at ``(V // 2, V - 1)``): a view cell is seen when its type is
    not ``unseen`` (0), which is exactly MiniGrid's visibility mask (``Grid.encode(vis_mask)`` writes zeros elsewhere,
    and a visible empty cell encodes as ``empty`` = 1). The agent's own cell is left out (it shows what the agent
    carries). From the env only the map's size and the agent's pose are read (its direction is observed; its cell it
    could integrate from its own moves).

    Placing the view (:func:`_view_index`): the view is the square at ``get_view_exts()``, turned. The map keeps a
    ``V``-cell margin on every side: view cells over the map's edge (MiniGrid shows them as walls) land there, never
    in the map.
    """

    def __init__(self, width: int, height: int, view_size: int) -> None:
        self.width, self.height, self.view_size = int(width), int(height), int(view_size)
        pad = self.view_size
        # (type, colour, state) as the image encodes them; one array, so an update is one compare and one copy
        self._cells = np.zeros((self.height + 2 * pad, self.width + 2 * pad, 3), dtype=np.uint8)
        self.version = 0  # bumped whenever a cell's encoding changes: the tracker refreshes its field then

    @property
    def types(self) -> np.ndarray:
        """``uint8 [H, W]``: the object index each cell showed last (0: never seen)."""
        pad = self.view_size
        return self._cells[pad : pad + self.height, pad : pad + self.width, 0]

    @property
    def colors(self) -> np.ndarray:
        """``uint8 [H, W]``: the colour index each cell showed last."""
        pad = self.view_size
        return self._cells[pad : pad + self.height, pad : pad + self.width, 1]

    def update(self, env: Any, image: np.ndarray) -> None:
        """Write the cells ``image`` shows (``env``: the unwrapped MiniGrid env, read for its pose only).

        Raises:
            ValueError: ``image`` is not ``[V, V, 3]`` for the map's view size ``V``.
        """
        size = self.view_size
        if image.shape != (size, size, 3):
            raise ValueError(f"image: expected shape ({size}, {size}, 3) (the agent's view), got {tuple(image.shape)}")
        top_x, top_y, _, _ = env.get_view_exts(size)
        window = image.reshape(size * size, 3)[_view_index(size, int(env.agent_dir))]  # [y, x, 3] from (top_x, top_y)
        seen = window[:, :, :1] != _UNSEEN
        x, y = _pos(env)
        seen[y - top_y, x - top_x] = False
        cells = self._cells[top_y + size : top_y + 2 * size, top_x + size : top_x + 2 * size]  # a view into the map
        if ((cells != window) & seen).any():
            np.copyto(cells, window, where=seen)
            self.version += 1

    def blocked(self) -> np.ndarray:
        """``bool [H * W]`` (``y * W + x``): seen as a wall or lava (never-seen cells are passable)."""
        return _BLOCKING_TYPES[self.types].ravel()

    def matches(self, type_idx: int, color_idx: int | None) -> np.ndarray:
        """``bool [H * W]``: last seen as an object of ``type_idx`` (and ``color_idx`` unless ``None``)."""
        hit = self.types == type_idx
        return (hit if color_idx is None else hit & (self.colors == color_idx)).ravel()


class LanguageRewardTracker:
    """R_lang of Eq. A10 along the episodes of one parsed mission (see the module docstring for the terms).

    Reads the *unwrapped* gymnasium MiniGrid env (``agent_pos``, ``agent_dir``, ``front_pos``, ``grid``,
    ``carrying``; the full map only for the ``"oracle"`` distance) and the observed ``image`` ``uint8 [V, V, 3]``
    (indexed ``[x, y]``, the agent at ``(V // 2, V - 1)``). Call :meth:`reset` after every env reset and :meth:`step`
    after every env step.

    Args:
        parsed: the mission's parse.
        r_scale: reward per step while the current target is in view.
        goal_bonus: paid once per target achieved.
        proximity_bonus: paid per cell of shortest-path distance gained towards the current target (0 skips the BFS).
        distance: the map of that distance: ``"observed"``, ``"oracle"`` (privileged) or ``"none"`` (no b_prox).

    Raises:
        ValueError: a target whose object type or colour minigrid does not know, or an unknown ``distance``.
    """

    def __init__(
        self,
        parsed: ParsedMission,
        *,
        r_scale: float,
        goal_bonus: float,
        proximity_bonus: float,
        distance: str = "observed",
    ) -> None:
        if distance not in LANGUAGE_DISTANCES:
            raise ValueError(f"distance: expected one of {', '.join(LANGUAGE_DISTANCES)}, got {distance!r}")
        self.parsed = parsed
        self.r_scale = float(r_scale)
        self.goal_bonus = float(goal_bonus)
        self.proximity_bonus = float(proximity_bonus)
        self.distance_mode = distance
        self.targets: tuple[Target, ...] = (*parsed.intermediate_goals, parsed.final_goal)
        for t in self.targets:
            if t.object not in OBJECT_TO_IDX or (t.color is not None and t.color not in COLOR_TO_IDX):
                raise ValueError(f"target {t} names an object type or colour minigrid does not know")
        last = len(self.targets) - 1
        self._matchers = [_matcher(t) for t in self.targets]
        self._criteria = [_criterion(t, i == last, parsed.actions) for i, t in enumerate(self.targets)]
        # (type, colour) indices of a target's cells in MiniGrid's encoding (colour None when the mission leaves it free)
        self._codes = [
            (OBJECT_TO_IDX[t.object], None if t.color is None else COLOR_TO_IDX[t.color]) for t in self.targets
        ]
        # the same as the bytes of a cell in the observed image
        self._patterns = [bytes(code[:1] if code[1] is None else code) for code in self._codes]
        self._uses_distance = self.proximity_bonus != 0.0 and distance != "none"
        self._index = 0
        self.observed_map: ObservedMap | None = None  # this episode's seen cells ("observed" distance only)
        self.field_updates = 0  # distance fields computed so far (a cost counter)
        self._field: list[int] | None = None
        self._field_key: tuple[int, int] | None = None  # (map version, target index) the field was checked at
        self._field_masks: tuple[bytes, bytes] | None = None  # (blocked, target) cells the field was computed from
        self._width = 0
        self._prev_pos: tuple[int, int] = (0, 0)

    # ------------------------------------------------------------------------------------------------------------
    @property
    def current_target(self) -> Target | None:
        """The first target not yet achieved this episode (``None`` once all are)."""
        return self.targets[self._index] if self._index < len(self.targets) else None

    @property
    def achieved(self) -> int:
        """How many targets were achieved this episode."""
        return self._index

    def _lookup(self, pos: tuple[int, int]) -> int | None:
        if self._field is None:
            return None
        d = self._field[pos[1] * self._width + pos[0]]
        return d if d >= 0 else None

    def distance(self, env: Any) -> int | None:
        """Shortest-path distance from the agent to the current target on the tracker's map (``None``: no target,
        no seen instance of it, unreachable, or no distance term)."""
        return self._lookup(_pos(env))

    # ------------------------------------------------------------------------------------------------------------
    def _refresh_field(self) -> None:
        """``"observed"``: recompute the field when the seen walls / lava or the seen target cells changed (most
        steps only reveal passable, non-target cells: then the field stands)."""
        if self.observed_map is None or self._index >= len(self.targets):
            return
        key = (self.observed_map.version, self._index)
        if key == self._field_key:
            return
        self._field_key = key
        blocked = self.observed_map.blocked()
        sources = self.observed_map.matches(*self._codes[self._index])
        masks = (blocked.tobytes(), sources.tobytes())
        if masks == self._field_masks:
            return
        self._field_masks = masks
        self._field = _bfs(self.observed_map.width, (~blocked).tolist(), np.flatnonzero(sources).tolist())
        self._width = self.observed_map.width
        self.field_updates += 1

    def _enter_target(self, env: Any) -> None:
        """Compute the distance field of the (new) current target and start ``p_{t-1}`` at the agent's cell."""
        self._field = None
        self._field_key = self._field_masks = None
        if self._index < len(self.targets) and self._uses_distance:
            if self.distance_mode == "oracle":
                self._field = distance_field(env.grid, self._matchers[self._index])
                self._width = env.grid.width
                self.field_updates += 1
            else:
                self._refresh_field()
        self._prev_pos = _pos(env)

    def _is_achieved(self, env: Any) -> bool:
        criterion, match = self._criteria[self._index], self._matchers[self._index]
        if criterion == "carry":
            return match(env.carrying)
        if criterion == "on":
            return match(env.grid.get(*env.agent_pos))
        front = env.front_pos
        in_grid = 0 <= front[0] < env.grid.width and 0 <= front[1] < env.grid.height
        faced = env.grid.get(*front) if in_grid else None
        if criterion == "face":
            return match(faced)
        here = env.grid.get(*env.agent_pos)  # "open": the agent faces or stands in an open matching door
        return (match(faced) and faced.is_open) or (match(here) and here.is_open)

    def _visible(self, image: np.ndarray) -> bool:
        """Is an instance of the current target in ``image`` ``uint8 [V, V, 3]``, the agent's own cell (which shows
        what it carries) left out? A byte search of ``(type, colour)`` at cell boundaries: ~4x faster than numpy
        masks on a 7x7 view."""
        if self._index >= len(self.targets):
            return False
        raw = np.ascontiguousarray(image, dtype=np.uint8).tobytes()  # cell (x, y) at byte 3 * (x * V + y)
        v_w, v_h = image.shape[0], image.shape[1]
        agent = 3 * ((v_w // 2) * v_h + v_h - 1)
        pattern = self._patterns[self._index]
        pos = raw.find(pattern)
        while pos >= 0:
            if pos % 3 == 0 and pos != agent:
                return True
            pos = raw.find(pattern, pos + 1)
        return False

    # ------------------------------------------------------------------------------------------------------------
    def reset(self, env: Any, image: np.ndarray) -> float:
        """Start a new episode (the first target is current again, nothing seen but ``image``); returns 0.0, R_lang
        of a reset."""
        self._index = 0
        if self._uses_distance and self.distance_mode == "observed":
            self.observed_map = ObservedMap(env.width, env.height, image.shape[0])
            self.observed_map.update(env, image)
        self._enter_target(env)
        return 0.0

    def step(self, env: Any, image: np.ndarray) -> float:
        """R_lang of the env step that led to the current state of ``env`` and its observed ``image``."""
        bonus = 0.0
        changed = False
        while self._index < len(self.targets) and self._is_achieved(env):
            bonus += self.goal_bonus
            self._index += 1
            changed = True
        if self.observed_map is not None and self._index < len(self.targets):
            self.observed_map.update(env, image)
        if changed:
            self._enter_target(env)
            proximity = 0.0
        else:
            self._refresh_field()  # D_t: the map known after this step
            pos = _pos(env)
            d_prev, d_now = self._lookup(self._prev_pos), self._lookup(pos)
            self._prev_pos = pos
            proximity = 0.0 if d_now is None or d_prev is None else self.proximity_bonus * (d_prev - d_now)
        match = self.r_scale if self.r_scale != 0.0 and self._visible(image) else 0.0
        return match + bonus + proximity


# --------------------------------------------------------------------------------------------------------------------
# env option
# --------------------------------------------------------------------------------------------------------------------
def check_language_option(option: Mapping[str, Any]) -> dict[str, Any]:
    """The ``language_reward`` env option with its defaults filled in (a plain, picklable dict).

    ``distance: "oracle"`` logs a warning, once per process: its b_prox reads the full map (privileged information).

    Raises:
        ValueError: unknown keys, a parser other than ``"regex"`` / ``"llm"``, ``"llm"`` without ``llm_path``, or a
            ``distance`` other than ``"observed"`` / ``"oracle"`` / ``"none"``.
    """
    unknown = set(option) - set(LANGUAGE_REWARD_DEFAULTS)
    if unknown:
        raise ValueError(f"language_reward: unknown keys {sorted(unknown)} (known: {sorted(LANGUAGE_REWARD_DEFAULTS)})")
    out = {**LANGUAGE_REWARD_DEFAULTS, **option}
    if out["parser"] not in ("regex", "llm"):
        raise ValueError(f"language_reward['parser']: expected 'regex' or 'llm', got {out['parser']!r}")
    if out["parser"] == "llm" and not out["llm_path"]:
        raise ValueError("language_reward['llm_path']: parser 'llm' needs the local directory of the model")
    if out["distance"] not in LANGUAGE_DISTANCES:
        raise ValueError(
            f"language_reward['distance']: expected one of {', '.join(LANGUAGE_DISTANCES)}, got {out['distance']!r}"
        )
    if out["distance"] == "oracle":
        _warn_oracle()
    for key in ("r_scale", "goal_bonus", "proximity_bonus"):
        out[key] = float(out[key])
    return out


_ORACLE_WARNED = False


def _warn_oracle() -> None:
    """One warning per process that the oracle distance is privileged (a collector's workers each log theirs)."""
    global _ORACLE_WARNED  # noqa: PLW0603 (a once-per-process flag)
    if not _ORACLE_WARNED:
        _ORACLE_WARNED = True
        logger.warning(
            "shaping.language.distance=oracle: R_lang's b_prox is a BFS on the full MiniGrid map, which the agent "
            "cannot observe (privileged information); results using it must say so"
        )


def _make_parser(kind: str, llm_path: str | None) -> Any:
    """The process-wide mission parser (``freamer_rl.machinery.mission.make_mission_parser``, cached there)."""
    from freamer_rl.machinery.mission import make_mission_parser  # noqa: PLC0415 (the LLM parser pulls in transformers)

    return make_mission_parser(kind, MINIGRID_MISSION_VOCAB, llm_path)


class LanguageReward:
    """Env-side R_lang for one MiniGrid env: parses each new mission once and tracks its targets per episode.

    Args:
        option: the ``language_reward`` env option (see :func:`check_language_option`).
    """

    def __init__(self, option: Mapping[str, Any]) -> None:
        self.option = check_language_option(option)
        self.parser = _make_parser(self.option["parser"], self.option["llm_path"])
        self._mission: str | None = None
        self._tracker: LanguageRewardTracker | None = None

    def reset(self, env: Any, mission: str, image: np.ndarray) -> float:
        """After an env reset: ``env`` the unwrapped gymnasium env, ``image`` ``uint8 [V, V, 3]``; returns 0.0."""
        if mission != self._mission or self._tracker is None:
            parsed = self.parser.parse(mission)
            opt = self.option
            self._tracker = LanguageRewardTracker(
                parsed,
                r_scale=opt["r_scale"],
                goal_bonus=opt["goal_bonus"],
                proximity_bonus=opt["proximity_bonus"],
                distance=opt["distance"],
            )
            self._mission = mission
            logger.debug("mission %r -> targets %s", mission, self._tracker.targets)
        return self._tracker.reset(env, image)

    def step(self, env: Any, image: np.ndarray) -> float:
        """R_lang of the env step just taken."""
        return self._tracker.step(env, image)


def language_reward_option(cfg: Any) -> dict[str, Any] | None:
    """``cfg.shaping.language`` as the ``language_reward`` env option (``None`` when its weight is 0 or the trainer's
    schema has no ``shaping`` section: the env then computes nothing)."""
    lang = cfg.shaping.language if hasattr(cfg, "shaping") else None
    if lang is None or not lang.weight:
        return None
    return check_language_option({key: getattr(lang, key) for key in LANGUAGE_REWARD_DEFAULTS})
