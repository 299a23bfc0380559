"""Mission parsing (paper Appendix A): a mission string -> final goal, intermediate goals, actions and objects.

``make_mission_parser("regex" | "llm", vocab, llm_path)`` returns a cached parser; the LLM parser (transformers, a
local Qwen2.5-Instruct directory) is imported lazily, so this package imports without transformers.
"""

from freamer_rl.machinery.mission.cache import (
    PARSERS,
    CachedMissionParser,
    clear_mission_parsers,
    make_mission_parser,
    mission_key,
    parser_stats,
)
from freamer_rl.machinery.mission.llm_parser import (
    FALLBACK_REASONS,
    LLMMissionParser,
    LLMNotInstalledError,
    LLMOutputError,
    MissingWeightsError,
    parse_llm_json,
    render_prompt,
)
from freamer_rl.machinery.mission.regex_parser import RegexMissionParser
from freamer_rl.machinery.mission.types import MissionVocabulary, ParsedMission, Target

__all__ = [
    "FALLBACK_REASONS",
    "PARSERS",
    "CachedMissionParser",
    "LLMMissionParser",
    "LLMNotInstalledError",
    "LLMOutputError",
    "MissingWeightsError",
    "MissionVocabulary",
    "ParsedMission",
    "RegexMissionParser",
    "Target",
    "clear_mission_parsers",
    "make_mission_parser",
    "mission_key",
    "parse_llm_json",
    "parser_stats",
    "render_prompt",
]
