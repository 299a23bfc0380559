"""LRU cache of mission parses (paper Appendix A.1: capacity 1,000, keyed by MD5) and the parser factory.

:func:`make_mission_parser` builds a parser by name from :data:`PARSERS` and wraps it in a
:class:`CachedMissionParser`. Within one process it returns the same object for the same (kind, vocabulary, model
path, options), so an env factory called once per parallel env loads an LLM once and shares its cache;
:func:`parser_stats` sums the statistics of every parser it made (the trainer logs them).
"""

from __future__ import annotations

import hashlib
import os
from collections import OrderedDict
from collections.abc import Callable

from freamer_rl.machinery.mission.llm_parser import LLMMissionParser, MissingWeightsError, missing_weights_message
from freamer_rl.machinery.mission.regex_parser import RegexMissionParser
from freamer_rl.machinery.mission.types import MissionVocabulary, ParsedMission


def mission_key(mission: str) -> str:
    """Return the cache key of ``mission``: the MD5 hex digest of its UTF-8 bytes (``None`` counts as ``""``)."""
    text = "" if mission is None else str(mission)
    return hashlib.md5(text.encode()).hexdigest()


class CachedMissionParser:
    """A parser behind an LRU cache of its parses.

    Args:
        parser: any object with ``parse(mission) -> ParsedMission`` (and optionally a ``fallbacks`` count).
        capacity: the most parses kept; the least recently used one is dropped first.
    """

    def __init__(self, parser, capacity: int = 1000) -> None:
        if int(capacity) < 1:
            raise ValueError(f"mission parser cache capacity must be >= 1, got {capacity}")
        self.parser = parser
        self.capacity = int(capacity)
        self.hits = 0
        self.misses = 0
        self._cache: OrderedDict[str, ParsedMission] = OrderedDict()

    @property
    def cache_size(self) -> int:
        """Return how many parses the cache holds."""
        return len(self._cache)

    def parse(self, mission: str) -> ParsedMission:
        """Return the parse of ``mission``: from the cache when present, else from the wrapped parser (then cached)."""
        key = mission_key(mission)
        cached = self._cache.get(key)
        if cached is not None:
            self.hits += 1
            self._cache.move_to_end(key)
            return cached
        self.misses += 1
        parsed = self.parser.parse(mission)
        self._cache[key] = parsed
        if len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return parsed

    def stats(self) -> dict:
        """Return ``{"hits", "misses", "hit_rate", "fallbacks"}`` (fallbacks of the wrapped parser, else 0)."""
        lookups = self.hits + self.misses
        return {
            "hits": self.hits,
            "misses": self.misses,
            "hit_rate": self.hits / lookups if lookups else 0.0,
            "fallbacks": int(getattr(self.parser, "fallbacks", 0)),
        }

    def clear(self) -> None:
        """Drop every cached parse and reset the hit/miss counts. Returns None."""
        self._cache.clear()
        self.hits = self.misses = 0


def _build_regex(vocab: MissionVocabulary, llm_path: str | None, **options) -> RegexMissionParser:
    """Return a :class:`RegexMissionParser` (``llm_path`` is ignored)."""
    return RegexMissionParser(vocab, **options)


def _build_llm(vocab: MissionVocabulary, llm_path: str | None, **options) -> LLMMissionParser:
    """Return an :class:`LLMMissionParser` loaded from ``llm_path``.

    Raises:
        MissingWeightsError: ``llm_path`` is unset or does not hold a model.
    """
    if not llm_path:
        raise MissingWeightsError(missing_weights_message(None, "no model directory given"))
    return LLMMissionParser(llm_path, vocab, **options)


# kind -> builder(vocab, llm_path, **options) -> parser
PARSERS: dict[str, Callable[..., object]] = {"regex": _build_regex, "llm": _build_llm}
_MADE: dict[tuple, CachedMissionParser] = {}


def make_mission_parser(
    kind: str, vocab: MissionVocabulary, llm_path: str | None = None, **options
) -> CachedMissionParser:
    """Return the cached parser of ``kind`` for ``vocab``; the same object again for the same arguments.

    Args:
        kind: a key of :data:`PARSERS` (``"regex"`` or ``"llm"``).
        vocab: the words a parse may contain.
        llm_path: the local model directory (kind ``"llm"``; recipe field ``shaping.language.llm_path``).
        **options: ``capacity`` for the cache; the rest goes to the parser (e.g. ``max_new_tokens``, ``device``).

    Raises:
        ValueError: unknown ``kind`` (the message names the known kinds).
        MissingWeightsError: kind ``"llm"`` without a usable ``llm_path``.
    """
    if kind not in PARSERS:
        raise ValueError(f"unknown mission parser {kind!r}; known parsers: {', '.join(sorted(PARSERS))}")
    path = os.path.abspath(os.path.expanduser(llm_path)) if llm_path else None
    key = (kind, vocab, path if kind != "regex" else None, repr(sorted(options.items())))
    if key not in _MADE:
        capacity = options.pop("capacity", 1000)
        _MADE[key] = CachedMissionParser(PARSERS[kind](vocab, path, **options), capacity=capacity)
    return _MADE[key]


def parser_stats() -> dict:
    """Return ``{"hits", "misses", "hit_rate", "fallbacks", "parsers"}`` summed over every parser made here."""
    hits = sum(p.hits for p in _MADE.values())
    misses = sum(p.misses for p in _MADE.values())
    return {
        "hits": hits,
        "misses": misses,
        "hit_rate": hits / (hits + misses) if hits + misses else 0.0,
        "fallbacks": sum(p.stats()["fallbacks"] for p in _MADE.values()),
        "parsers": len(_MADE),
    }


def clear_mission_parsers() -> None:
    """Forget every parser :func:`make_mission_parser` made (tests; frees a loaded LLM). Returns None."""
    _MADE.clear()
