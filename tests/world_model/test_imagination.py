"""RSSM world-model env (TorchRL ModelBasedEnvBase) and policy optimisation in imagination (Appendix J.4)."""

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.utils import check_env_specs
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator

from freamer_rl.world_model import ImaginationPPO, RSSMWorldModelEnv, WorldModel, valid_imagination_mask
from freamer_rl.world_model.bench_imagination import ContinuationDone, build_dreamer, run

OBS_DIMS = {"imu": 6, "hr_features": 3}
N_ACT, D, S = 5, 24, 8
BATCH_SHAPES = [(), (4,), (3, 2)]


def small_wm() -> WorldModel:
    return WorldModel(OBS_DIMS, N_ACT, embed_dim=16, deter_dim=D, stoch_dim=S, hidden=32)


def latents(shape) -> TensorDict:
    return TensorDict({"deter": torch.randn(*shape, D), "stoch": torch.randn(*shape, S)}, batch_size=shape)


def actor_critic(env):
    policy = ProbabilisticActor(
        TensorDictModule(
            MLP(in_features=D + S, out_features=N_ACT, num_cells=[32]), in_keys=["latent"], out_keys=["logits"]
        ),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
        spec=env.action_spec,
    )
    value = ValueOperator(MLP(in_features=D + S, out_features=1, num_cells=[32]), in_keys=["latent"])
    return policy, value


@pytest.mark.parametrize("env_batch", [(), (4,)])
def test_check_env_specs(env_batch):
    env = RSSMWorldModelEnv(small_wm(), batch_size=env_batch)
    check_env_specs(env, tensordict=env.reset(latents(env_batch)))
    assert env.action_spec.n == N_ACT
    assert env.observation_spec["latent"].shape == (*env_batch, D + S)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_rollout_shape_h15(shape):
    env = RSSMWorldModelEnv(small_wm())
    policy, _ = actor_critic(env)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        traj = env.rollout(15, policy, auto_reset=False, tensordict=env.reset(latents(shape)))
    assert traj.batch_size == (*shape, 15)
    assert traj["next", "latent"].shape == (*shape, 15, D + S)
    assert traj["next", "reward"].shape == (*shape, 15, 1)
    assert traj["action"].shape == (*shape, 15)
    # the step is Markov in (deter, stoch): next state of step t is the state of step t+1
    torch.testing.assert_close(traj["next", "deter"][..., :-1, :], traj["deter"][..., 1:, :])
    torch.testing.assert_close(traj["latent"], torch.cat([traj["deter"], traj["stoch"]], -1))


def test_reset_without_latents_raises():
    env = RSSMWorldModelEnv(small_wm())
    with pytest.raises(ValueError, match="posterior latents"):
        env.reset()
    with pytest.raises(ValueError, match="posterior latents"):
        env.reset(TensorDict({"deter": torch.zeros(2, D)}, [2]))
    with pytest.raises(ValueError, match="stoch"):
        env.reset(TensorDict({"deter": torch.zeros(2, D), "stoch": torch.zeros(2, S + 1)}, [2]))


def test_done_modes_and_fixed_horizon():
    wm = small_wm()
    with torch.no_grad():  # continuation prob ~ 0: every imagined step terminates
        last = wm.continue_head[-1]
        last.weight.zero_()
        last.bias.fill_(-20.0)
    seeds = latents((6,))
    for mode, expect in (("threshold", True), ("sample", True), ("never", False)):
        env = RSSMWorldModelEnv(wm, done_mode=mode)
        traj = env.rollout(15, auto_reset=False, tensordict=env.reset(seeds))
        assert traj.batch_size == (6, 15)  # a predicted termination never shortens imagination
        assert bool(traj["next", "terminated"].all()) is expect
        assert not traj["next", "truncated"].any()
        mask = valid_imagination_mask(traj)
        assert mask[:, 0].all()
        assert bool(mask[:, 1:].any()) is (not expect)
    with pytest.raises(ValueError, match="done_mode"):
        RSSMWorldModelEnv(wm, done_mode="maybe")


