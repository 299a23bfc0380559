"""Imagined steps per second: :class:`RSSMWorldModelEnv` vs TorchRL's ``DreamerEnv`` at equal sizes, in one run.

Both envs: deterministic state 256, stochastic state 64, hidden 256, 5 discrete actions, a 2-hidden-layer reward
MLP of width 256, batch 64, horizon 15, the same kind of policy (an MLP of width 256 over ``[deter; stoch]`` that
samples a categorical action), untrained weights, ``torch.no_grad()``, one CPU thread. ``DreamerEnv`` is built the
way TorchRL's own helpers build it (``RSSMPrior`` in a ``SafeModule`` + reward ``SafeModule`` in a
``WorldModelWrapper``); it predicts no termination. Ours is measured twice: as used (done_mode="threshold", one
continuation-head MLP more per step) and with done_mode="never" (the same work as DreamerEnv). DreamerEnv is also
measured with a continuation MLP of the reward MLP's size added to its world model (``terminated = sigmoid(MLP) <
0.5``, written into its step output) -- the same work as ours as used. The four are interleaved round by round so
that load from other processes hits them alike; the median over rounds is reported, and each of ours is compared with
the DreamerEnv doing the same work (median of the per-round ratios).

Run::

    python -m freamer_rl.world_model.bench_imagination        # [--batch 64 --horizon 15 --rounds 20]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Composite, OneHot, Unbounded
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.modules import MLP, OneHotCategorical, ProbabilisticActor, SafeModule, SafeSequential, WorldModelWrapper
from torchrl.modules.models.model_based import RSSMPrior

from freamer_rl.world_model.imagination import RSSMWorldModelEnv
from freamer_rl.world_model.rssm import WorldModel

logger = logging.getLogger(__name__)

DETER, STOCH, HIDDEN, N_ACTIONS = 256, 64, 256, 5


def _policy(in_keys, latent_dim: int, distribution_class, spec) -> ProbabilisticActor:
    net = MLP(in_features=latent_dim, out_features=N_ACTIONS, num_cells=[HIDDEN, HIDDEN], activation_class=nn.ELU)
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=in_keys, out_keys=["logits"]),
        in_keys=["logits"],
        distribution_class=distribution_class,
        spec=spec,
        return_log_prob=True,
    )


def build_ours(batch: int) -> tuple[RSSMWorldModelEnv, ProbabilisticActor, TensorDict]:
    wm = WorldModel({"imu": 36, "hr_features": 16}, N_ACTIONS, deter_dim=DETER, stoch_dim=STOCH, hidden=HIDDEN)
    env = RSSMWorldModelEnv(wm, batch_size=(batch,))
    policy = _policy(["latent"], DETER + STOCH, torch.distributions.Categorical, env.action_spec)
    seeds = TensorDict({"deter": torch.randn(batch, DETER), "stoch": torch.randn(batch, STOCH)}, [batch])
    return env, policy, seeds


class ContinuationDone(nn.Module):
    """``[state; belief] -> terminated = sigmoid(MLP) < 0.5``: the work of our continuation head, for DreamerEnv."""

    def __init__(self) -> None:
        super().__init__()
        self.net = MLP(in_features=DETER + STOCH, out_features=1, num_cells=[HIDDEN, HIDDEN], activation_class=nn.ELU)

    def forward(self, state: torch.Tensor, belief: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        terminated = torch.sigmoid(self.net(torch.cat([state, belief], dim=-1))) < 0.5
        return terminated, terminated


def build_dreamer(batch: int, continuation: bool = False) -> tuple[DreamerEnv, ProbabilisticActor, TensorDict]:
    """TorchRL's DreamerEnv as TorchRL's helpers build it; ``continuation=True`` adds a continuation MLP of the
    reward MLP's size to its world model (writing ``terminated``/``done``), i.e. the work of our threshold mode."""
    action_spec = OneHot(N_ACTIONS, shape=(batch, N_ACTIONS))
    prior = RSSMPrior(action_spec, hidden_dim=HIDDEN, rnn_hidden_dim=DETER, state_dim=STOCH, action_dim=N_ACTIONS)
    modules = [SafeModule(prior, in_keys=["state", "belief", "action"], out_keys=["_", "_", "state", "belief"])]
    if continuation:
        modules.append(SafeModule(ContinuationDone(), in_keys=["state", "belief"], out_keys=["terminated", "done"]))
    transition = SafeSequential(*modules)
    reward = SafeModule(
        MLP(in_features=DETER + STOCH, out_features=1, num_cells=[HIDDEN, HIDDEN], activation_class=nn.ELU),
        in_keys=["state", "belief"],
        out_keys=["reward"],
    )
    env = DreamerEnv(
        WorldModelWrapper(transition, reward),
        prior_shape=torch.Size([STOCH]),
        belief_shape=torch.Size([DETER]),
        batch_size=torch.Size([batch]),
    )
    env.observation_spec = Composite(state=Unbounded((batch, STOCH)), belief=Unbounded((batch, DETER)), shape=(batch,))
    env.state_spec = env.observation_spec.clone()
    env.action_spec = action_spec
    env.reward_spec = Unbounded((batch, 1))
    policy = _policy(["state", "belief"], DETER + STOCH, OneHotCategorical, action_spec)
    seeds = TensorDict({"state": torch.randn(batch, STOCH), "belief": torch.randn(batch, DETER)}, [batch])
    return env, policy, seeds


