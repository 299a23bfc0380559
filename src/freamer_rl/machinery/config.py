"""Recipe sections of the training machinery: ``shaping``, ``success_buffer``, ``ogm``."""

from __future__ import annotations

from dataclasses import dataclass, field

from freamer_rl.config.checks import NON_NEGATIVE, POSITIVE, Range

#: Choices of ``shaping.language.distance``: how b_prox of R_lang measures the distance to the current target.
LANGUAGE_DISTANCES: tuple[str, ...] = ("observed", "oracle", "none")


@dataclass
class LanguageRewardConfig:
    """R_lang = s_match * r_scale + b_goal + b_prox (App. A.2, Eq. A10) from the parsed mission (App. A.1)."""

    weight: float = 0.0  # lambda_lang (Table A20: 0.2); 0 = off
    parser: str = "regex"  # regex | llm (a causal LM through transformers, from llm_path)
    llm_path: str | None = None  # local directory of e.g. Qwen2.5-1.5B-Instruct (config, tokenizer, weights)
    r_scale: float = 0.1  # per step while the current target is in view
    goal_bonus: float = 1.0  # once per target reached (key carried, door opened, goal reached)
    proximity_bonus: float = 0.1  # per cell of shortest-path distance gained towards the current target
    # the distance of b_prox: observed (BFS on the cells seen so far this episode, unseen cells passable, only seen
    # targets) | oracle (BFS on the full map the agent cannot see: privileged information, flagged as such) | none
    distance: str = "observed"


@dataclass
class NoveltyConfig:
    """Count-based novelty bonus of the NovelD family (``freamer_rl.machinery.exploration.NoveltyBonus``)."""

    weight: float = 0.0  # 0 = off
    alpha: float = 0.5  # NovelD: bonus = max(N(s') - alpha * N(s), 0) on the first visit of s' in an episode
    keys: list[str] = field(default_factory=lambda: ["grid", "direction"])  # observation entries hashed


@dataclass
class ShapingConfig:
    """Reward terms added to the env reward for PPO (App. G.1-G.2, A.5). Success is still judged on the env reward.

    shaped = reward_scale * (r_env + decay * (sum of weight * term) - time_penalty * (1 + success_rate)), with decay =
    max(1 - 1.25 * success_rate, 0) when ``adaptive`` (G.2), else 1.
    """

    adaptive: bool = False
    language: LanguageRewardConfig = field(default_factory=LanguageRewardConfig)
    vision_language: float = 0.0  # lambda_VL (Table A20: 0.1): cosine of the refined vision (or state) and language
    curiosity: float = 0.0  # lambda_intrinsic (Table A20: 0.2): forward-model prediction error on the fused embedding
    curiosity_lr: float = 1e-4  # the curiosity forward model's own Adam (eps 1e-5, grad clip 1.0)
    novelty: NoveltyConfig = field(default_factory=NoveltyConfig)
    time_penalty: float = 0.0  # alpha of P_time (App. A.5; 0.02 recommended with the language reward)
    # the factor on the reward PPO's GAE reads (not on the logged return): smaller value targets for a critic that
    # shares the policy's trunk (recipes/gym/cartpole.yaml says what it measured)
    reward_scale: float = 1.0
    # divide that reward by a running std of its discounted return (machinery/return_norm.py): value targets of
    # about unit size whatever the task's reward size; reward_scale still applies first
    return_norm: bool = False
    return_norm_floor: float = 0.1  # the smallest return std divided by: the factor is at most 1 / floor


@dataclass
class SuccessBufferConfig:
    """Successful episodes replayed into PPO (App. G.3) with V-trace targets and truncated importance weights."""

    enabled: bool = False
    mix: float = 0.25  # fraction of each minibatch's sequences drawn from the buffer
    capacity: int = 512  # sequences kept (oldest dropped first)
    rho_clip: float = 1.0  # truncation of the importance weights (V-trace rho-bar = c-bar)


@dataclass
class OGMConfig:
    """OGM-GE gate modulation driven by each modality's FM-loss convergence (Section 4.3.5, Appendix K)."""

    mode: str = "none"  # none | A (gate logits only, lr x lr_scale) | B (all FM parameters)
    alpha: float = 0.5  # modulation strength: coefficient 1 - tanh(alpha * relu(discrepancy - 1))
    lr_scale: float = 10.0  # Mode A learning-rate amplification of the gate logits
    noise: bool = True  # GE: Gaussian noise with the gradient's own std
    ema: float = 0.9  # smoothing of the per-modality FM losses


MACHINERY_RANGES: dict[str, Range] = {
    "shaping.language.weight": (NON_NEGATIVE, ">= 0"),
    "shaping.language.r_scale": (NON_NEGATIVE, ">= 0"),
    "shaping.language.goal_bonus": (NON_NEGATIVE, ">= 0"),
    "shaping.language.proximity_bonus": (NON_NEGATIVE, ">= 0"),
    "shaping.vision_language": (NON_NEGATIVE, ">= 0"),
    "shaping.curiosity": (NON_NEGATIVE, ">= 0"),
    "shaping.curiosity_lr": (POSITIVE, "> 0"),
    "shaping.novelty.weight": (NON_NEGATIVE, ">= 0"),
    "shaping.novelty.alpha": (NON_NEGATIVE, ">= 0"),
    "shaping.time_penalty": (NON_NEGATIVE, ">= 0"),
    "shaping.reward_scale": (POSITIVE, "> 0"),
    "shaping.return_norm_floor": (POSITIVE, "> 0"),
    "success_buffer.mix": (lambda v: 0 < v < 1, "in (0, 1)"),
    "success_buffer.rho_clip": (POSITIVE, "> 0"),
    "ogm.alpha": (POSITIVE, "> 0"),
    "ogm.lr_scale": (POSITIVE, "> 0"),
    "ogm.ema": (lambda v: 0 <= v < 1, "in [0, 1)"),
}
