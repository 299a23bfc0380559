"""Exploration bonuses (NoveltyBonus, CuriosityModel, R_VL) and the reward mixer (paper App. G.1, G.2, A.5)."""

import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, InitTracker, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from freamer_rl.errors import ConfigError
from freamer_rl.machinery.exploration import CuriosityModel, NoveltyBonus, next_step_valid, vision_language_similarity
from freamer_rl.machinery.reward_mixer import RewardMixer
from freamer_rl.machinery.shaping import RewardShaper
from freamer_rl.trainers.registry import load_recipe

torch.set_num_threads(1)


class ScriptEnv(EnvBase):
    """The action is the next state: ``obs`` = the action taken (int64 ``[*B, 1]``); a reset goes to state 0.
    Action 9 ends the episode (terminated), so rollouts exercise partial resets."""

    batch_locked = True

    def __init__(self, batch_size=()):
        super().__init__(batch_size=torch.Size(batch_size))
        b = self.batch_size
        self.observation_spec = Composite(obs=Unbounded(shape=(*b, 1), dtype=torch.int64), shape=b)
        self.action_spec = Categorical(10, shape=b, dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(*b, 1))
        flag = Categorical(2, shape=(*b, 1), dtype=torch.bool)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=b)
        self._obs = torch.zeros(*b, 1, dtype=torch.int64)

    def _reset(self, tensordict=None, **kwargs):
        mask = None if tensordict is None else tensordict.get("_reset", None)
        mask = torch.ones(*self.batch_size, 1, dtype=torch.bool) if mask is None else mask.reshape(self._obs.shape)
        self._obs = torch.where(mask, torch.zeros_like(self._obs), self._obs)
        false = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(
            {"obs": self._obs.clone(), "done": false, "terminated": false.clone(), "truncated": false.clone()},
            batch_size=self.batch_size,
        )

    def _step(self, tensordict):
        self._obs = tensordict["action"].reshape(self._obs.shape).clone()
        end = self._obs == 9
        return TensorDict(
            {
                "obs": self._obs.clone(),
                "reward": torch.zeros(self._obs.shape),
                "done": end,
                "terminated": end.clone(),
                "truncated": torch.zeros_like(end),
            },
            batch_size=self.batch_size,
        )

    def _set_seed(self, seed):
        pass


class Driver:
    """Steps a :class:`ScriptEnv` wrapped in the transforms, carrying the root tensordict as a collector does."""

    def __init__(self, batch_size=(), alpha=0.5):
        self.bonus = NoveltyBonus(in_keys=["obs"], alpha=alpha)
        self.env = TransformedEnv(ScriptEnv(batch_size), Compose(InitTracker(), StepCounter(), RewardSum(), self.bonus))
        self.td = None

    def reset(self, mask=None):
        """Full reset, or a partial one of the rows where ``mask`` ([*B, 1] bool) is True; returns the bonus."""
        td = None if mask is None else self.td.clone().set("_reset", torch.tensor(mask))
        self.td = self.env.reset(td)
        return self.td["novelty_bonus"].reshape(-1).tolist()

    def go(self, actions):
        """One step with ``actions`` (an int, or one per row); returns the bonus per row."""
        td = self.td.clone().set("action", torch.tensor(actions).reshape(self.env.batch_size))
        td = self.env.step(td)
        self.td = step_mdp(td)
        return td["next", "novelty_bonus"].reshape(-1).tolist()


# -- NoveltyBonus ------------------------------------------------------------------------------------------------
def test_novelty_closed_form_unbatched():
    d = Driver()
    r3, r2 = 1 / math.sqrt(3), 1 / math.sqrt(2)
    assert d.reset() == [0.0]  # state 0: count 1
    expected = [
        (1, 1 - 0.5),  # first visit of 1: N(1) = 1, N(0) = 1
        (2, 1 - 0.5),
        (1, 0.0),  # seen in this episode
        (0, 0.0),  # the reset state is in the episodic set too
    ]
    for action, want in expected:
        assert d.go(action) == pytest.approx([want])
    assert d.reset() == [0.0]  # clears the episodic set, keeps the counts: 0 has 3
    expected = [
        (1, r3 - 0.5 * r3),  # count(1) = 3, count(0) = 3
        (3, 1 - 0.5 * r3),  # new state
        (2, r2 - 0.5 * 1),  # count(2) = 2, the previous state 3 has count 1
    ]
    for action, want in expected:
        assert d.go(action) == pytest.approx([want])
    assert d.bonus.counts_summary() == {"distinct_states": 4, "total_visits": 9}


