"""Fixed and hand-written reference policies of the health env: the yardstick for the imagination-trained policy.

Every reference policy is a :class:`~tensordict.nn.TensorDictModuleBase` that reads the real env's observations and
writes ``"action"`` (int64 ``[*B]``); :func:`evaluate_reference` rolls it with exactly the protocol of
:func:`freamer_rl.health.evaluation.evaluate_policy` (a fresh env of ``eval.num_envs`` episodes, env seed
``eval.seed``, ``env.episode_length`` steps, metrics read at each env's first ``done``), so the numbers are directly
comparable with a run's ``eval_return_mean``.

Policies (:data:`REFERENCE_POLICIES`):

* ``"continue"``, ``"rest"``, ``"increase"``, ``"change"``, ``"alert"``: always that action;
* ``"random"``: uniform over the 5 actions (its own seeded generator);
* ``"hr_threshold"``: :class:`HeartRateThresholdPolicy` -- Rest while the heart rate is above ``rest_above`` bpm
  (default 150, 10 bpm below the danger zone), Alert above ``alert_above`` (default 185), else Continue.
"""

from __future__ import annotations

import logging
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from freamer_rl.health.agent import make_health_env
from freamer_rl.health.evaluation import rollout_metrics

logger = logging.getLogger(__name__)

__all__ = [
    "ACTION_NAMES",
    "REFERENCE_POLICIES",
    "ConstantActionPolicy",
    "UniformRandomPolicy",
    "HeartRateThresholdPolicy",
    "make_reference_policy",
    "evaluate_reference",
]

#: action names of the health env, in index order (``freamer_rl_envs.health.HEALTH_ACTIONS``; the library does not import envs)
ACTION_NAMES: tuple[str, ...] = ("continue", "rest", "increase", "change", "alert")
REFERENCE_POLICIES: tuple[str, ...] = (*ACTION_NAMES, "random", "hr_threshold")


class ConstantActionPolicy(TensorDictModuleBase):
    """Always the same action: writes ``"action"`` int64 ``[*B]`` (``B`` = the tensordict's batch shape)."""

    def __init__(self, action: int, num_actions: int = len(ACTION_NAMES)) -> None:
        super().__init__()
        if not 0 <= int(action) < num_actions:
            raise ValueError(f"action: expected an index in [0, {num_actions}), got {action!r}")
        self.action = int(action)
        self.in_keys = []
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(
            "action", torch.full(tensordict.batch_size, self.action, dtype=torch.int64, device=tensordict.device)
        )
        return tensordict


class UniformRandomPolicy(TensorDictModuleBase):
    """Uniformly random actions from its own generator (``seed``): ``"action"`` int64 ``[*B]``."""

    def __init__(self, num_actions: int = len(ACTION_NAMES), seed: int = 0) -> None:
        super().__init__()
        self.num_actions = int(num_actions)
        self.generator = torch.Generator().manual_seed(int(seed))
        self.in_keys = []
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        a = torch.randint(0, self.num_actions, tuple(tensordict.batch_size), generator=self.generator)
        tensordict.set("action", a.to(tensordict.device))
        return tensordict


class HeartRateThresholdPolicy(TensorDictModuleBase):
    """Hand-written heuristic on ``"heart_rate"`` ``[*B, 1]`` (bpm): Alert when ``HR > alert_above``, Rest when
    ``HR > rest_above``, else Continue. Writes ``"action"`` int64 ``[*B]``."""

    def __init__(self, rest_above: float = 150.0, alert_above: float = 185.0, hr_key: Any = "heart_rate") -> None:
        super().__init__()
        if not rest_above < alert_above:
            raise ValueError(f"rest_above ({rest_above}) must be < alert_above ({alert_above})")
        self.rest_above = float(rest_above)
        self.alert_above = float(alert_above)
        self.hr_key = hr_key
        self.in_keys = [hr_key]
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        hr = tensordict.get(self.hr_key)
        if hr.shape != (*tensordict.batch_size, 1):
            raise ValueError(
                f"HeartRateThresholdPolicy: expected {self.hr_key!r} of shape "
                f"{(*tensordict.batch_size, 1)}, got {tuple(hr.shape)}"
            )
        hr = hr.squeeze(-1)
        action = torch.zeros_like(hr, dtype=torch.int64)
        action = action.masked_fill(hr > self.rest_above, ACTION_NAMES.index("rest"))
        action = action.masked_fill(hr > self.alert_above, ACTION_NAMES.index("alert"))
        tensordict.set("action", action)
        return tensordict


def make_reference_policy(name: str, *, seed: int = 0, **kwargs: Any) -> TensorDictModuleBase:
    """One of :data:`REFERENCE_POLICIES` (``kwargs`` go to :class:`HeartRateThresholdPolicy`)."""
    if name in ACTION_NAMES:
        return ConstantActionPolicy(ACTION_NAMES.index(name))
    if name == "random":
        return UniformRandomPolicy(seed=seed)
    if name == "hr_threshold":
        return HeartRateThresholdPolicy(**kwargs)
    raise ValueError(f"unknown reference policy {name!r}; known: {', '.join(REFERENCE_POLICIES)}")


@torch.no_grad()
def evaluate_reference(
    cfg: Any, policy: str | TensorDictModuleBase, *, num_envs: int | None = None, seed: int | None = None
) -> dict[str, float]:
    """Real-env metrics of a reference policy under the evaluation protocol of a
    :class:`~freamer_rl.health.config.HealthConfig` ``cfg`` (``num_envs`` default ``eval.num_envs``, env ``seed``
    default ``eval.seed``): ``return_mean``, ``return_std``, ``violations_mean``, ``length_mean``, ``episodes``."""

    module = make_reference_policy(policy) if isinstance(policy, str) else policy
    n = num_envs or cfg.eval.num_envs
    env = make_health_env(cfg, num_envs=n, seed=cfg.eval.seed if seed is None else seed)
    try:
        traj = env.rollout(cfg.env.episode_length, module, break_when_any_done=False)
    finally:
        env.close()
    return rollout_metrics(traj)