def _rollouts_per_second(env, policy, seeds, horizon: int, n_rollouts: int, warmup: int = 0) -> float:
    """Imagined steps/s of ``n_rollouts`` rollouts ``[batch, horizon]`` (after ``warmup`` untimed ones)."""
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        for _ in range(warmup):
            out = env.rollout(
                horizon, policy, auto_reset=False, break_when_any_done=False, tensordict=env.reset(seeds.clone())
            )
            if tuple(out.shape) != (seeds.shape[0], horizon):
                raise RuntimeError(f"rollout shape {tuple(out.shape)} != {(seeds.shape[0], horizon)}")
        t0 = time.perf_counter()
        for _ in range(n_rollouts):
            env.rollout(
                horizon, policy, auto_reset=False, break_when_any_done=False, tensordict=env.reset(seeds.clone())
            )
        dt = time.perf_counter() - t0
    return n_rollouts * seeds.shape[0] * horizon / dt


def run(batch: int = 64, horizon: int = 15, rounds: int = 20, rollouts_per_round: int = 2, threads: int = 1) -> dict:
    """Measure the four configurations, interleaved round by round (load from other processes hits them alike).
    Returns the median (and mean) over rounds of imagined steps/s, the ratios to plain DreamerEnv, and the
    equal-work ratios (ours as used vs DreamerEnv with a continuation MLP; ours without continuation vs plain
    DreamerEnv), each the median of the per-round ratios."""
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    ours_env, ours_policy, ours_seeds = build_ours(batch)
    # same world model, done_mode="never": no continuation head evaluated -- the same work as DreamerEnv
    ours_never = RSSMWorldModelEnv(ours_env.world_model, batch_size=(batch,), done_mode="never")
    configs = {
        "rssm_world_model_env": (ours_env, ours_policy, ours_seeds),
        "rssm_world_model_env_no_continuation": (ours_never, ours_policy, ours_seeds),
        "torchrl_dreamer_env": build_dreamer(batch),
        "torchrl_dreamer_env_with_continuation": build_dreamer(batch, continuation=True),
    }
    for cfg in configs.values():
        _rollouts_per_second(*cfg, horizon, 1, warmup=2)
    res: dict[str, list[float]] = {k: [] for k in configs}
    for _ in range(rounds):
        for name, cfg in configs.items():
            res[name].append(_rollouts_per_second(*cfg, horizon, rollouts_per_round))
    median = {k: float(torch.tensor(v).median()) for k, v in res.items()}
    mean = {k: sum(v) / len(v) for k, v in res.items()}
    ref = median["torchrl_dreamer_env"]
    # paired per round: ours vs the DreamerEnv doing the same work (median of the per-round ratios)
    pairs = {
        "rssm_world_model_env": "torchrl_dreamer_env_with_continuation",
        "rssm_world_model_env_no_continuation": "torchrl_dreamer_env",
    }
    equal_work = {
        ours: round(float(torch.tensor([a / b for a, b in zip(res[ours], res[theirs])]).median()), 3)
        for ours, theirs in pairs.items()
    }
    return {
        "batch": batch,
        "horizon": horizon,
        "threads": threads,
        "rounds": rounds,
        "sizes": {"deter": DETER, "stoch": STOCH, "hidden": HIDDEN, "actions": N_ACTIONS},
        "median_steps_per_s": {k: round(v, 1) for k, v in median.items()},
        "mean_steps_per_s": {k: round(v, 1) for k, v in mean.items()},
        "median_ratio_vs_dreamer_env": {k: round(v / ref, 3) for k, v in median.items() if k != "torchrl_dreamer_env"},
        "equal_work_pairs": pairs,
        "equal_work_ratio": equal_work,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--horizon", type=int, default=15)
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--rollouts-per-round", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    result = run(args.batch, args.horizon, args.rounds, args.rollouts_per_round, args.threads)
    sys.stdout.write(json.dumps(result) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
