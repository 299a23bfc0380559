"""The shaped reward PPO trains on: env reward + decayed bonus terms - time penalty (paper App. G.1, G.2, A.5).

``("next", "reward")`` (the env's, on which success is judged) is never modified; :class:`RewardMixer` writes
``("next", "shaped_reward")`` and the trainer's GAE reads it (``GAE.set_keys(reward="shaped_reward")``)::

    r_shaped = scale * (r_env + decay * sum_i w_i * term_i - P)                      (G.1 + G.2 + A.5)
    decay    = max(1 - 1.25 * S, 0)   (adaptive=True, G.2)   or 1   (adaptive=False)
    P        = time_penalty * (1 + rho / 100),  rho = 100 * S  (the success rate in percent)

``P`` is the per-step penalty: A.5's ``P_time = alpha (1 + rho/100) t`` is what it adds up to after ``t`` steps
(alpha = 0.05, rho = 29.5 %, t = 145 gives 9.39, the figure quoted in A.5; see
:meth:`RewardMixer.accumulated_time_penalty`).

``scale`` (``shaping.reward_scale``, 1 by default) sets the size of the returns the critic regresses on: with a
critic that shares the policy's trunk, returns of ~100 (CartPole) let the value loss's gradient crowd out the
policy's after gradient clipping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn

__all__ = ["RewardMixer"]

#: what writes each usual bonus entry (the last element of its key), for the missing-key error
KNOWN_WRITERS = {
    "novelty_bonus": "the NoveltyBonus env transform (freamer_rl.machinery.exploration; append it to the env's Compose)",
    "curiosity_reward": "CuriosityModel.intrinsic_reward on the batch (freamer_rl.machinery.exploration)",
    "vl_reward": "vision_language_similarity on the batch's refined embeddings (freamer_rl.machinery.exploration)",
    "lang_reward": "the env's language reward (freamer_rl_envs.minigrid_language)",
}


def _last(key: NestedKey) -> str:
    return key if isinstance(key, str) else key[-1]


class RewardMixer(nn.Module):
    """Mixes bonus terms into ``("next", "shaped_reward")`` ``[*B, T, 1]`` (module docstring for the equation).

    Follows TorchRL's loss-key pattern: the keys live in :attr:`tensor_keys` (an ``_AcceptedKeys`` dataclass) and
    :meth:`set_keys` renames them. The mixer has no parameters; its one piece of state is each env row's bonus so far
    in its unfinished episode, for the ``bonus_per_episode`` diagnostic (batches must come in collection order).

    Keys (defaults):
        reward: ``("next", "reward")``, the env reward ``[*B, T, 1]`` (read, never written).
        done, terminated: ``("next", "done")``, ``("next", "terminated")``; declared so the mixer's keys can be kept
            in step with the value estimator's (:attr:`in_keys` lists them) -- the arithmetic does not read them;
            ``done`` (when present) ends the episodes of the ``bonus_per_episode`` diagnostic.
        shaped_reward: ``("next", "shaped_reward")``, the output.

    Args:
        terms: ``{name: (key, weight)}``; each ``key`` holds a ``[*B, T, 1]`` (or ``[*B, T]``) bonus, e.g.
            ``{"novelty": (("next", "novelty_bonus"), 0.1)}``. A zero weight keeps the term in the diagnostics.
        adaptive: G.2's decay ``max(1 - 1.25 S, 0)`` of the bonus sum; False: decay 1.
        time_penalty: A.5's ``alpha`` (0 turns the penalty off; the paper's 0.05, or 0.02 as A.5 recommends).
        scale: the factor on the whole shaped reward (finite, > 0; 1 leaves it as it is).
        out_key: shortcut for ``set_keys(shaped_reward=...)``.

    Forward: ``mixer(td, success_rate)`` writes the output key and returns ``td``. ``success_rate`` is the recent
    success rate ``S`` in ``[0, 1]``; NaN (no episode finished yet) counts as 0. :meth:`diagnostics` returns the
    last call's ``bonus_<name>`` (each term's raw mean), ``shaping_decay``, ``time_penalty`` (per step) and, with
    terms and a ``done`` entry, ``bonus_per_episode``: the weighted, decayed bonus each episode that ended in the
    batch collected, from its first step (carried over from earlier batches) to its last, averaged over those
    episodes (NaN when none ended), in env-reward units (before ``scale``). Read it beside the episode return: a
    positive per-step bonus that adds up to more than the task's reward pays the agent to keep episodes running
    rather than to finish them (DoorKey-8x8 with the novelty bonus at weight 0.1: ~5 per episode against a goal
    reward of at most 1). The carried sums are not checkpointed: after a resume each row's first episode counts from
    the resume.

    Raises:
        KeyError: a term's key (or the reward) is missing, naming the key and what writes it.
        ValueError: a non-finite weight, a negative time penalty, a scale that is not finite and > 0, or a success
            rate outside ``[0, 1]``.
    """

    @dataclass
    class _AcceptedKeys:
        reward: NestedKey = ("next", "reward")
        done: NestedKey = ("next", "done")
        terminated: NestedKey = ("next", "terminated")
        shaped_reward: NestedKey = ("next", "shaped_reward")

    default_keys = _AcceptedKeys

    def __init__(
        self,
        terms: dict[str, tuple[NestedKey, float]] | None = None,
        *,
        adaptive: bool = True,
        time_penalty: float = 0.0,
        scale: float = 1.0,
        out_key: NestedKey | None = None,
    ) -> None:
        super().__init__()
        self.terms: dict[str, tuple[NestedKey, float]] = {}
        for name, (key, weight) in (terms or {}).items():
            if not math.isfinite(weight):
                raise ValueError(f"RewardMixer: weight of term {name!r} must be finite, got {weight!r}")
            self.terms[name] = (key, float(weight))
        if not (math.isfinite(time_penalty) and time_penalty >= 0):
            raise ValueError(f"RewardMixer: time_penalty must be a finite number >= 0, got {time_penalty!r}")
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"RewardMixer: scale must be a finite number > 0, got {scale!r}")
        self.adaptive = bool(adaptive)
        self.time_penalty = float(time_penalty)
        self.scale = float(scale)
        self.tensor_keys = self._AcceptedKeys()
        if out_key is not None:
            self.set_keys(shaped_reward=out_key)
        self._diagnostics: dict[str, torch.Tensor] = {}
        self._carry: torch.Tensor | None = None  # [rows] bonus so far in each row's unfinished episode

    def set_keys(self, **kwargs: NestedKey) -> RewardMixer:
        """Rename keys (``reward``, ``done``, ``terminated``, ``shaped_reward``), as TorchRL's losses do."""
        allowed = {f.name for f in fields(self._AcceptedKeys)}
        for name, key in kwargs.items():
            if name not in allowed:
                raise ValueError(
                    f"RewardMixer.set_keys: {name!r} is not a key of the mixer (expected one of {sorted(allowed)})"
                )
            setattr(self.tensor_keys, name, key)
        return self

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        return [k.reward, k.done, k.terminated, *(key for key, _ in self.terms.values())]

    @property
    def out_keys(self) -> list[NestedKey]:
        return [self.tensor_keys.shaped_reward]

    # -- the equation ---------------------------------------------------------------------------------------------
    @staticmethod
    def _clean_rate(success_rate: float) -> float:
        rate = float(success_rate)
        if math.isnan(rate):
            return 0.0  # no episode finished yet
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"RewardMixer: success_rate must be in [0, 1] (or NaN), got {success_rate!r}")
        return rate

    def decay(self, success_rate: float) -> float:
        """G.2's bonus weight ``max(1 - 1.25 S, 0)`` (1 when ``adaptive`` is False)."""
        return max(1.0 - 1.25 * self._clean_rate(success_rate), 0.0) if self.adaptive else 1.0

    def step_penalty(self, success_rate: float) -> float:
        """A.5's per-step penalty ``alpha (1 + rho / 100)`` with ``rho = 100 S``."""
        rho = 100.0 * self._clean_rate(success_rate)
        return self.time_penalty * (1.0 + rho / 100.0)

    @staticmethod
    def accumulated_time_penalty(alpha: float, success_rate: float, steps: int) -> float:
        """A.5's ``P_time = alpha (1 + rho/100) t`` after ``t = steps`` steps (0.05, 0.295, 145 -> 9.39)."""
        return RewardMixer(time_penalty=alpha, adaptive=False).step_penalty(success_rate) * steps

    def _get(self, td: TensorDictBase, name: str, key: NestedKey) -> torch.Tensor:
        value = td.get(key, None)
        if value is None:
            writer = KNOWN_WRITERS.get(
                _last(key), "whatever produces it (an env transform, or a module run on the batch before the mixer)"
            )
            raise KeyError(f"RewardMixer: {name} key {key!r} is missing from the tensordict; it is written by {writer}")
        return value

    def forward(self, td: TensorDictBase, success_rate: float) -> TensorDictBase:
        """Write ``shaped_reward`` ``[*B, T, 1]`` into ``td`` (the env reward is left as it is); returns ``td``."""
        keys = self.tensor_keys
        reward = self._get(td, "reward", keys.reward)
        decay = self.decay(success_rate)
        penalty = self.step_penalty(success_rate)
        bonus = torch.zeros_like(reward)
        diag: dict[str, torch.Tensor] = {}
        for name, (key, weight) in self.terms.items():
            term = self._get(td, f"term {name!r}", key)
            if term.shape == reward.shape[:-1]:
                term = term.unsqueeze(-1)
            term = term.to(reward.dtype)
            bonus = bonus + weight * term
            diag[f"bonus_{name}"] = term.detach().mean()
        td.set(keys.shaped_reward, self.scale * (reward + decay * bonus - penalty))
        done = td.get(keys.done, None)
        if self.terms and done is not None:
            diag["bonus_per_episode"] = self._episode_bonus(decay * bonus.detach(), done)
        diag["shaping_decay"] = torch.tensor(decay)
        diag["time_penalty"] = torch.tensor(penalty)
        self._diagnostics = diag
        return td

    def _episode_bonus(self, added: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """Mean bonus of the episodes that end in this batch (0-dim; NaN when none), each summed from its first step;
        ``added`` ``[*B, T, 1]`` the weighted bonus per step, ``done`` ``[*B, T, 1]`` or ``[*B, T]``. Vectorised over
        time (cumulative sums, the last end before each step by ``cummax``): no host sync."""
        steps = added.shape[-2]
        a = added.reshape(-1, steps)
        d = done.reshape(a.shape).bool()
        if self._carry is None or self._carry.shape != a.shape[:1]:
            self._carry = torch.zeros(a.shape[0], dtype=a.dtype, device=a.device)
        total = self._carry[:, None] + a.cumsum(-1)  # bonus since the row's episode start before this batch
        t = torch.arange(steps, device=a.device).expand_as(d)
        last_end = torch.where(d, t, torch.full_like(t, -1)).cummax(-1).values  # last end at or before t
        before = torch.cat([torch.full_like(last_end[:, :1], -1), last_end[:, :-1]], -1)  # last end before t
        zero = torch.zeros_like(total[:, :1])
        padded = torch.cat([zero, total], -1)  # padded[:, i + 1] = total at i; padded[:, 0] = 0 (no end yet)
        per_step = total - padded.gather(-1, before + 1)  # this episode's bonus up to t
        self._carry = total[:, -1] - padded.gather(-1, last_end[:, -1:] + 1).squeeze(-1)
        ends = d.sum()
        mean = (per_step * d).sum() / ends.clamp_min(1)
        return torch.where(ends > 0, mean, torch.full_like(mean, math.nan))

    def diagnostics(self) -> dict[str, float]:
        """The last forward's ``bonus_<name>`` (mean raw term), ``shaping_decay``, ``time_penalty`` as floats
        (one host sync per term, here rather than in :meth:`forward`)."""
        return {k: float(v) for k, v in self._diagnostics.items()}

    def extra_repr(self) -> str:
        return f"terms={self.terms}, adaptive={self.adaptive}, time_penalty={self.time_penalty}, scale={self.scale}"
