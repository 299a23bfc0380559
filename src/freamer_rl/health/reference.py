"""Fixed and hand-written reference policies of the health env: the yardstick for the imagination-trained policy.

Every reference policy is a :class:`~tensordict.nn.TensorDictModuleBase` that reads the real env's observations and
writes ``"action"`` (int64 ``[*B]``); :func:`evaluate_reference` rolls it with exactly the protocol of
:func:`freamer_rl.health.evaluation.evaluate_policy` (a fresh env of ``eval.num_envs`` episodes, env seed
``eval.seed``, the evaluation subjects ``eval.subjects`` when set, ``env.episode_length`` steps, metrics read at
each env's first ``done``), so the numbers are directly comparable with a run's ``eval_return_mean``.

Policies (:data:`REFERENCE_POLICIES`):

* ``"continue"``, ``"rest"``, ``"increase"``, ``"change"``, ``"alert"``: always that action;
* ``"random"``: uniform over the 5 actions (its own seeded generator);
* ``"hr_threshold"``: :class:`HeartRateThresholdPolicy` -- Rest while the heart rate is above ``rest_above`` bpm
  (default 150, 10 bpm below the danger zone), Alert above ``alert_above`` (default 185), else Continue;
* ``"hr_controller"``: :class:`HeartRateControllerPolicy` -- the rule plus Increase below ``increase_below``
  (default 145 bpm) while the env's ``"level"`` is below plan: it brings the intensity back after a Rest, which the
  rule never does (the rule's level stays down until the next activity segment);
* ``"oracle"``: :class:`~freamer_rl.health.oracle.OraclePlanner` -- receding-horizon lookahead on the env's own
  simulator (privileged: it reads the env's state; the ceiling of the table).

:func:`ceiling_table` evaluates several of them on the same episodes and reports each mean return with a 95 %
bootstrap interval over the episodes and as a fraction of the oracle's (paired bootstrap: the episodes are the same
for every policy); :func:`format_ceiling_table` renders it as markdown.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from freamer_rl.health.config import ACTION_NAMES, REFERENCE_POLICIES
from freamer_rl.health.evaluation import make_eval_env, rollout_metrics
from freamer_rl.health.oracle import ORACLE_DEFAULTS, OraclePlanner

logger = logging.getLogger(__name__)

__all__ = [
    "ACTION_NAMES",
    "REFERENCE_POLICIES",
    "ConstantActionPolicy",
    "UniformRandomPolicy",
    "HeartRateThresholdPolicy",
    "HeartRateControllerPolicy",
    "make_reference_policy",
    "reference_rollout",
    "episode_returns",
    "evaluate_reference",
    "reference_summary",
    "bootstrap_mean_ci",
    "CEILING_POLICIES",
    "ceiling_table",
    "format_ceiling_table",
]

#: the rows of the ceiling table (issue 22), the oracle first: every other row is read as a fraction of it
CEILING_POLICIES: tuple[str, ...] = ("oracle", "hr_controller", "hr_threshold", "continue", "rest", "random")


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


class HeartRateControllerPolicy(HeartRateThresholdPolicy):
    """:class:`HeartRateThresholdPolicy` plus **Increase** where ``HR < increase_below`` and ``"level"`` ``[*B, 1]``
    is below 1 (below plan), so the intensity comes back once the heart rate has; never above plan. Writes
    ``"action"`` int64 ``[*B]``."""

    def __init__(
        self,
        rest_above: float = 150.0,
        alert_above: float = 185.0,
        increase_below: float = 145.0,
        hr_key: Any = "heart_rate",
        level_key: Any = "level",
    ) -> None:
        super().__init__(rest_above, alert_above, hr_key)
        if not increase_below <= rest_above:
            raise ValueError(f"increase_below ({increase_below}) must be <= rest_above ({rest_above})")
        self.increase_below = float(increase_below)
        self.level_key = level_key
        self.in_keys = [hr_key, level_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        below_plan = tensordict.get(self.level_key).reshape(tensordict.batch_size) < 1.0
        slow = (tensordict.get(self.hr_key).reshape(tensordict.batch_size) < self.increase_below) & below_plan
        action = super().forward(tensordict).get("action")
        tensordict.set("action", action.masked_fill(slow, ACTION_NAMES.index("increase")))
        return tensordict


def make_reference_policy(name: str, *, seed: int = 0, **kwargs: Any) -> TensorDictModuleBase:
    """One of :data:`REFERENCE_POLICIES`. ``kwargs`` go to :class:`HeartRateThresholdPolicy` (``"hr_threshold"``),
    :class:`HeartRateControllerPolicy` (``"hr_controller"``)
    or to :class:`~freamer_rl.health.oracle.OraclePlanner` (``"oracle"``: ``horizon``, ``depth``,
    ``noise_samples``, and ``tails``, names of reference policies, default ``("continue", "hr_threshold")``)."""
    if name in ACTION_NAMES:
        return ConstantActionPolicy(ACTION_NAMES.index(name))
    if name == "random":
        return UniformRandomPolicy(seed=seed)
    if name == "hr_threshold":
        return HeartRateThresholdPolicy(**kwargs)
    if name == "hr_controller":
        return HeartRateControllerPolicy(**kwargs)
    if name == "oracle":
        options = {**ORACLE_DEFAULTS, "seed": seed, **kwargs}
        tails = options.pop("tails", ("continue", "hr_threshold"))
        if "oracle" in tails:
            raise ValueError("oracle: tails must be fixed reference policies, not 'oracle'")
        modules = [make_reference_policy(t, seed=seed) for t in tails]
        return OraclePlanner(modules, num_actions=len(ACTION_NAMES), **options)
    raise ValueError(f"unknown reference policy {name!r}; known: {', '.join(REFERENCE_POLICIES)}")


@torch.no_grad()
def reference_rollout(
    cfg: Any, policy: str | TensorDictModuleBase, *, num_envs: int | None = None, seed: int | None = None
) -> TensorDictBase:
    """The evaluation protocol's rollout ``[num_envs, env.episode_length]`` of a reference policy: a fresh env of
    ``num_envs`` (default ``eval.num_envs``) episodes from env ``seed`` (default ``eval.seed``) over the evaluation
    subjects (``eval.subjects``, else ``env.subjects``), built by :func:`freamer_rl.health.evaluation.make_eval_env`
    as :func:`freamer_rl.health.evaluation.evaluate_policy` builds a trained policy's. An
    :class:`~freamer_rl.health.oracle.OraclePlanner` is bound to that env for the rollout."""
    module = make_reference_policy(policy) if isinstance(policy, str) else policy
    env = make_eval_env(cfg, num_envs=num_envs, seed=seed)
    if isinstance(module, OraclePlanner):
        module.bind(env)
    try:
        return env.rollout(cfg.env.episode_length, module, break_when_any_done=False)
    finally:
        if isinstance(module, OraclePlanner):
            module.bind(None)
        env.close()


def episode_returns(traj: TensorDictBase) -> torch.Tensor:
    """float32 ``[n]``: each env's episode return, read at its first ``("next", "done")`` (as
    :func:`~freamer_rl.health.evaluation.rollout_metrics`, which also checks that every env finished)."""
    rollout_metrics(traj)  # the same checks and the same reading
    done = traj.get(("next", "done")).reshape(traj.shape[0], -1)
    first = done.float().argmax(dim=-1)
    return traj.get(("next", "episode", "return"))[torch.arange(traj.shape[0]), first].float().reshape(-1)


def evaluate_reference(
    cfg: Any, policy: str | TensorDictModuleBase, *, num_envs: int | None = None, seed: int | None = None
) -> dict[str, float]:
    """Real-env metrics of a reference policy under the evaluation protocol of a
    :class:`~freamer_rl.health.config.HealthConfig` ``cfg`` (:func:`reference_rollout`): ``return_mean``,
    ``return_std``, ``violations_mean``, ``length_mean``, ``episodes``."""
    return rollout_metrics(reference_rollout(cfg, policy, num_envs=num_envs, seed=seed))


def reference_summary(cfg: Any, policies: Sequence[str], agent_return: float) -> dict[str, float]:
    """The reference policies' mean return on the evaluation episodes of ``cfg`` (:func:`evaluate_reference`) as
    ``eval_ref_<name>_return``, and the learned policy's ``agent_return`` (the same episodes) as a fraction of two of
    them: ``eval_fraction_of_oracle`` (when ``"oracle"`` is listed) and ``eval_vs_hr_threshold`` (``"hr_threshold"``)."""
    out: dict[str, float] = {}
    for name in policies:
        start = time.perf_counter()
        ret = float(evaluate_reference(cfg, name)["return_mean"])
        logger.info("reference %s: return %.2f (%.1f s)", name, ret, time.perf_counter() - start)
        out[f"eval_ref_{name}_return"] = ret
    for name, key in (("oracle", "eval_fraction_of_oracle"), ("hr_threshold", "eval_vs_hr_threshold")):
        ref = out.get(f"eval_ref_{name}_return")
        if ref is not None:
            # a reference return of 0 has no fraction: NaN, never a silent 0 or inf
            out[key] = agent_return / ref if ref != 0 else float("nan")
    return out


def bootstrap_mean_ci(
    values: Sequence[float] | np.ndarray,
    *,
    reference: Sequence[float] | np.ndarray | None = None,
    resamples: int = 10_000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Percentile-bootstrap ``(estimate, low, high)`` of ``mean(values)``, or, with ``reference`` (paired: the same
    episodes), of ``mean(values) / mean(reference)``; episodes are resampled with replacement, jointly for the pair."""
    x = np.asarray(values, dtype=np.float64)
    y = None if reference is None else np.asarray(reference, dtype=np.float64)
    if x.ndim != 1 or x.size == 0 or (y is not None and y.shape != x.shape):
        raise ValueError(f"bootstrap_mean_ci: values {x.shape} and reference must be equal non-empty 1-D arrays")
    if not 0.0 < confidence < 1.0 or resamples < 1:
        raise ValueError(f"bootstrap_mean_ci: confidence in (0, 1) and resamples >= 1, got {confidence}, {resamples}")
    idx = np.random.default_rng(seed).integers(0, x.size, size=(int(resamples), x.size))
    stat = x[idx].mean(1) if y is None else x[idx].mean(1) / y[idx].mean(1)
    estimate = float(x.mean() if y is None else x.mean() / y.mean())
    tail = 50.0 * (1.0 - confidence)
    low, high = np.percentile(stat, [tail, 100.0 - tail])
    return estimate, float(low), float(high)