def test_world_model_latents_seed_the_env():
    wm = small_wm()
    batch = TensorDict(
        {
            "imu": torch.randn(2, 5, 6),
            "hr_features": torch.randn(2, 5, 3),
            "action": torch.randint(0, N_ACT, (2, 5)),
            "next": {
                "imu": torch.randn(2, 5, 6),
                "hr_features": torch.randn(2, 5, 3),
                "reward": torch.randn(2, 5, 1),
                "done": torch.zeros(2, 5, 1, dtype=torch.bool),
                "terminated": torch.zeros(2, 5, 1, dtype=torch.bool),
            },
        },
        [2, 5],
    )
    _, seeds = wm.loss(batch, return_latents=True)
    env = RSSMWorldModelEnv(wm)
    traj = env.rollout(15, auto_reset=False, tensordict=env.reset(seeds))
    assert traj.batch_size == (12, 15)


@pytest.mark.parametrize("lambda_return", [False, True])
def test_imagination_update(lambda_return):
    env = RSSMWorldModelEnv(small_wm())
    policy, value = actor_critic(env)
    before = [p.clone() for p in policy.parameters()]
    wm_before = [p.clone() for p in env.world_model.parameters()]
    algo = ImaginationPPO(
        env, policy, value, epochs=2, num_minibatches=2, lr=1e-3, lambda_return_actor_critic=lambda_return
    )
    metrics = algo.update(latents((16,)))
    assert all(math.isfinite(v) for v in metrics.values()), metrics
    loss_key = "loss_actor" if lambda_return else "loss_objective"
    for k in (loss_key, "loss_critic", "loss_entropy", "entropy", "imagined_reward", "valid_fraction"):
        assert k in metrics, k
    assert any(not torch.equal(a, b) for a, b in zip(before, policy.parameters()))
    # the world model is frozen during policy learning
    assert all(torch.equal(a, b) for a, b in zip(wm_before, env.world_model.parameters()))


def test_bench_imagination_smoke():
    res = run(batch=4, horizon=3, rounds=1, rollouts_per_round=1)
    assert set(res["median_steps_per_s"]) == {
        "rssm_world_model_env",
        "rssm_world_model_env_no_continuation",
        "torchrl_dreamer_env",
        "torchrl_dreamer_env_with_continuation",
    }
    assert all(v > 0 for v in res["median_steps_per_s"].values())
    assert set(res["equal_work_ratio"]) == {"rssm_world_model_env", "rssm_world_model_env_no_continuation"}
    # one round: each ratio is ours over the DreamerEnv doing the same work (rates rounded to 0.1 step/s)
    rate = res["median_steps_per_s"]
    for ours, theirs in res["equal_work_pairs"].items():
        assert res["equal_work_ratio"][ours] == pytest.approx(rate[ours] / rate[theirs], rel=0.01, abs=2e-3), ours


def test_bench_dreamer_continuation_writes_termination():
    """The equal-work DreamerEnv really evaluates its continuation MLP: its rollout carries the predicted flag."""
    env, policy, seeds = build_dreamer(4, continuation=True)
    cont = next(m for m in env.world_model.modules() if isinstance(m, ContinuationDone))
    with torch.no_grad():
        torch.nn.init.constant_(cont.net[-1].bias, -5.0)  # sigmoid(-5 + small) < 0.5 -> terminated everywhere
        for p in cont.net[-1].parameters():
            if p.ndim > 1:
                p.zero_()
        traj = env.rollout(3, policy, auto_reset=False, break_when_any_done=False, tensordict=env.reset(seeds))
    assert traj.shape == (4, 3)  # fixed-horizon imagination, as the benchmark runs it
    assert traj["next", "terminated"].all() and traj["next", "done"].all()
