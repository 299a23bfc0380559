"""Success replay with the off-policy correction (freamer_rl.machinery.success_buffer): the step mask, the FIFO buffer,
V-trace targets and weights, the weighted PPO reduction, and one mixed minibatch through the real tiny FreamerV1."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ProbabilisticActor, ValueOperator, set_recurrent_mode
from torchrl.objectives import ClipPPOLoss

from freamer_rl.machinery.success_buffer import (
    LOSS_MASK_KEY,
    LOSS_WEIGHT_KEY,
    REPLAY_MASK_KEY,
    SuccessBuffer,
    correct_replay,
    mix_minibatch,
    replay_sequences,
    success_step_mask,
    weighted_ppo_loss,
)
from freamer_rl.run import env_registry
from freamer_rl.run.sequences import split_sequences
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config

torch.set_num_threads(1)
TINY = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"
MINIGRID_SUCCESS = env_registry.get_adapter("minigrid").success  # terminated with a positive reward


def _flags(rows):
    return torch.tensor(rows, dtype=torch.bool).unsqueeze(-1)


def hand_batch():
    """Four envs x 6 steps; the expected success mask is in the comments (1 = step of a successful episode)."""
    is_init = [
        [0, 0, 0, 1, 0, 0],  # episode from an earlier batch ends in success at t=2 -> 1 1 1 0 0 0
        [1, 0, 1, 0, 1, 0],  # truncated (failure) at 1, successes at 3 and 5 -> 0 0 1 1 1 1
        [1, 0, 0, 1, 0, 0],  # terminated without reward (failure) at 2, then running -> 0 0 0 0 0 0
        [0, 1, 0, 0, 0, 0],
    ]  # a one-step tail succeeds at t=0, then running -> 1 0 0 0 0 0
    done = [[0, 0, 1, 0, 0, 0], [0, 1, 0, 1, 0, 1], [0, 0, 1, 0, 0, 0], [1, 0, 0, 0, 0, 0]]
    term = [[0, 0, 1, 0, 0, 0], [0, 0, 0, 1, 0, 1], [0, 0, 1, 0, 0, 0], [1, 0, 0, 0, 0, 0]]
    reward = [[0, 0, 0.8, 0, 0, 0], [0, 0, 0, 0.5, 0, 0.9], [0, 0, 0, 0, 0, 0], [0.7, 0, 0, 0, 0, 0]]
    expected = torch.tensor([[1, 1, 1, 0, 0, 0], [0, 0, 1, 1, 1, 1], [0, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0]]).bool()
    td = TensorDict(
        {
            "is_init": _flags(is_init),
            "next": {"done": _flags(done), "terminated": _flags(term), "reward": torch.tensor(reward).unsqueeze(-1)},
        },
        batch_size=[4, 6],
    )
    return td, expected


# ---------------------------------------------------------------------------------------------------------------
# success_step_mask
# ---------------------------------------------------------------------------------------------------------------
def test_success_mask_on_hand_made_batches():
    td, expected = hand_batch()
    seen = []

    def spy(ends):
        seen.append(ends.numel())
        assert bool(ends["done"].all()), "success_fn must only see episode ends"
        return MINIGRID_SUCCESS(ends)

    assert torch.equal(success_step_mask(td, spy), expected)
    assert seen == [int(td["next", "done"].sum())]


def test_success_mask_with_leading_worker_dims():
    """``[workers, envs, T]`` (a multi-process collector): each worker's rows masked as alone."""
    td, expected = hand_batch()
    stacked = torch.stack([td, td.clone()], 0)
    assert torch.equal(success_step_mask(stacked, MINIGRID_SUCCESS), torch.stack([expected, expected]))


def test_success_mask_without_episode_ends_marks_nothing():
    quiet, _ = hand_batch()
    quiet["next", "done"].zero_()
    assert not success_step_mask(quiet, lambda ends: pytest.fail("called without ends")).any()


