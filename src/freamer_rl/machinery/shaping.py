"""The trainer's reward shaping: the bonus terms of App. G.1 (R_lang, R_VL, R_intrinsic), the novelty bonus, the
adaptive decay of G.2 and the time penalty of A.5, combined into the key PPO trains on.

The env reward ``("next", "reward")`` is never changed (episode success is judged on it); the shaped reward goes to
``("next", "shaped_reward")`` and the trainer's GAE reads that key. Where each term comes from:

============================  ===============================================  ========================
term (``("next", key)``)       computed by                                      recipe weight
============================  ===============================================  ========================
``lang_reward``                the env (MiniGrid: ``envs/minigrid_language``)   ``shaping.language.weight``
``novelty_bonus``              :class:`~freamer_rl.machinery.exploration.NoveltyBonus`    ``shaping.novelty.weight``
                               (a transform this module adds to the env)
``vl_reward``                  here: the cosine of the refined embeddings as    ``shaping.vision_language``
                               a potential (:func:`potential_difference`)
``curiosity_reward``           here, :class:`~freamer_rl.machinery.exploration.           ``shaping.curiosity``
                               CuriosityModel` on the fused embedding
============================  ===============================================  ========================
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from freamer_rl.machinery.exploration import CuriosityModel, NoveltyBonus, vision_language_similarity
from freamer_rl.machinery.return_norm import ReturnNormalizer
from freamer_rl.machinery.reward_mixer import RewardMixer
from freamer_rl.run.optim import StepStats, optimizer_step

SHAPED_REWARD = "shaped_reward"
CURIOSITY_EPS = 1e-5  # Adam eps of the curiosity forward model (its lr: shaping.curiosity_lr)
CURIOSITY_GRAD_CLIP = 1.0  # its gradient-norm clip
#: gradient steps of the curiosity forward model per collected batch (on the whole batch)
CURIOSITY_STEPS = 4


def env_transforms(cfg) -> list:
    """Transforms the shaping adds to the training env, after ``RewardSum`` (so returns stay the env's own)."""
    novelty = cfg.shaping.novelty
    # 16-byte digests as keys: a MiniGrid view is 1.2 kB, and a long run meets hundreds of thousands of them
    return [NoveltyBonus(in_keys=list(novelty.keys), alpha=novelty.alpha, digest_size=16)] if novelty.weight else []


def potential_difference(phi: torch.Tensor, done: torch.Tensor, gamma: float) -> torch.Tensor:
    """Potential-based shaping ``gamma * phi(s_{t+1}) - phi(s_t)`` ``[*B, T, 1]`` from per-state potentials
    ``phi [*B, T, 1]`` (time on dim -2; G.2 follows this framework, Ng et al. 1999): it cannot change which policy is
    optimal, and a potential that is positive everywhere does not turn into a bonus for long episodes. An episode's
    end has potential 0; the last step of a row, whose next state was not embedded, uses ``phi(s_t)``."""
    nxt = phi.clone()
    nxt[..., :-1, :] = phi[..., 1:, :]
    nxt = torch.where(done, torch.zeros_like(nxt), nxt)
    return gamma * nxt - phi


class RewardShaper:
    """Computes the trainer-side terms of a collected batch ``[*B, T]`` and mixes everything into
    ``("next", "shaped_reward")``. ``active`` is False when the recipe turns nothing on (PPO then reads the env
    reward directly). ``gamma``: the trainer's discount, which ``shaping.return_norm`` needs."""

    def __init__(
        self,
        cfg,
        modalities: list[str],
        embed_dim: int,
        n_actions: int,
        device: torch.device,
        *,
        gamma: float | None = None,
    ) -> None:
        s = cfg.shaping
        terms: dict[str, tuple] = {}
        if s.language.weight:
            terms["lang"] = (("next", "lang_reward"), s.language.weight)
        if s.novelty.weight:
            terms["novelty"] = (("next", "novelty_bonus"), s.novelty.weight)
        self.vl_keys = None
        if s.vision_language:
            first = "vision" if "vision" in modalities else "state"
            # the refined embeddings when each modality has a refiner (model.flow.placement: pre), else the raw ones
            prefix = "refined" if cfg.model.flow.placement == "pre" else "embed"
            self.vl_keys = ((prefix, first), (prefix, "language"))
            terms["vl"] = (("next", "vl_reward"), s.vision_language)
            self.gamma = cfg.ppo.gamma
        self.curiosity: CuriosityModel | None = None
        if s.curiosity:
            self.curiosity = CuriosityModel(embed_dim, n_actions).to(device)
            # its own optimiser settings (shaping.curiosity_lr), not the policy's: the forward model is not the policy
            self.curiosity_opt = torch.optim.Adam(self.curiosity.parameters(), lr=s.curiosity_lr, eps=CURIOSITY_EPS)
            self.max_grad_norm = CURIOSITY_GRAD_CLIP
            self.step_stats = StepStats("curiosity")
            terms["curiosity"] = (("next", "curiosity_reward"), s.curiosity)
        self.return_norm: ReturnNormalizer | None = None
        if s.return_norm:
            if gamma is None:
                raise ValueError("shaping.return_norm: this trainer gives the reward shaper no discount (gamma)")
            self.return_norm = ReturnNormalizer(gamma, s.return_norm_floor)
        self.active = bool(terms) or s.time_penalty > 0 or s.reward_scale != 1.0 or s.return_norm
        self.mixer = RewardMixer(
            terms,
            adaptive=s.adaptive,
            time_penalty=s.time_penalty,
            scale=s.reward_scale,
            out_key=("next", SHAPED_REWARD),
        )

    def __call__(self, data: TensorDictBase, success_rate: float) -> dict[str, float]:
        """Write the trainer-side terms and the shaped reward into ``data``; returns diagnostics for progress.csv."""
        done = data["next", "done"]
        logs: dict[str, float] = {}
        if self.vl_keys is not None:
            with torch.no_grad():
                sim = vision_language_similarity(data[self.vl_keys[0]], data[self.vl_keys[1]])
            data.set(("next", "vl_reward"), potential_difference(sim, done, self.gamma))
        if self.curiosity is not None:
            logs["loss_curiosity"] = self._curiosity_terms(data)
        self.mixer(data, success_rate)
        logs.update(self.mixer.diagnostics())
        if self.return_norm is not None:
            key = ("next", SHAPED_REWARD)
            data.set(key, self.return_norm(data[key], done))
            logs.update({k: float(v) for k, v in self.return_norm.diagnostics().items()})
        return logs

    def _curiosity_terms(self, data: TensorDictBase) -> float:
        """Intrinsic reward from the forward model's prediction error, then a few steps training it on the batch."""
        phi = data["fused"].detach()
        action = data["action"]
        valid = self.curiosity.valid_mask(data["next", "done"])
        with torch.no_grad():
            data.set(("next", "curiosity_reward"), self.curiosity.intrinsic_reward(phi, action, valid))
        params = list(self.curiosity.parameters())
        loss = torch.zeros(())
        with torch.enable_grad():  # the trainer calls this from its no-grad advantage pass
            for _ in range(CURIOSITY_STEPS):
                loss = self.curiosity.loss(phi, action, valid)
                optimizer_step(loss, self.curiosity_opt, params, self.max_grad_norm, self.step_stats)
        return float(loss.detach())

    def state_dict(self) -> dict:
        state = {}
        if self.curiosity is not None:
            state.update(curiosity=self.curiosity.state_dict(), curiosity_opt=self.curiosity_opt.state_dict())
        if self.return_norm is not None:
            state["return_norm"] = self.return_norm.state()
        return state

    def load_state_dict(self, state: dict) -> None:
        if self.curiosity is not None and state.get("curiosity") is not None:
            self.curiosity.load_state_dict(state["curiosity"])
            self.curiosity_opt.load_state_dict(state["curiosity_opt"])
        if self.return_norm is not None and state.get("return_norm") is not None:
            self.return_norm.load_state(state["return_norm"])