def test_novelty_max_clips_at_zero_and_alpha_zero():
    d = Driver()
    for _ in range(8):  # state 4 becomes common
        d.reset()
        d.go(4)
    d.reset()
    d.go(5)  # a rare state: count 1
    assert d.go(4) == [0.0]  # first visit this episode, but N(4) = 1/sqrt(9) < 0.5 * N(5) = 0.5
    d0 = Driver(alpha=0.0)
    d0.reset()
    assert d0.go(7) == [1.0]  # alpha = 0: the episodic count bonus 1/sqrt(n)


def test_novelty_batched_partial_reset():
    d = Driver(batch_size=(2,))
    d.reset()  # both rows at 0: count(0) = 2
    assert d.go([1, 1]) == pytest.approx([2**-0.5 - 0.5 * 2**-0.5] * 2)  # all rows counted first, then read
    assert d.go([2, 0]) == pytest.approx([1 - 0.5 * 2**-0.5, 0.0])  # row 1 is back at its start state
    # the reset row reads 0; row 0 keeps its current value (TorchRL merges a partial reset row by row)
    assert d.reset([[False], [True]]) == pytest.approx([1 - 0.5 * 2**-0.5, 0.0])
    assert d.td["obs"].tolist() == [[2], [0]]  # row 0 kept its state
    assert d.bonus.counts_summary() == {"distinct_states": 3, "total_visits": 7}
    # row 0 has seen 1 in its episode; row 1 starts a new one: count(1) = 4, count(0) = 4
    assert d.go([1, 1]) == pytest.approx([0.0, 0.5 - 0.5 * 0.5])
    assert d.bonus.counts_summary() == {"distinct_states": 3, "total_visits": 9}


def test_novelty_rollout_specs_and_auto_reset():
    d = Driver(batch_size=(3,))
    env, bonus = d.env, d.bonus
    check_env_specs(env)
    bonus.reset_counts()
    data = env.rollout(40, break_when_any_done=False)  # random actions: action 9 ends episodes row by row
    b = data["next", "novelty_bonus"]
    assert b.shape == (3, 40, 1) and b.dtype == torch.float32 and (b >= 0).all()
    assert bonus.counts_summary()["total_visits"] == 3 + 120 + int(data["next", "done"].sum())
    with pytest.raises(RuntimeError, match="online env transform"):
        bonus(data)


@pytest.mark.parametrize("batched", [False, True])
def test_novelty_check_env_specs_minigrid(batched):
    from freamer_rl_envs.minigrid import make_minigrid_env, make_minigrid_vec_env

    if batched:
        base = make_minigrid_vec_env("MiniGrid-Empty-5x5-v0", 3, seed=0)
    else:
        base = make_minigrid_env("MiniGrid-Empty-5x5-v0", seed=0)
    bonus = NoveltyBonus(in_keys=["grid", "direction"])
    env = TransformedEnv(base, Compose(InitTracker(), StepCounter(max_steps=6), RewardSum(), bonus))
    check_env_specs(env)
    data = env.rollout(15, break_when_any_done=False)
    assert data["next", "novelty_bonus"].shape == (*env.batch_size, 15, 1)
    assert bonus.counts_summary()["distinct_states"] > 1
    env.close()


def test_novelty_missing_key_is_named():
    env = TransformedEnv(ScriptEnv(), NoveltyBonus(in_keys=["pixels"]))
    with pytest.raises(KeyError, match="pixels"):
        env.reset()


def test_novelty_digest_keys_count_like_exact_keys():
    """A 16-byte BLAKE2b key per state gives the bonuses and counts of the exact keys (no collision among 7 states)."""
    exact, digest = Driver(), Driver()
    digest.bonus.digest_size = 16
    script = [[1, 2, 1, 3], [2, 2, 4], [1, 5, 6]]
    for episode in script:
        assert exact.reset() == digest.reset()
        for action in episode:
            assert digest.go(action) == pytest.approx(exact.go(action)), (episode, action)
    assert digest.bonus.counts_summary() == exact.bonus.counts_summary() == {"distinct_states": 7, "total_visits": 13}
    with pytest.raises(ValueError, match="digest_size"):
        NoveltyBonus(in_keys=["obs"], digest_size=65)


