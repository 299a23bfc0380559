"""The parsed form of a mission string (paper Appendix A, Eq. A8) and the vocabulary it must stay within."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MissionVocabulary:
    """The words a parse may use: an env adapter provides it (MiniGrid: its object types and colours).

    Attributes:
        objects: object type names, e.g. ``("goal", "key", "door", "ball", "box")``.
        colors: colour names, e.g. ``("red", "green", "blue", "purple", "yellow", "grey")``.
        actions: action verbs, e.g. ``("go", "get", "pick", "open", "unlock", "put", "traverse", "find", "reach")``.
    """

    objects: tuple[str, ...]
    colors: tuple[str, ...]
    actions: tuple[str, ...]


@dataclass(frozen=True)
class Target:
    """An object the mission names: its type and, when the mission gives one, its colour (``None``: any)."""

    object: str
    color: str | None = None


@dataclass(frozen=True)
class ParsedMission:
    """``(g_final, {g_i}, {a_j}, {o_k})`` of Eq. A8, every word inside a :class:`MissionVocabulary`.

    Attributes:
        final_goal: the target whose reaching ends the task (``Target("goal")`` for "get to the goal").
        intermediate_goals: targets to deal with first, in order (the key before the door it unlocks).
        actions: action verbs in mission order.
        objects: every object mentioned, in mission order.
        source: ``"regex"`` or ``"llm"`` -- which parser produced it.
    """

    final_goal: Target
    intermediate_goals: tuple[Target, ...] = ()
    actions: tuple[str, ...] = ()
    objects: tuple[Target, ...] = ()
    source: str = "regex"