def ceiling_table(
    cfg: Any,
    policies: Sequence[str] = CEILING_POLICIES,
    *,
    num_envs: int | None = None,
    seed: int | None = None,
    resamples: int = 10_000,
    **oracle: Any,
) -> list[dict[str, Any]]:
    """The ceiling table (issue 22): every policy of ``policies`` (names of :data:`REFERENCE_POLICIES`; ``"oracle"``
    must be among them) on the same evaluation episodes (:func:`reference_rollout`), one row each: ``policy``,
    ``return_mean`` with its 95 % bootstrap interval ``return_low`` / ``return_high`` over the episodes,
    ``fraction_of_oracle`` = mean / oracle's mean with a paired 95 % interval ``fraction_low`` / ``fraction_high``,
    ``violations_mean``, ``length_mean``, ``episodes`` and ``seconds`` (wall time of the rollout). ``oracle``
    keyword arguments go to the planner (:func:`make_reference_policy`)."""
    if "oracle" not in policies:
        raise ValueError(f"ceiling_table: policies must include 'oracle' (the denominator), got {list(policies)}")
    returns: dict[str, np.ndarray] = {}
    rows: list[dict[str, Any]] = []
    for name in policies:
        module = make_reference_policy(name, **(oracle if name == "oracle" else {}))
        start = time.perf_counter()
        traj = reference_rollout(cfg, module, num_envs=num_envs, seed=seed)
        seconds = time.perf_counter() - start
        metrics = rollout_metrics(traj)
        returns[name] = episode_returns(traj).numpy()
        mean, low, high = bootstrap_mean_ci(returns[name], resamples=resamples)
        rows.append(
            {
                "policy": name,
                "return_mean": mean,
                "return_low": low,
                "return_high": high,
                "violations_mean": metrics["violations_mean"],
                "length_mean": metrics["length_mean"],
                "episodes": metrics["episodes"],
                "seconds": seconds,
            }
        )
        logger.info("ceiling table: %s return %.2f [%.2f, %.2f] in %.1f s", name, mean, low, high, seconds)
    for row in rows:
        frac, low, high = bootstrap_mean_ci(returns[row["policy"]], reference=returns["oracle"], resamples=resamples)
        row.update(fraction_of_oracle=frac, fraction_low=low, fraction_high=high)
    return rows


def format_ceiling_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown of :func:`ceiling_table`'s rows: return mean [95 % CI], fraction of the oracle [95 % CI],
    violations, seconds."""
    lines = [
        "| policy | return (95% CI) | fraction of oracle (95% CI) | violations / episode | episodes | seconds |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['policy']} | {r['return_mean']:.1f} [{r['return_low']:.1f}, {r['return_high']:.1f}] | "
            f"{r['fraction_of_oracle']:.3f} [{r['fraction_low']:.3f}, {r['fraction_high']:.3f}] | "
            f"{r['violations_mean']:.2f} | {r['episodes']} | {r['seconds']:.1f} |"
        )
    return "\n".join(lines)