# -- CuriosityModel ----------------------------------------------------------------------------------------------
def _curiosity_batch(b=4, t=6, d=8, n_act=3):
    phi = torch.randn(b, t, d)
    action = torch.randint(n_act, (b, t))
    done = torch.zeros(b, t, 1, dtype=torch.bool)
    done[0, 2] = True
    return phi, action, done


def test_curiosity_shapes_and_invalid_zero():
    phi, action, done = _curiosity_batch()
    model = CuriosityModel(8, 3)
    valid = next_step_valid(done)
    assert valid.shape == (4, 6) and not valid[:, -1].any() and not valid[0, 2]
    assert torch.equal(model.valid_mask(done), valid)
    r = model.intrinsic_reward(phi, action, valid)
    assert r.shape == (4, 6, 1) and not r.requires_grad
    assert (r[:, -1] == 0).all() and r[0, 2].item() == 0 and (r[valid] != 0).all()
    # [*B, T, 1] masks and actions give the same reward; the last step is invalid whatever valid says
    r2 = model.intrinsic_reward(phi, action.unsqueeze(-1), valid.unsqueeze(-1), update_stats=False)
    assert torch.allclose(r2, r)
    r3 = model.intrinsic_reward(phi, action, torch.ones(4, 6, 1, dtype=torch.bool), update_stats=False)
    assert (r3[:, -1] == 0).all()


def test_curiosity_running_std_normalisation():
    phi, action, done = _curiosity_batch()
    model = CuriosityModel(8, 3)
    valid = next_step_valid(done)
    raw = model.prediction_error(phi, action, valid).detach()
    r = model.intrinsic_reward(phi, action, valid)  # updates the stats with this batch first
    errs = raw[valid]
    n0 = 1e-4  # the prior count (mean 0, var 1)
    n = errs.numel()
    mean = errs.mean()
    var = (n0 * 1.0 + n * errs.var(unbiased=False) + mean**2 * n0 * n / (n0 + n)) / (n0 + n)
    assert torch.allclose(model.err_var, var, rtol=1e-4)
    centred = (raw - raw[valid].mean()) / (var + model.eps).sqrt() * valid.unsqueeze(-1)
    assert torch.allclose(r, centred, rtol=1e-4, atol=1e-6)
    assert abs(float(r[valid].mean())) < 1e-5  # centred: no standing bonus or penalty for merely staying alive
    before = model.err_var.clone()
    model.intrinsic_reward(phi, action, torch.zeros_like(valid))  # all invalid: statistics unchanged
    assert torch.allclose(model.err_var, before)


def test_curiosity_loss_decreases_and_features_detached():
    phi, action, done = _curiosity_batch()
    phi.requires_grad_(True)
    model = CuriosityModel(8, 3)
    valid = next_step_valid(done)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    first = model.loss(phi, action, valid)
    for _ in range(60):
        loss = model.loss(phi, action, valid)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first.item()
    assert phi.grad is None  # only the forward model learns
    assert model.loss(phi, action, torch.zeros_like(valid)).item() == 0.0


def test_curiosity_forward_is_sync_free(monkeypatch):
    phi, action, done = _curiosity_batch()
    model = CuriosityModel(8, 3)
    valid = next_step_valid(done)

    def refuse(*args):
        raise AssertionError("host sync in the curiosity forward")

    monkeypatch.setattr(torch.Tensor, "item", refuse)
    monkeypatch.setattr(torch.Tensor, "__bool__", refuse)
    with pytest.raises(AssertionError, match="host sync"):  # the patch is live
        bool(torch.ones(()))
    model.intrinsic_reward(phi, action, valid)  # update_stats=True too
    model.loss(phi, action, valid)
    monkeypatch.undo()
    # per-row vmap equals calling each row as its own batch (the centring mean is the batch's)
    fn = lambda p, a, v: model.intrinsic_reward(p, a, v, update_stats=False)  # noqa: E731
    expected = torch.stack([fn(phi[i : i + 1], action[i : i + 1], valid[i : i + 1])[0] for i in range(len(phi))])
    assert torch.allclose(torch.func.vmap(fn)(phi, action, valid), expected, atol=1e-6)