def test_success_mask_errors_name_the_problem():
    td, _ = hand_batch()
    with pytest.raises(KeyError, match="is_init"):
        success_step_mask(td.exclude("is_init"), MINIGRID_SUCCESS)
    with pytest.raises(ValueError, match="no notion of success"):
        success_step_mask(td, None)
    with pytest.raises(ValueError, match="flags"):
        success_step_mask(td, lambda ends: torch.ones(1, dtype=torch.bool))


# ---------------------------------------------------------------------------------------------------------------
# SuccessBuffer
# ---------------------------------------------------------------------------------------------------------------
def seqs_with_ids(ids, L=4):
    ids = torch.as_tensor(ids)
    return TensorDict(
        {
            "id": ids[:, None].expand(-1, L).clone(),
            "obs": {"x": ids[:, None, None].float().expand(-1, L, 2).clone()},
            "empty": {},  # the trunk's output groups stay as empty sub-tensordicts after exclude()
        },
        batch_size=[len(ids), L],
    )


def _ids(buf):
    return buf.ordered()["id"][:, 0].tolist()


def test_buffer_keeps_masked_sequences_fifo():
    buf = SuccessBuffer(3)
    assert len(buf) == 0 and buf.sample(2) is None and buf.ordered() is None
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[0, 3] = mask[2, :] = True
    assert buf.add(seqs_with_ids([0, 1, 2, 3]), mask) == 2  # sequences 0 and 2
    assert _ids(buf) == [0, 2]
    assert buf.add(seqs_with_ids([4, 5]), torch.ones(2, 4, dtype=torch.bool)) == 2
    assert len(buf) == 3 and _ids(buf) == [2, 4, 5]  # capacity: the oldest (0) went
    stored_mask = dict(zip(_ids(buf), buf.ordered()[REPLAY_MASK_KEY]))
    assert stored_mask[2].all() and stored_mask[4].all()


def test_buffer_batch_larger_than_capacity_keeps_its_newest():
    buf = SuccessBuffer(3)
    buf.add(seqs_with_ids([0]), torch.ones(1, 4, dtype=torch.bool))
    buf.add(seqs_with_ids([10, 11, 12, 13, 14]), torch.ones(5, 4, dtype=torch.bool))
    assert _ids(buf) == [12, 13, 14]


def test_buffer_samples_without_replacement_up_to_its_size():
    buf = SuccessBuffer(3)
    buf.add(seqs_with_ids([2, 4, 5]), torch.ones(3, 4, dtype=torch.bool))
    s = buf.sample(2)
    assert s.batch_size == (2, 4) and s["id"][:, 0].unique().numel() == 2  # without replacement
    assert set(s["id"][:, 0].tolist()) <= {2, 4, 5}
    assert s[REPLAY_MASK_KEY].dtype == torch.bool and s[REPLAY_MASK_KEY].shape == (2, 4)
    big = buf.sample(7)  # more than stored: with replacement
    assert big.batch_size == (7, 4) and set(big["id"][:, 0].tolist()) <= {2, 4, 5}


