"""TorchRL PPO-MLP baseline on MiniGrid: what a TorchRL user would write first.

FlatObsWrapper observations (2835 floats), separate MLP 256x2 tanh actor and critic, ClipPPOLoss (clip 0.2,
entropy 0.01), GAE(0.99, 0.95), Adam 3e-4, 2048 frames per batch, 4 epochs of minibatch 256, grad-norm clip 0.5,
one env, one thread (../shared/notes/baselines-measured.md).

``--novelty W`` (W > 0) adds a count-based NovelD bonus: a ``NoveltyBonus`` transform on the env writes
``("next", "novelty_bonus")``, a ``RewardMixer`` adds ``W * bonus`` to the env reward as ``("next", "shaped_reward")``
and GAE reads that key; success and returns are still measured on the env reward.

    python benchmarks/ppo_mlp_baseline.py --env MiniGrid-MultiRoom-N2-S4-v0 --frames 100000 --seed 0
    python benchmarks/ppo_mlp_baseline.py --env MiniGrid-MultiRoom-N2-S4-v0 --frames 100000 --novelty 0.1
"""

from __future__ import annotations

import argparse
import json
import time
from collections import deque

import gymnasium as gym
import torch
from minigrid.wrappers import FlatObsWrapper
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.envs import Compose, DTypeCastTransform, GymWrapper, RewardSum, StepCounter, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from freamer_rl.machinery.exploration import NoveltyBonus
from freamer_rl.machinery.reward_mixer import RewardMixer


def make_flat_env(env_id: str, seed: int, novelty_alpha: float | None = None):
    """FlatObs MiniGrid env; ``novelty_alpha`` given: with the NovelD count bonus ``("next", "novelty_bonus")``."""
    transforms = Compose(DTypeCastTransform(torch.uint8, torch.float32, in_keys=["observation"]), StepCounter(),
                         RewardSum())  # fmt: skip
    if novelty_alpha is not None:
        # a 16-byte digest of each 2835-float observation keeps the count table small over long runs
        transforms.append(NoveltyBonus(in_keys=["observation"], alpha=novelty_alpha, digest_size=16))
    env = TransformedEnv(GymWrapper(FlatObsWrapper(gym.make(env_id)), categorical_action_encoding=True), transforms)
    env.set_seed(seed)
    return env


def train_ppo_mlp(env_id: str, seed: int, total_frames: int, *, frames_per_batch: int = 2048, window: int = 100,
                  progress=None, novelty_weight: float = 0.0, novelty_alpha: float = 0.5) -> dict:
    """Train the baseline; returns a summary with per-batch ``rows`` (frames, episodes, success_rate, return).

    ``novelty_weight > 0`` trains PPO on ``reward + novelty_weight * novelty_bonus`` (``"method": "ppo_mlp_novelty"``).
    """
    torch.manual_seed(seed)
    torch.set_num_threads(1)
    novelty = novelty_weight > 0
    alpha = novelty_alpha if novelty else None
    env_fn = lambda: make_flat_env(env_id, seed, alpha)  # noqa: E731 (direct backend: no pickling)
    probe = env_fn()
    obs_dim = probe.observation_spec["observation"].shape[-1]
    n_act = probe.action_spec.space.n
    actor = ProbabilisticActor(
        TensorDictModule(MLP(in_features=obs_dim, out_features=n_act, num_cells=[256, 256], activation_class=nn.Tanh),
                         in_keys=["observation"], out_keys=["logits"]),
        in_keys=["logits"], spec=probe.action_spec, distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )
    critic = ValueOperator(MLP(in_features=obs_dim, out_features=1, num_cells=[256, 256], activation_class=nn.Tanh),
                           in_keys=["observation"])
    probe.close()
    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=0.01, critic_coeff=0.5, loss_critic_type="l2")
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
    mixer = None
    if novelty:  # PPO learns from the shaped reward; success and returns below read the env reward
        mixer = RewardMixer({"novelty": (("next", "novelty_bonus"), novelty_weight)}, adaptive=False)
        gae.set_keys(reward="shaped_reward")
    opt = torch.optim.Adam(loss.parameters(), lr=3e-4)
    collector = Collector(env_fn, actor, frames_per_batch=frames_per_batch, total_frames=total_frames,
                          auto_register_policy_transforms=False)
    rb = ReplayBuffer(storage=LazyTensorStorage(frames_per_batch), sampler=SamplerWithoutReplacement(), batch_size=256)
    succ, rets = deque(maxlen=window), deque(maxlen=window)
    rows, frames, episodes = [], 0, 0
    first95 = (None, None)
    t0 = time.perf_counter()
    for data in collector:
        frames += data.numel()
        nxt = data["next"]
        done = nxt["done"].reshape(-1)
        for i in done.nonzero().flatten().tolist():
            episodes += 1
            s = bool(nxt["terminated"].reshape(-1)[i]) and float(nxt["reward"].reshape(-1)[i]) > 0
            succ.append(float(s))
            rets.append(float(nxt["episode_reward"].reshape(-1)[i]))
            if first95[0] is None and len(succ) == window and sum(succ) / window >= 0.95:
                first95 = (frames - data.numel() + i + 1, episodes)
        if mixer is not None:
            mixer(data, success_rate=sum(succ) / len(succ) if succ else float("nan"))
        with torch.no_grad():
            gae(data)
        rb.extend(data.reshape(-1))
        for _ in range(4):
            for _ in range(frames_per_batch // 256):
                mb = rb.sample()
                ld = loss(mb)
                total = ld["loss_objective"] + ld["loss_critic"] + ld["loss_entropy"]
                opt.zero_grad()
                total.backward()
                torch.nn.utils.clip_grad_norm_(loss.parameters(), 0.5)
                opt.step()
        collector.update_policy_weights_()
        rows.append({"frames": frames, "episodes": episodes,
                     "success_rate": sum(succ) / len(succ) if succ else float("nan"),
                     "return_mean": sum(rets) / len(rets) if rets else float("nan")})
        if progress is not None:
            progress(rows[-1])
    wall = time.perf_counter() - t0
    collector.shutdown()
    return {
        "method": "ppo_mlp_novelty" if novelty else "ppo_mlp", "env": env_id, "seed": seed, "frames": frames,
        "episodes": episodes,
        "final_success_rate": rows[-1]["success_rate"] if rows else float("nan"),
        "frames_to_95": first95[0], "episodes_to_95": first95[1], "wall_time_s": wall, "fps": frames / wall,
        "rows": rows,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="MiniGrid-MultiRoom-N2-S4-v0")
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--novelty", type=float, default=0.0, metavar="W",
                    help="weight of the NovelD count bonus (0: off)")
    args = ap.parse_args()
    out = train_ppo_mlp(args.env, args.seed, args.frames, novelty_weight=args.novelty)
    out.pop("rows")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