def test_vision_language_similarity():
    a = torch.tensor([[1.0, 0.0], [1.0, 1.0], [0.0, 2.0]])
    b = torch.tensor([[2.0, 0.0], [-1.0, -1.0], [1.0, 0.0]])
    sim = vision_language_similarity(a, b)
    assert sim.shape == (3, 1) and sim.reshape(-1).tolist() == pytest.approx([1.0, -1.0, 0.0])
    assert vision_language_similarity(torch.randn(2, 5, 7), torch.randn(2, 5, 7)).shape == (2, 5, 1)


# -- RewardMixer -------------------------------------------------------------------------------------------------
def _mix_batch():
    reward = torch.tensor([[[0.0], [0.0], [0.9]]])  # [1, 3, 1]
    nov = torch.tensor([[[0.5], [0.0], [0.2]]])
    cur = torch.tensor([[1.0, 2.0, 0.0]])  # [*B, T] is accepted too
    done = torch.tensor([[[False], [False], [True]]])
    return TensorDict(
        {
            "next": {
                "reward": reward,
                "novelty_bonus": nov,
                "curiosity_reward": cur,
                "done": done,
                "terminated": done.clone(),
            }
        },
        batch_size=[1, 3],
    )


def test_reward_mixer_adaptive_and_time_penalty():
    terms = {"novelty": (("next", "novelty_bonus"), 0.4), "curiosity": (("next", "curiosity_reward"), 0.1)}
    td = _mix_batch()
    mixer = RewardMixer(terms, adaptive=True, time_penalty=0.05)
    mixer(td, success_rate=0.4)
    decay, penalty = 1 - 1.25 * 0.4, 0.05 * (1 + 40 / 100)  # 0.5 and 0.07 per step
    want = [0.0 + decay * (0.4 * 0.5 + 0.1 * 1.0) - penalty, decay * 0.2 - penalty, 0.9 + decay * 0.08 - penalty]
    assert td["next", "shaped_reward"].shape == (1, 3, 1)
    assert td["next", "shaped_reward"].reshape(-1).tolist() == pytest.approx(want)
    assert td["next", "reward"].reshape(-1).tolist() == pytest.approx([0.0, 0.0, 0.9])  # env reward untouched
    diag = mixer.diagnostics()
    # one episode ended in the batch: it collected decay * (0.4 * 0.7 + 0.1 * 3.0) of bonus
    assert diag == pytest.approx(
        {
            "bonus_novelty": 0.7 / 3,
            "bonus_curiosity": 1.0,
            "shaping_decay": 0.5,
            "time_penalty": 0.07,
            "bonus_per_episode": 0.5 * (0.28 + 0.3),
        }
    )
    mixer(td, success_rate=0.9)  # decay floors at 0; penalty 0.05 * 1.9
    assert td["next", "shaped_reward"].reshape(-1).tolist() == pytest.approx([-0.095, -0.095, 0.9 - 0.095])
    mixer(td, success_rate=float("nan"))  # no episode yet: S = 0
    assert mixer.diagnostics()["shaping_decay"] == 1.0 and mixer.diagnostics()["time_penalty"] == pytest.approx(0.05)


def test_reward_mixer_non_adaptive_keys_and_errors():
    td = _mix_batch()
    mixer = RewardMixer({"novelty": (("next", "novelty_bonus"), 2.0)}, adaptive=False)
    mixer(td, success_rate=0.9)
    assert td["next", "shaped_reward"].reshape(-1).tolist() == pytest.approx([1.0, 0.0, 1.3])
    mixer.set_keys(shaped_reward=("next", "mixed"))
    mixer(td, 0.0)
    assert ("next", "mixed") in td.keys(True) and mixer.out_keys == [("next", "mixed")]
    with pytest.raises(ValueError, match="not a key"):
        mixer.set_keys(rewards="x")
    with pytest.raises(ValueError, match="success_rate"):
        mixer(td, 1.5)
    missing = RewardMixer({"vl": (("next", "vl_reward"), 1.0), "novelty": (("next", "novelty_bonus"), 1.0)})
    with pytest.raises(KeyError, match=r"'vl_reward'.*vision_language_similarity"):
        missing(td, 0.0)
    with pytest.raises(KeyError, match="NoveltyBonus"):
        missing(td.exclude(("next", "novelty_bonus")).update({"next": {"vl_reward": torch.zeros(1, 3, 1)}}), 0.0)