def test_buffer_refuses_foreign_batches():
    buf = SuccessBuffer(4)
    buf.add(seqs_with_ids([0]), torch.ones(1, 4, dtype=torch.bool))
    other = seqs_with_ids([1]).exclude("id")
    with pytest.raises(ValueError, match="missing.*id"):
        buf.add(other, torch.ones(1, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="length"):
        buf.add(seqs_with_ids([1], L=5), torch.ones(1, 5, dtype=torch.bool))
    with pytest.raises(KeyError, match="replay_mask"):
        buf.add(seqs_with_ids([1]))
    with pytest.raises(ValueError, match="mask shape"):
        buf.add(seqs_with_ids([1]), torch.ones(1, 3, dtype=torch.bool))


def _wrapped_buffer():
    buf = SuccessBuffer(3)
    for start in (0, 2, 4):  # wraps around: the stored order is 3, 4, 5
        buf.add(seqs_with_ids([start, start + 1]), torch.ones(2, 4, dtype=torch.bool))
    return buf


def _saved_and_loaded(state, tmp_path):
    torch.save({"success_buffer": state}, tmp_path / "buf.pt")
    return torch.load(tmp_path / "buf.pt", weights_only=True)["success_buffer"]


def test_buffer_state_dict_round_trip(tmp_path):
    buf = _wrapped_buffer()
    back = SuccessBuffer(3)
    back.load_state_dict(_saved_and_loaded(buf.state_dict(), tmp_path))
    assert len(back) == 3 and _ids(back) == [3, 4, 5]
    assert (back.ordered() == buf.ordered()).all()
    back.add(seqs_with_ids([9]), torch.ones(1, 4, dtype=torch.bool))  # FIFO continues where it stopped
    assert _ids(back) == [4, 5, 9]


def test_buffer_loaded_into_a_smaller_capacity_keeps_the_newest(tmp_path):
    small = SuccessBuffer(2)
    small.load_state_dict(_saved_and_loaded(_wrapped_buffer().state_dict(), tmp_path))
    assert _ids(small) == [4, 5]


def test_buffer_empty_state_and_missing_entries():
    empty = SuccessBuffer(2)
    empty.load_state_dict(SuccessBuffer(2).state_dict())
    assert len(empty) == 0
    with pytest.raises(KeyError, match="rows"):
        empty.load_state_dict({"size": 1, "seq_len": 4})


# ---------------------------------------------------------------------------------------------------------------
# V-trace
# ---------------------------------------------------------------------------------------------------------------
GAMMA = 0.9


def replay_batch(reward, done, term, value, log_mu, log_pi=None, mask=None):
    """A replayed [S, L] batch and the callables returning fixed ``log_pi`` / ``value``."""
    reward, value, log_mu = (torch.tensor(x, dtype=torch.float32) for x in (reward, value, log_mu))
    log_pi = log_mu.clone() if log_pi is None else torch.tensor(log_pi, dtype=torch.float32)
    S, L = reward.shape
    td = TensorDict(
        {
            "action": torch.zeros(S, L, dtype=torch.long),
            "action_log_prob": log_mu,
            REPLAY_MASK_KEY: torch.ones(S, L, dtype=torch.bool) if mask is None else torch.tensor(mask).bool(),
            "next": {"reward": reward.unsqueeze(-1), "done": _flags(done), "terminated": _flags(term)},
        },
        batch_size=[S, L],
    )
    return td, (lambda t: log_pi), (lambda t: value.unsqueeze(-1))


def test_vtrace_on_policy_equals_td1_returns_by_hand():
    """pi == mu, no truncation: v_t is the lambda=1 return, bootstrapped at the bootstrap points by hand."""
    r = [[0, 0, 0, 1, 0, 0], [0, 0, 1, 0, 0, 0], [0, 0.5, 0, 0, 0, 1]]
    done = [[0, 0, 0, 0, 0, 0], [0, 0, 1, 0, 0, 0], [0, 0, 1, 0, 0, 1]]
    term = [[0, 0, 0, 0, 0, 0], [0, 0, 1, 0, 0, 0], [0, 0, 0, 0, 0, 1]]  # row 2: truncated at t=2
    V = [[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [0.6, 0.5, 0.4, 0.3, 0.2, 0.1], [0.2, 0.2, 0.7, 0.1, 0.3, 0.9]]
    g = GAMMA
    expected = [
        # no end in the sequence: bootstrap from V(s_5); step 5 is a bootstrap point (target = its value)
        [g**3 + g**5 * 0.6, g**2 + g**4 * 0.6, g + g**3 * 0.6, 1 + g**2 * 0.6, g * 0.6, 0.6],
        # success at t=2 (terminal return), new episode bootstrapped from V(s_5)
        [g**2, g, 1, g**2 * 0.1, g * 0.1, 0.1],
        # truncated at t=2: a bootstrap point; a terminated last step is trained (target = its reward)
        [0.5 * g + g**2 * 0.7, 0.5 + g * 0.7, 0.7, g**2, g, 1],
    ]
    trained = torch.tensor([[1, 1, 1, 1, 1, 0], [1, 1, 1, 1, 1, 0], [1, 1, 0, 1, 1, 1]], dtype=torch.float32)
    td, log_pi_fn, value_fn = replay_batch(r, done, term, V, log_mu=torch.full((3, 6), -1.3).tolist())
    out = correct_replay(td, log_prob_fn=log_pi_fn, value_fn=value_fn, gamma=g, rho_clip=100.0)
    target = torch.tensor(expected)
    torch.testing.assert_close(out["value_target"].squeeze(-1), target)
    # the advantage is the lambda=1 advantage G_t - V(s_t) (0 at bootstrap points)
    torch.testing.assert_close(out["advantage"].squeeze(-1), (target - torch.tensor(V)) * trained)
    torch.testing.assert_close(out[LOSS_WEIGHT_KEY], trained)
    torch.testing.assert_close(out["state_value"].squeeze(-1), torch.tensor(V))
    assert out["advantage"].shape == (3, 6, 1) and out["action_log_prob"].shape == (3, 6)
    # another reward key (a shaped reward, as the GAE module may read): V-trace reads that one
    shaped = td.clone()
    shaped["next", "shaped_reward"] = shaped["next", "reward"].clone()
    shaped["next", "reward"].zero_()
    out2 = correct_replay(
        shaped, log_prob_fn=log_pi_fn, value_fn=value_fn, gamma=g, rho_clip=100.0, reward_key=("next", "shaped_reward")
    )
    torch.testing.assert_close(out2["value_target"], out["value_target"])
    with pytest.raises(KeyError, match="shaped_reward"):
        correct_replay(td, log_prob_fn=log_pi_fn, value_fn=value_fn, gamma=g, reward_key=("next", "shaped_reward"))


def hand_vtrace(gamma, log_pi, log_mu, V, r, done, term, rho_bar):
    """The V-trace recursion written out step by step for one row (lists), with bootstrap points."""
    L = len(r)
    v, adv = [0.0] * L, [0.0] * L
    for t in reversed(range(L)):
        if not (term[t] or (not done[t] and t < L - 1)):  # bootstrap point
            v[t] = V[t]
            continue
        rho = min(rho_bar, math.exp(log_pi[t] - log_mu[t]))
        nxt_v = 0.0 if term[t] else V[t + 1]
        delta = rho * (r[t] + gamma * nxt_v - V[t])
        v[t] = V[t] + delta + (0.0 if done[t] else gamma * rho * (v[t + 1] - V[t + 1]))  # c_bar = rho_bar
        adv[t] = r[t] + gamma * (0.0 if term[t] else v[t + 1]) - V[t]
    return v, adv


def test_vtrace_truncation_and_weights():
    gen = torch.Generator().manual_seed(3)
    S, L, rho_clip = 3, 7, 1.0
    log_mu = (-torch.rand(S, L, generator=gen) * 2).tolist()
    diff = torch.linspace(-2.0, 2.0, S * L).reshape(S, L)[:, torch.randperm(L, generator=gen)]
    log_pi = (torch.tensor(log_mu) + diff).tolist()
    r = torch.rand(S, L, generator=gen).tolist()
    V = torch.rand(S, L, generator=gen).tolist()
    done = [[0, 0, 1, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0], [0, 1, 0, 0, 1, 0, 1]]
    term = [[0, 0, 1, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0, 1]]
    mask = [[1, 1, 1, 0, 0, 0, 0], [1] * 7, [1] * 7]  # row 0: the second episode failed
    td, log_pi_fn, value_fn = replay_batch(r, done, term, V, log_mu, log_pi, mask)
    out = correct_replay(td, log_prob_fn=log_pi_fn, value_fn=value_fn, gamma=GAMMA, rho_clip=rho_clip)
    for i in range(S):
        v, adv = hand_vtrace(GAMMA, log_pi[i], log_mu[i], V[i], r[i], done[i], term[i], rho_clip)
        torch.testing.assert_close(out["value_target"][i, :, 0], torch.tensor(v))
        torch.testing.assert_close(out["advantage"][i, :, 0], torch.tensor(adv))
    w = out[LOSS_WEIGHT_KEY]
    trained = torch.tensor(mask).bool()
    trained[:, -1] &= torch.tensor(term).bool()[:, -1]
    trained[2, 4] = False  # truncated step
    ratio = diff.exp()
    torch.testing.assert_close(w, torch.where(trained, ratio.clamp_max(rho_clip), torch.zeros(())))
    assert w.max() <= rho_clip and bool((w[trained & (diff > 0)] == rho_clip).all())
    assert torch.equal(out["action_log_prob"], torch.tensor(log_pi))  # clipping is centred on pi_k
    with pytest.raises(KeyError, match="'replay_mask'"):
        correct_replay(td.exclude(REPLAY_MASK_KEY), log_prob_fn=log_pi_fn, value_fn=value_fn, gamma=GAMMA)
    with pytest.raises(ValueError, match="value_fn"):
        correct_replay(td, log_prob_fn=log_pi_fn, value_fn=lambda t: torch.zeros(S, L, 2), gamma=GAMMA)


# ---------------------------------------------------------------------------------------------------------------
# weighted_ppo_loss
# ---------------------------------------------------------------------------------------------------------------
def toy_actor_critic():
    actor = ProbabilisticActor(
        TensorDictModule(nn.Linear(3, 4), in_keys=["obs"], out_keys=["logits"]),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )
    return actor, ValueOperator(nn.Linear(3, 1), in_keys=["obs"])


def toy_batch(actor, S=4, L=5, seed=0):
    gen = torch.Generator().manual_seed(seed)
    td = TensorDict({"obs": torch.randn(S, L, 3, generator=gen)}, batch_size=[S, L])
    with torch.no_grad():
        td = actor(td)
    td["action_log_prob"] = td["action_log_prob"] + 0.3 * torch.randn(S, L, generator=gen)  # an older policy
    td["advantage"] = torch.randn(S, L, 1, generator=gen)
    td["value_target"] = torch.randn(S, L, 1, generator=gen)
    return td.exclude("logits")


def ppo_losses(actor, critic, reduction):
    return ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=0.2,
        entropy_coeff=0.01,
        critic_coeff=0.5,
        loss_critic_type="l2",
        normalize_advantage=True,
        functional=False,
        reduction=reduction,
    )


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_weighted_loss_with_unit_weights_is_the_mean_reduction():
    actor, critic = toy_actor_critic()
    td = toy_batch(actor)
    mean = ppo_losses(actor, critic, "mean")(td)
    per_step = ppo_losses(actor, critic, "none")(td)
    for key in ("loss_objective", "loss_critic", "loss_entropy"):
        assert per_step[key].shape == (4, 5), key
    mixed = mix_minibatch(td)  # no replay: weights 1, no validity mask
    assert LOSS_MASK_KEY not in mixed.keys()
    out = weighted_ppo_loss(per_step, mixed[LOSS_WEIGHT_KEY])
    for key in ("loss_objective", "loss_critic", "loss_entropy"):
        assert torch.equal(out[key], mean[key]), (key, out[key], mean[key])
    assert torch.equal(out["clip_fraction"], mean["clip_fraction"])
    with pytest.raises(ValueError, match="reduction='none'"):
        weighted_ppo_loss(mean, mixed[LOSS_WEIGHT_KEY])


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_weighted_loss_ignores_zero_weight_steps():
    actor, critic = toy_actor_critic()
    loss = ppo_losses(actor, critic, "none")
    onp = toy_batch(actor, S=2, seed=1)
    replay = toy_batch(actor, S=2, seed=2)
    w = torch.rand(2, 5, generator=torch.Generator().manual_seed(4)) + 0.1
    w[0, 2:] = 0.0
    w[1, -1] = 0.0
    replay[LOSS_WEIGHT_KEY] = w

    def losses_and_grads(rp):
        mb = mix_minibatch(onp, rp)
        out = weighted_ppo_loss(loss(mb), mb[LOSS_WEIGHT_KEY])
        total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
        params = list(actor.parameters()) + list(critic.parameters())
        return [out[k].detach() for k in ("loss_objective", "loss_critic", "loss_entropy")], torch.autograd.grad(
            total, params
        )

    base, base_grads = losses_and_grads(replay)
    junk = replay.clone()
    zero = (w == 0).unsqueeze(-1)
    junk["advantage"] = torch.where(zero, 100.0, junk["advantage"])  # would dominate the normalisation statistics
    junk["value_target"] = torch.where(zero, -100.0, junk["value_target"])
    junk["action_log_prob"] = torch.where(zero.squeeze(-1), junk["action_log_prob"] - 5.0, junk["action_log_prob"])
    again, grads = losses_and_grads(junk)
    for a, b in zip(base + list(base_grads), again + list(grads)):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
    # a step with w > 0 does count
    live = replay.clone()
    live["value_target"][1, 0] += 10.0
    assert not torch.allclose(losses_and_grads(live)[0][1], base[1])


# ---------------------------------------------------------------------------------------------------------------
# The real tiny FreamerV1
# ---------------------------------------------------------------------------------------------------------------
def freamer_replay_fns(modules):
    """``log_prob_fn`` / ``value_fn`` of :func:`correct_replay` for FreamerModules: the pattern for the trainer.

    One trunk pass in recurrent mode from the stored memory at t = 0, written into the replayed tensordict by
    ``log_prob_fn`` (correct_replay calls it first); ``value_fn`` then runs only the critic head on those outputs.
    correct_replay wraps both in ``torch.no_grad()``.
    """

    def log_prob_fn(td):
        with set_recurrent_mode(True):
            modules.trunk(td)
        return modules.actor.get_dist(td).log_prob(td["action"])

    def value_fn(td):
        return modules.critic(td)["state_value"]

    return log_prob_fn, value_fn


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny FreamerV1, one collected batch after the trainer's advantage step, and 2 replayed sequences of env 0
    (forced successful: a random policy rarely succeeds)."""
    cfg = load_config(TINY, ["run.total_frames=128"])
    trainer = Trainer(cfg, tmp_path_factory.mktemp("tiny") / "run", resume=False)
    trainer.life.lock.release()
    data = trainer.compute_advantage(trainer.collect_batch())
    mask = success_step_mask(data, env_registry.get_adapter(cfg.env.adapter).success)
    assert mask.shape == data.shape
    forced = mask.clone()
    forced[0] = True
    buffer = SuccessBuffer(16, device=trainer.device)
    seqs = replay_sequences(data, forced, cfg.ppo.sequence_length, drop=trainer.modules.trunk.out_keys)
    assert buffer.add(seqs) >= data.shape[-1] // cfg.ppo.sequence_length
    return cfg, trainer, data, seqs, buffer.sample(2)


def _trainer_loss(cfg, modules, reduction):
    """The trainer's ClipPPOLoss settings."""
    p = cfg.ppo
    return ClipPPOLoss(
        modules.actor,
        modules.critic,
        clip_epsilon=p.clip_epsilon,
        entropy_coeff=p.entropy_coeff,
        critic_coeff=p.critic_coeff,
        loss_critic_type="l2",
        normalize_advantage=p.normalize_advantage,
        functional=False,
        reduction=reduction,
    )


def test_replay_sequences_drop_the_trunk_outputs(tiny):
    _, _, _, seqs, _ = tiny
    assert ("next", "grid") not in seqs.keys(True) and ("next", "terminated") in seqs.keys(True)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_replay_without_an_update_is_on_policy(tiny):
    """No update since collection: pi_k == mu, the recurrent values match GAE's step-mode ones, weights 0/1."""
    cfg, trainer, _, _, replay = tiny
    L = cfg.ppo.sequence_length
    log_prob_fn, value_fn = freamer_replay_fns(trainer.modules)
    fixed = correct_replay(replay, log_prob_fn=log_prob_fn, value_fn=value_fn, gamma=cfg.ppo.gamma, rho_clip=1.0)
    torch.testing.assert_close(fixed["action_log_prob"], replay["action_log_prob"], atol=1e-4, rtol=0)
    torch.testing.assert_close(fixed["state_value"], replay["state_value"], atol=1e-4, rtol=0)
    expect_w = replay[REPLAY_MASK_KEY] & (
        replay["next", "terminated"].squeeze(-1) | (torch.arange(L) < L - 1) & ~replay["next", "done"].squeeze(-1)
    )
    torch.testing.assert_close(fixed[LOSS_WEIGHT_KEY], expect_w.float(), atol=1e-4, rtol=0)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_weighted_reduction_without_replay_is_the_trainers_mean(tiny):
    cfg, trainer, data, _, _ = tiny
    modules = trainer.modules
    onp = split_sequences(data.exclude("next", *modules.trunk.out_keys), cfg.ppo.sequence_length)[:4]
    with set_recurrent_mode(True):
        mb = modules.trunk(mix_minibatch(onp))
    ours = weighted_ppo_loss(_trainer_loss(cfg, modules, "none")(mb), mb[LOSS_WEIGHT_KEY])
    theirs = _trainer_loss(cfg, modules, "mean")(mb)
    for key in ("loss_objective", "loss_critic", "loss_entropy"):
        torch.testing.assert_close(ours[key], theirs[key], rtol=1e-6, atol=1e-7)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_off_policy_mixed_minibatch_trains(tiny):
    """The policy moves on: replayed steps get clipped IS weights, and the mixed loss has finite, non-zero grads."""
    cfg, trainer, data, _, replay = tiny
    modules, L = trainer.modules, cfg.ppo.sequence_length
    saved = {k: v.clone() for k, v in modules.actor_value.state_dict().items()}
    try:
        with torch.no_grad():
            for q in modules.actor.parameters():
                q.add_(0.05 * torch.randn_like(q))
        log_prob_fn, value_fn = freamer_replay_fns(modules)
        fixed = correct_replay(replay, log_prob_fn=log_prob_fn, value_fn=value_fn, gamma=cfg.ppo.gamma, rho_clip=1.0)
        assert not torch.equal(fixed["action_log_prob"], replay["action_log_prob"])
        ratio = (fixed["action_log_prob"] - replay["action_log_prob"]).exp()
        trained = fixed[LOSS_WEIGHT_KEY] > 0
        torch.testing.assert_close(fixed[LOSS_WEIGHT_KEY][trained], ratio.clamp_max(1.0)[trained])
        onp = split_sequences(data.exclude("next", *modules.trunk.out_keys), L)[:4]
        mixed = mix_minibatch(onp, fixed)
        assert mixed.batch_size == (6, L)
        with set_recurrent_mode(True):
            mb = modules.trunk(mixed)
        out = weighted_ppo_loss(_trainer_loss(cfg, modules, "none")(mb), mb[LOSS_WEIGHT_KEY])
        total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
        assert torch.isfinite(total)
        total.backward()
        grads = [q.grad for q in trainer.params if q.grad is not None]
        assert grads and all(torch.isfinite(g).all() for g in grads)
        assert any(g.abs().sum() > 0 for g in grads)
    finally:
        modules.actor_value.load_state_dict(saved)
        modules.actor_value.zero_grad(set_to_none=True)
