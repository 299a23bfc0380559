"""Rule-based mission parser: the fallback of Eq. (A9) and the parser used when no LLM is configured.

It reads a MiniGrid/BabyAI mission word by word and splits it into clauses, each starting at a verb ("pick up the
blue key | and open the blue door"). Every clause names at most one goal: its first object, except for
"put X near Y" / "X next to Y", whose goal is Y (X becomes an intermediate goal), and "avoid X", which names no goal.
Objects after "from"/"in" ("get the key from the purple room") are places visited before the clause's goal.
BabyAI's "A after you B" is read in execution order (B, then A). The final goal is the goal of the last clause; the
goals of earlier clauses are the intermediate goals, in order.

Only words of the :class:`~freamer_rl.machinery.mission.types.MissionVocabulary` reach the result: objects and actions are
vocabulary words (a plural such as "rooms" counts as its singular when that is a vocabulary object), and a colour
word directly before an object word sets that object's colour.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from freamer_rl.machinery.mission.types import MissionVocabulary, ParsedMission, Target

_WORD = re.compile(r"[a-z]+")
# Verbs that start a clause even when they are not vocabulary actions (only vocabulary actions are reported).
CLAUSE_VERBS = frozenset(
    {
        "go",
        "get",
        "reach",
        "pick",
        "open",
        "put",
        "place",
        "unlock",
        "find",
        "traverse",
        "use",
        "avoid",
        "drop",
        "toggle",
        "fetch",
        "grab",
        "take",
        "collect",
        "visit",
        "enter",
        "close",
        "explore",
        "move",
        "navigate",
        "bring",
        "carry",
        "locate",
        "search",
    }
)
AVOID_VERBS = frozenset({"avoid"})
GOAL_PREPOSITIONS = frozenset({"near", "beside", "next_to"})  # "put X near Y": Y is the goal
PLACE_PREPOSITIONS = frozenset({"from", "in", "inside", "through"})  # "get X from the Y room": Y is a place


@dataclass
class _Clause:
    """A verb and the objects it governs, each tagged ``"main"``, ``"goal_prep"`` or ``"place"``."""

    verb: str | None
    items: list[tuple[str, Target]] = field(default_factory=list)
    preposition: str | None = None


def _as_text(mission: object) -> str:
    """Return ``mission`` as a lower-case string (``None`` -> ``""``)."""
    return "" if mission is None else str(mission).lower()


def _words(mission: object) -> list[str]:
    """Return the lower-case words of ``mission``, with "next to" joined into one word ``next_to``."""
    words = _WORD.findall(_as_text(mission))
    out: list[str] = []
    for word in words:
        if word == "to" and out and out[-1] == "next":
            out[-1] = "next_to"
        else:
            out.append(word)
    return out


def _dedupe(targets: list[Target]) -> list[Target]:
    """Return ``targets`` without repeats, first occurrence kept."""
    seen: set[Target] = set()
    return [t for t in targets if not (t in seen or seen.add(t))]


class RegexMissionParser:
    """Parse MiniGrid/BabyAI missions with word rules; :meth:`parse` never raises.

    Args:
        vocab: the words a parse may contain.
    """

    source = "regex"

    def __init__(self, vocab: MissionVocabulary) -> None:
        self.vocab = vocab
        self._objects = {o.lower(): o for o in vocab.objects}
        self._colors = {c.lower(): c for c in vocab.colors}
        self._actions = {a.lower(): a for a in vocab.actions}

    def default_goal(self) -> Target:
        """Return the final goal used when a mission names no object: ``goal`` if a vocabulary object, else the first
        vocabulary object (``Target("goal")`` for an empty vocabulary)."""
        if "goal" in self._objects:
            return Target(self._objects["goal"])
        return Target(self.vocab.objects[0]) if self.vocab.objects else Target("goal")

    def parse(self, mission: str) -> ParsedMission:
        """Return the :class:`ParsedMission` of ``mission`` (source ``"regex"``); every word is in the vocabulary."""
        words = _words(mission)
        actions = tuple(self._actions[w] for w in words if w in self._actions)
        clauses = [c for segment in self._segments(words) for c in self._clauses(segment)]
        mentioned = _dedupe([t for c in clauses for _, t in c.items])
        goals: list[Target] = []
        for clause in clauses:
            goals.extend(self._clause_goals(clause))
        final = goals[-1] if goals else self.default_goal()
        intermediate = [g for g in _dedupe(goals[:-1]) if g != final]
        mentioned_in_order = self._objects_in_order(words, mentioned)
        return ParsedMission(
            final_goal=final,
            intermediate_goals=tuple(intermediate),
            actions=actions,
            objects=tuple(mentioned_in_order),
            source=self.source,
        )

    # ----------------------------------------------------------------------------------------------------------------
    def _object_word(self, word: str) -> str | None:
        """Return the vocabulary object that ``word`` names (singular or a plain plural), or None."""
        for candidate in (word, word[:-2] if word.endswith("es") else None, word[:-1] if word.endswith("s") else None):
            if candidate and candidate in self._objects:
                return self._objects[candidate]
        return None

    def _segments(self, words: list[str]) -> list[list[str]]:
        """Return the word lists in execution order: "A after you B" -> [B, A]; otherwise [words]."""
        for i in range(len(words) - 1):
            if words[i] == "after" and words[i + 1] == "you":
                return [words[i + 2 :], words[:i]]
        return [words]

    def _clauses(self, words: list[str]) -> list[_Clause]:
        """Return the clauses of ``words``: a new clause at every verb; objects before any verb form their own."""
        clauses = [_Clause(verb=None)]
        for i, word in enumerate(words):
            if word in CLAUSE_VERBS or word in self._actions:
                clauses.append(_Clause(verb=word))
                continue
            clause = clauses[-1]
            if word == "to":  # "go through the door to the goal": what follows "to" is no longer a place
                clause.preposition = None
                continue
            if word in GOAL_PREPOSITIONS or word in PLACE_PREPOSITIONS:
                clause.preposition = word
                continue
            obj = self._object_word(word)
            if obj is None:
                continue
            color = self._colors.get(words[i - 1]) if i > 0 else None
            role = "main"
            if clause.preposition in GOAL_PREPOSITIONS:
                role = "goal_prep"
            elif clause.preposition in PLACE_PREPOSITIONS:
                role = "place"
            clause.items.append((role, Target(obj, color)))
        return [c for c in clauses if c.items]

    def _clause_goals(self, clause: _Clause) -> list[Target]:
        """Return the goals a clause contributes, its own goal last (empty for "avoid X")."""
        if clause.verb in AVOID_VERBS:
            return []
        by_role = {role: [t for r, t in clause.items if r == role] for role in ("main", "goal_prep", "place")}
        if by_role["goal_prep"]:  # put X near Y: X first, then Y
            return by_role["place"] + by_role["main"] + by_role["goal_prep"][:1]
        if by_role["main"]:  # get X from Y: the place Y first, then X
            return by_role["place"] + by_role["main"][:1]
        return by_role["place"][:1]

    def _objects_in_order(self, words: list[str], mentioned: list[Target]) -> list[Target]:
        """Return ``mentioned`` re-sorted into the order the mission text names them (clauses may be reordered)."""
        position: dict[Target, int] = {}
        for i, word in enumerate(words):
            obj = self._object_word(word)
            if obj is not None:
                target = Target(obj, self._colors.get(words[i - 1]) if i > 0 else None)
                position.setdefault(target, i)
        return sorted(mentioned, key=lambda t: position.get(t, len(words)))