def test_bonus_per_episode_sums_each_episode_across_batches():
    mixer = RewardMixer({"novelty": (("next", "novelty_bonus"), 2.0)}, adaptive=False)
    td = _mix_batch().expand(2, 3).clone()  # two rows; weighted bonus per step 1.0, 0.0, 0.4 (1.4 per batch)
    td["next", "done"].zero_()  # no episode ends: nothing to report, each row carries 1.4
    mixer(td, 0.0)
    assert math.isnan(mixer.diagnostics()["bonus_per_episode"])
    td["next", "done"][0, -1] = True  # row 0 ends at its last step: 1.4 carried + 1.4
    mixer(td, 0.0)
    assert mixer.diagnostics()["bonus_per_episode"] == pytest.approx(2.8)
    td["next", "done"].zero_()
    td["next", "done"][:, 0] = True  # both end at the first step: row 0 from 0, row 1 from its 2.8 carried
    mixer(td, 0.0)
    assert mixer.diagnostics()["bonus_per_episode"] == pytest.approx(((0 + 1.0) + (2.8 + 1.0)) / 2)
    td["next", "done"].zero_()
    td["next", "done"][:, -1] = True  # each row's new episode: 0.4 left over from the last batch + 1.4
    mixer(td, 0.0)
    assert mixer.diagnostics()["bonus_per_episode"] == pytest.approx(1.8)
    no_terms = RewardMixer(time_penalty=0.05)  # no bonus terms: no bonus to report
    no_terms(td, 0.0)
    assert "bonus_per_episode" not in no_terms.diagnostics()


def test_time_penalty_matches_appendix_a5():
    assert RewardMixer.accumulated_time_penalty(0.05, 0.295, 145) == pytest.approx(9.39, abs=5e-3)
    mixer = RewardMixer(time_penalty=0.05, adaptive=False)
    td = TensorDict({"next": {"reward": torch.zeros(1, 145, 1)}}, batch_size=[1, 145])
    mixer(td, success_rate=0.295)
    assert td["next", "shaped_reward"].sum().item() == pytest.approx(-9.39, abs=5e-3)


@pytest.mark.parametrize("scale", [0.1, 1.0, 2.5])
def test_reward_mixer_scale_multiplies_the_whole_shaped_reward(scale):
    td = _mix_batch()
    RewardMixer({"novelty": (("next", "novelty_bonus"), 2.0)}, adaptive=False, time_penalty=0.05, scale=scale)(td, 0.0)
    want = [scale * (r + 2.0 * b - 0.05) for r, b in zip([0.0, 0.0, 0.9], [0.5, 0.0, 0.2])]
    assert td["next", "shaped_reward"].reshape(-1).tolist() == pytest.approx(want)
    assert td["next", "reward"].reshape(-1).tolist() == pytest.approx([0.0, 0.0, 0.9])  # the logged reward stays
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="scale must be a finite number > 0"):
            RewardMixer(scale=bad)


@pytest.mark.parametrize("recipe", ["gym/cartpole.yaml", "baselines/ppo_mlp_cartpole.yaml"])
def test_shaping_reward_scale_turns_the_shaper_on_for_both_trainers(recipe):
    path = Path(__file__).resolve().parents[2] / "recipes" / recipe
    _, cfg = load_recipe(path, ["shaping.reward_scale=0.1"])
    shaper = RewardShaper(cfg, [], 0, 0, torch.device("cpu"))
    assert shaper.active and shaper.mixer.scale == 0.1
    td = TensorDict(
        {"next": {"reward": torch.ones(2, 3, 1), "done": torch.zeros(2, 3, 1, dtype=torch.bool)}}, batch_size=[2, 3]
    )
    td["next", "terminated"] = td["next", "done"].clone()
    shaper(td, 0.0)
    assert torch.allclose(td["next", "shaped_reward"], torch.full((2, 3, 1), 0.1))
    unscaled = load_recipe(path, ["shaping.reward_scale=1.0"])[1]
    assert not RewardShaper(unscaled, [], 0, 0, torch.device("cpu")).active  # 1.0 and nothing else: no shaping
    with pytest.raises(ConfigError, match="shaping.reward_scale"):
        load_recipe(path, ["shaping.reward_scale=0"])
