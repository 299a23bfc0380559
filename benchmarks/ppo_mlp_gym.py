"""TorchRL PPO-MLP on a gymnasium env: the baseline a TorchRL user writes first, with the recipe's PPO settings.

Separate MLP 64x64 tanh actor and critic on ``"observation"`` (TorchRL's ``MLP``), a categorical head for discrete
actions or a ``TanhNormal`` head for a Box, ``ClipPPOLoss`` + ``GAE``, Adam, gradient-norm clipping, and the batch
layout of the TorchRL PPO tutorial (flattened, shuffled frames: fine without memory). Everything that is not the
model -- envs, frames per batch, epochs, minibatch size, learning rate, gamma, lambda, clip, entropy and critic
coefficients -- comes from the same recipe as the FreamerV1 run, so the two differ only in the network.

    python benchmarks/ppo_mlp_gym.py recipes/gym/cartpole.yaml --seed 0 --frames 100000
"""

from __future__ import annotations

import argparse
import json
import time
from collections import deque

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.envs import Compose, RewardSum, SerialEnv, StepCounter, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from freamer_rl.trainers.registry import load_config
from freamer_rl_envs.gym import make_gym_env


def _actor(env, hidden: int) -> ProbabilisticActor:
    obs_dim = env.observation_spec["observation"].shape[-1]
    spec = env.action_spec
    if spec.dtype.is_floating_point:
        n = spec.shape[-1]
        net = nn.Sequential(MLP(in_features=obs_dim, out_features=2 * n, num_cells=[hidden, hidden],
                                activation_class=nn.Tanh), NormalParamExtractor())
        return ProbabilisticActor(
            TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]), in_keys=["loc", "scale"],
            spec=spec, distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high}, return_log_prob=True,
        )
    net = MLP(in_features=obs_dim, out_features=spec.space.n, num_cells=[hidden, hidden], activation_class=nn.Tanh)
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["logits"]), in_keys=["logits"], spec=spec,
        distribution_class=torch.distributions.Categorical, return_log_prob=True,
    )


def train_ppo_mlp_gym(recipe: str, seed: int, total_frames: int, *, overrides: list[str] | None = None,
                      hidden: int = 64, window: int = 100) -> dict:
    """Train the baseline; returns a summary with per-batch ``rows`` (frames, episodes, return_mean).

    ``overrides`` are the dotted recipe overrides of the FreamerV1 run it stands beside (only env and ppo are read).
    """
    cfg = load_config(recipe, overrides or [])
    p, env_id, n_envs = cfg.ppo, cfg.env.id, cfg.env.num_envs
    torch.manual_seed(seed)
    torch.set_num_threads(1)

    def env_fn():
        env = TransformedEnv(SerialEnv(n_envs, lambda: make_gym_env(env_id)), Compose(StepCounter(), RewardSum()))
        env.set_seed(seed)
        return env

    probe = make_gym_env(env_id)
    actor = _actor(probe, hidden)
    critic = ValueOperator(MLP(in_features=probe.observation_spec["observation"].shape[-1], out_features=1,
                               num_cells=[hidden, hidden], activation_class=nn.Tanh), in_keys=["observation"])
    probe.close()
    loss = ClipPPOLoss(actor, critic, clip_epsilon=p.clip_epsilon, entropy_coeff=p.entropy_coeff,
                       critic_coeff=p.critic_coeff, loss_critic_type="l2", normalize_advantage=p.normalize_advantage)
    gae = GAE(gamma=p.gamma, lmbda=p.gae_lambda, value_network=critic, average_gae=False)
    opt = torch.optim.Adam(loss.parameters(), lr=p.lr, eps=p.adam_eps)
    collector = Collector(env_fn, actor, frames_per_batch=p.frames_per_batch, total_frames=total_frames,
                          auto_register_policy_transforms=False)
    rb = ReplayBuffer(storage=LazyTensorStorage(p.frames_per_batch), sampler=SamplerWithoutReplacement(),
                      batch_size=p.minibatch_size)
    rets: deque = deque(maxlen=window)
    rows, frames, episodes = [], 0, 0
    t0 = time.perf_counter()
    for data in collector:
        frames += data.numel()
        nxt = data["next"]
        ended = nxt["episode_reward"][nxt["done"]].tolist()
        episodes += len(ended)
        rets.extend(ended)
        with torch.no_grad():
            gae(data)
        rb.empty()
        rb.extend(data.reshape(-1))
        for _ in range(p.epochs * max(1, p.frames_per_batch // p.minibatch_size)):
            ld = loss(rb.sample())
            total = ld["loss_objective"] + ld["loss_critic"] + ld.get("loss_entropy", 0.0)
            opt.zero_grad()
            total.backward()
            torch.nn.utils.clip_grad_norm_(loss.parameters(), p.max_grad_norm)
            opt.step()
        collector.update_policy_weights_()
        rows.append({"frames": frames, "episodes": episodes, "success_rate": float("nan"),
                     "return_mean": sum(rets) / len(rets) if rets else float("nan")})
    wall = time.perf_counter() - t0
    collector.shutdown()
    return {"method": "ppo_mlp", "env": env_id, "seed": seed, "frames": frames, "episodes": episodes,
            "final_return_mean": rows[-1]["return_mean"] if rows else float("nan"), "final_success_rate": float("nan"),
            "wall_time_s": wall, "fps": frames / wall, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recipe")
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("overrides", nargs="*", help="dotted recipe overrides (env.*, ppo.*)")
    args = ap.parse_intermixed_args()
    out = train_ppo_mlp_gym(args.recipe, args.seed, args.frames, overrides=args.overrides)
    out.pop("rows")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
