"""PPO heads built from the env's action spec: the actor's distribution follows the kind of action.

=====================================  ===============================================  ==========================
action spec                            actor head (on ``"hidden"`` ``[*B, d]``)          distribution
=====================================  ===============================================  ==========================
``Categorical(n)`` (integer index)     MLP -> ``"logits"`` ``[*B, n]``                  ``Categorical``
``OneHot(n)``                          MLP -> ``"logits"`` ``[*B, n]``                  ``OneHotCategorical``
``Bounded`` float box ``[*A]``         MLP -> ``"loc"``, ``"scale"`` ``[*B, *A]``       ``TanhNormal(low, high)``
``Unbounded`` float box ``[*A]``       MLP -> ``"loc"``, ``"scale"`` ``[*B, *A]``       ``IndependentNormal``
=====================================  ===============================================  ==========================

The critic is the same two-layer MLP with one output (``"state_value"``). Discrete heads start near uniform (output
gain 0.01, as PPO implementations do); continuous heads start with ``loc ~ 0`` and ``scale ~ softplus(1) ~ 1.3``.
"""

from __future__ import annotations

import torch
from tensordict.nn import NormalParamExtractor
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot, Unbounded
from torchrl.modules import IndependentNormal, OneHotCategorical, ProbabilisticActor, TanhNormal, ValueOperator

from freamer_rl.errors import EnvSetupError
from freamer_rl.layers.tdmodule import KeyedModule
from freamer_rl.model.action_prior import ActionPriorConfig, PriorLogits, prior_keys, prior_module

__all__ = ["build_actor", "build_critic", "action_kind", "mlp_head", "CRITIC_INPUTS"]

#: ``model.critic_input`` choices: the critic's gradient reaches the trunk (shared) or stops at its input (detached)
CRITIC_INPUTS = ("shared", "detached")


def mlp_head(in_dim: int, hidden: int, out_dim: int, out_gain: float) -> nn.Sequential:
    """Two-layer tanh head with orthogonal init; a small output gain keeps the initial policy near uniform."""
    net = nn.Sequential(nn.Linear(in_dim, hidden), nn.Tanh(), nn.Linear(hidden, out_dim))
    nn.init.orthogonal_(net[0].weight, gain=2**0.5)
    nn.init.zeros_(net[0].bias)
    nn.init.orthogonal_(net[2].weight, gain=out_gain)
    nn.init.zeros_(net[2].bias)
    return net


def action_kind(action_spec) -> str:
    """``"categorical"``, ``"one_hot"``, ``"bounded"`` or ``"unbounded"``; :class:`EnvSetupError` otherwise."""
    shape = tuple(action_spec.shape)
    if isinstance(action_spec, Categorical) and shape == ():
        return "categorical"
    if isinstance(action_spec, OneHot) and action_spec.ndim == 1:
        return "one_hot"
    if action_spec.dtype.is_floating_point and isinstance(action_spec, (Bounded, Unbounded)) and len(shape) >= 1:
        return "bounded" if isinstance(action_spec, Bounded) else "unbounded"
    raise EnvSetupError(
        f"action spec {type(action_spec).__name__}(shape={shape}, dtype={action_spec.dtype}) has no head: expected "
        "Categorical(n) with shape [] (e.g. GymEnv(..., categorical_action_encoding=True)), OneHot(n) with shape "
        "[n], or a float Bounded / Unbounded box with at least one dim (multi-discrete, composite and scalar-shaped "
        "box actions are not supported)"
    )


def build_actor(
    action_spec, in_dim: int, hidden: int, in_key="hidden", prior: ActionPriorConfig | None = None
) -> ProbabilisticActor:
    """The policy head for ``action_spec`` (table in the module docstring); writes ``action_log_prob``.

    ``prior`` (discrete actions only): a threshold rule on one observation added to the logits
    (:mod:`freamer_rl.model.action_prior`); the head then also reads ``prior.key`` (and ``prior.condition.key``)."""
    kind = action_kind(action_spec)
    if prior is not None and prior.key is not None and kind not in ("categorical", "one_hot"):
        raise EnvSetupError(f"action_prior: needs a discrete action (Categorical / OneHot), the env's is {kind}")
    if kind in ("categorical", "one_hot"):
        n = int(action_spec.space.n)
        net = mlp_head(in_dim, hidden, n, out_gain=0.01)
        dist = torch.distributions.Categorical if kind == "categorical" else OneHotCategorical
        rule = prior_module(prior, n)
        in_keys = [in_key, *prior_keys(prior)]
        return ProbabilisticActor(
            KeyedModule(net if rule is None else PriorLogits(net, rule), in_keys=in_keys, out_keys=["logits"]),
            in_keys=["logits"],
            out_keys=["action"],
            spec=action_spec,
            distribution_class=dist,
            return_log_prob=True,
        )
    shape = tuple(action_spec.shape)
    n = int(torch.Size(shape).numel())
    net = nn.Sequential(mlp_head(in_dim, hidden, 2 * n, out_gain=0.01), _Unflatten(shape), NormalParamExtractor())
    # every action dim is one event: the log-prob sums over the whole action, whatever its shape
    if kind == "bounded":
        dist = TanhNormal
        kwargs = {"low": action_spec.space.low, "high": action_spec.space.high, "event_dims": len(shape)}
    else:
        dist = IndependentNormal
        kwargs = {"event_dim": len(shape)}
    return ProbabilisticActor(
        KeyedModule(net, in_keys=[in_key], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        out_keys=["action"],
        spec=action_spec,
        distribution_class=dist,
        distribution_kwargs=kwargs,
        return_log_prob=True,
    )


def build_critic(in_dim: int, hidden: int, in_key="hidden", *, detached: bool = False) -> ValueOperator:
    """``V(s)``: the same MLP with one output, written to ``"state_value"``; ``detached``: through a stop-gradient
    on its input (the value loss trains the head only; the same parameters and state-dict keys)."""
    net = mlp_head(in_dim, hidden, 1, out_gain=1.0)
    return ValueOperator(_DetachedInput(*net) if detached else net, in_keys=[in_key])


class _DetachedInput(nn.Sequential):
    """An ``nn.Sequential`` that reads its input through ``detach()`` (its layers and keys unchanged)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.detach())


class _Unflatten(nn.Module):
    """``[*B, 2 * prod(A)]`` -> ``[*B, *A[:-1], 2 * A[-1]]`` so NormalParamExtractor splits loc/scale per action."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__()
        self.shape = shape

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if len(self.shape) <= 1:
            return x
        return x.reshape(*x.shape[:-1], *self.shape[:-1], 2 * self.shape[-1])
