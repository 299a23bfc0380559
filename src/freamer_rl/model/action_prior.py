"""A fixed threshold rule added to the actor's logits: the policy starts as the rule and PPO learns a residual on it.

``model.action_prior`` (FreamerV1) and ``network.action_prior`` (the TorchRL baselines) take the same section::

    action_prior:
      key: heart_rate          # one scalar observation (shape [] or [1]); null: no prior (the default)
      thresholds: [150, 185]   # ascending
      actions: [0, 1, 4]       # Continue at or below 150, Rest above 150, Alert above 185 (-1: no prior there)
      logit: 2.0               # added to the rule's action's logit
      condition:               # optional: a second scalar observation picks between two rows of actions
        key: level             # null (the default): `actions` everywhere
        threshold: 0.99        # `actions` where level <= 0.99, `condition.actions` where level > 0.99
        actions: [0, 0, 1, 4]

The actor head's logits become ``head(h) + logit * onehot(actions[i])`` with ``i`` the number of thresholds that
``x`` exceeds (``torch.bucketize``, strict ``>``); with a condition, the row is ``condition.actions`` where its key
exceeds ``condition.threshold``. The health env's heart-rate controller is such a rule: Increase below 145 bpm
while the level is below plan, Continue up to 150, Rest above, Alert above 185 (``recipes/suites/health_mf_loso.yaml``,
``mlp_ctrl5``). The orthogonal head starts near zero (output gain 0.01), so the
initial policy takes the rule's action with probability ``e^logit / (e^logit + n - 1)`` and its mode *is* the rule
(PyTorch's default init, ``network.init: torch_default``, starts the head at logits of a few tenths: the mode is the
rule wherever they differ by less than ``logit``); the loss then trains the head, which can move any state away
from the rule. The prior has no parameters and no host syncs; it reads the observation from the same tensordict as
the head, so TorchRL's ``ClipPPOLoss`` recomputes it unchanged. A kickstart of this kind is only as fair as its use:
give it to every arm of a comparison (the health suite ``recipes/suites/health_mf_loso.yaml`` gives it to the
PPO-MLP and FreamerV1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from freamer_rl.errors import ConfigError, EnvSetupError

__all__ = [
    "PriorConditionConfig",
    "ActionPriorConfig",
    "ThresholdRulePrior",
    "PriorLogits",
    "check_action_prior",
    "check_prior_key",
    "prior_keys",
]


@dataclass
class PriorConditionConfig:
    key: str | None = None  # a second scalar observation; None: the prior's `actions` everywhere
    threshold: float = 0.0  # the prior's `actions` where key <= threshold, these `actions` where key > threshold
    actions: list[int] = field(default_factory=list)  # one per interval of the prior's thresholds; -1: no prior


@dataclass
class ActionPriorConfig:
    key: str | None = None  # observation key of one scalar; None: no prior
    thresholds: list[float] = field(default_factory=list)  # ascending cut points on the observation
    # len(thresholds) + 1: the action below, between, above them; -1: no prior in that interval (the head alone)
    actions: list[int] = field(default_factory=list)
    logit: float = 2.0  # added to the rule's action's logit (0: the prior is off but still validated)
    condition: PriorConditionConfig = field(default_factory=PriorConditionConfig)


def prior_keys(prior: ActionPriorConfig | None) -> list[str]:
    """The observation keys the prior reads: ``[]``, ``[key]`` or ``[key, condition.key]``."""
    if prior is None or prior.key is None:
        return []
    return [prior.key] if prior.condition.key is None else [prior.key, prior.condition.key]


def _check_actions(actions: list[int], field_name: str) -> None:
    if any(not isinstance(a, int) or a < -1 for a in actions) or max(actions) < 0:
        raise ConfigError(
            f"{field_name}: expected action indices >= 0 (or -1: no prior in that interval, not all), got {actions}"
        )


def check_action_prior(prior: ActionPriorConfig, section: str) -> None:
    """Every field of ``<section>.action_prior``, named in the error (the action count is checked at build)."""
    name = f"{section}.action_prior"
    if prior.key is None:
        if prior.thresholds or prior.actions:
            raise ConfigError(f"{name}.key: thresholds/actions are set but key is null; name the observation key")
        return
    if not isinstance(prior.key, str) or not prior.key:
        raise ConfigError(f"{name}.key: expected an observation key (a non-empty string), got {prior.key!r}")
    if not prior.thresholds:
        raise ConfigError(f"{name}.thresholds: give at least one threshold")
    if any(b <= a for a, b in zip(prior.thresholds, prior.thresholds[1:])):
        raise ConfigError(f"{name}.thresholds: expected strictly ascending values, got {prior.thresholds}")
    if len(prior.actions) != len(prior.thresholds) + 1:
        raise ConfigError(
            f"{name}.actions: expected len(thresholds) + 1 = {len(prior.thresholds) + 1} actions "
            f"(below, between and above the thresholds), got {len(prior.actions)}: {prior.actions}"
        )
    _check_actions(prior.actions, f"{name}.actions")
    if not prior.logit >= 0.0:
        raise ConfigError(f"{name}.logit: expected a value >= 0, got {prior.logit}")
    _check_condition(prior, name)


def _check_condition(prior: ActionPriorConfig, name: str) -> None:
    cond = prior.condition
    if cond.key is None:
        if cond.actions:
            raise ConfigError(f"{name}.condition.key: actions are set but key is null; name the observation key")
        return
    if not isinstance(cond.key, str) or not cond.key:
        raise ConfigError(f"{name}.condition.key: expected an observation key (a non-empty string), got {cond.key!r}")
    if cond.key == prior.key:
        raise ConfigError(f"{name}.condition.key: {cond.key!r} is the prior's own key; name a second observation")
    if len(cond.actions) != len(prior.actions):
        raise ConfigError(
            f"{name}.condition.actions: expected one action per interval of thresholds ({len(prior.actions)}), "
            f"got {len(cond.actions)}: {cond.actions}"
        )
    _check_actions(cond.actions, f"{name}.condition.actions")


def check_prior_key(prior: ActionPriorConfig, observation_spec, action_spec, section: str) -> None:
    """The env has discrete actions, the prior's key is one of its scalar observations and its actions exist:
    :class:`EnvSetupError` naming ``<section>.action_prior``."""
    name = f"{section}.action_prior"
    if prior.key is None:
        return
    num_actions = getattr(getattr(action_spec, "space", None), "n", None)
    if num_actions is None or action_spec.dtype.is_floating_point:
        raise EnvSetupError(f"{name}: needs a discrete action (Categorical / OneHot), the env's is {action_spec}")
    fields = [(f"{name}.key", prior.key, f"{name}.actions", prior.actions)]
    if prior.condition.key is not None:
        cond = prior.condition
        fields.append((f"{name}.condition.key", cond.key, f"{name}.condition.actions", cond.actions))
    known = observation_spec.keys(True, True)
    for key_field, key, actions_field, actions in fields:
        if key not in known:
            raise EnvSetupError(f"{key_field}: {key!r} is not an observation of the env ({', '.join(map(str, known))})")
        shape = tuple(observation_spec[key].shape)
        if shape not in ((), (1,)):
            raise EnvSetupError(f"{key_field}: {key!r} has shape {list(shape)}; the rule reads one scalar ([] or [1])")
        if max(actions) >= int(num_actions):
            raise EnvSetupError(f"{actions_field}: {actions} names an action >= the env's {num_actions} actions")


class ThresholdRulePrior(nn.Module):
    """``x [*B] or [*B, 1] -> [*B, n]``: ``logit * onehot(actions[#thresholds below x])`` (no parameters); an
    interval whose action is -1 adds nothing. With ``condition_threshold`` / ``condition_actions`` the forward also
    takes ``y`` (a second scalar of the same batch shape) and reads the row ``condition_actions`` where
    ``y > condition_threshold``."""

    def __init__(
        self,
        thresholds: list[float],
        actions: list[int],
        num_actions: int,
        logit: float,
        condition_threshold: float | None = None,
        condition_actions: list[int] | None = None,
    ) -> None:
        super().__init__()
        n = int(num_actions)
        self.register_buffer("thresholds", torch.tensor(thresholds, dtype=torch.float32))
        # -1 (no prior) becomes an extra column n that forward drops
        self.register_buffer("actions", torch.tensor([n if a < 0 else a for a in actions], dtype=torch.long))
        self.conditioned = condition_actions is not None
        if self.conditioned:  # registered only then: priors without a condition keep their state-dict keys
            row = torch.tensor([n if a < 0 else a for a in condition_actions], dtype=torch.long)
            self.register_buffer("condition_actions", row)
            self.register_buffer("condition_threshold", torch.tensor(float(condition_threshold)))
        self.num_actions = n
        self.logit = float(logit)

    def forward(self, x: torch.Tensor, like: torch.Tensor, y: torch.Tensor | None = None) -> torch.Tensor:
        """``like``: the head's logits ``[*B, n]`` (their batch shape, dtype and device); ``y``: the condition's
        observation (required exactly when the prior has a condition)."""
        if (y is None) == self.conditioned:
            need = "has a condition: pass its observation y" if self.conditioned else "has no condition: y must be None"
            raise ValueError(f"ThresholdRulePrior: this prior {need}")
        x = x.reshape(like.shape[:-1]).to(self.thresholds.dtype)
        bucket = torch.bucketize(x.contiguous(), self.thresholds)  # strict: x == threshold stays below it
        action = self.actions[bucket]
        if y is not None:
            above = y.reshape(like.shape[:-1]).to(self.thresholds.dtype) > self.condition_threshold
            action = torch.where(above, self.condition_actions[bucket], action)
        onehot = nn.functional.one_hot(action, self.num_actions + 1)[..., : self.num_actions]
        return self.logit * onehot.to(like.dtype)


class PriorLogits(nn.Module):
    """``(h [*B, d], x[, y]) -> head(h) + prior(x[, y])``: the actor head with the rule's logits added."""

    def __init__(self, head: nn.Module, prior: ThresholdRulePrior) -> None:
        super().__init__()
        self.head = head
        self.prior = prior

    def forward(self, h: torch.Tensor, x: torch.Tensor, y: torch.Tensor | None = None) -> torch.Tensor:
        logits = self.head(h)
        return logits + self.prior(x, logits, y)


def prior_module(prior: ActionPriorConfig | None, num_actions: int) -> ThresholdRulePrior | None:
    """The prior of a validated config, or ``None`` when it has no key."""
    if prior is None or prior.key is None:
        return None
    cond = prior.condition
    row = None if cond.key is None else list(cond.actions)
    return ThresholdRulePrior(
        list(prior.thresholds), list(prior.actions), num_actions, prior.logit, cond.threshold, row
    )
