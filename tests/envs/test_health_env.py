"""Batched PAMAP2 health env (envs/health.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs, step_mdp

from freamer_rl.data import (
    HRFeatureParams,
    hr_feature_sequence,
    pamap2_features,
    synthetic_recording,
    write_synthetic_pamap2,
)
from freamer_rl_envs.health import (
    ALERT,
    CHANGE,
    CHANGE_TO,
    CONTINUE,
    HEALTH_ACTIONS,
    INCREASE,
    REST,
    exertion,
    fatigue_update,
    hrv_update,
    make_health_env,
)

DUR = 600.0  # synthetic seconds per subject in these tests (one cached data build for the whole file)


def make(batch_size=4, **kw):
    kw.setdefault("synthetic_duration_s", DUR)
    kw.setdefault("seed", 0)
    return make_health_env(batch_size=batch_size, **kw)


def const_policy(action: int):
    def policy(td):
        return td.set("action", torch.full(td.batch_size, action, dtype=torch.int64))

    return policy


def rest_when_high(td):
    hr = td["heart_rate"].squeeze(-1)
    return td.set("action", torch.where(hr > 145, REST, CONTINUE).long())


@pytest.mark.parametrize("batch_size", [1, 4])
def test_check_env_specs(batch_size):
    env = make(batch_size)
    check_env_specs(env, seed=0)
    assert env.batch_size == torch.Size([batch_size])


def test_observation_keys_shapes_and_dtypes():
    env = make(3)
    td = env.reset()
    assert td["imu"].shape == (3, 36) and td["imu"].dtype == torch.float32
    assert td["hr_features"].shape == (3, 16) and td["hr_features"].dtype == torch.float32
    assert td["heart_rate"].shape == (3, 1) and td["heart_rate"].dtype == torch.float32
    assert td["activity"].shape == (3,) and td["activity"].dtype == torch.int64
    assert td["level"].shape == (3, 1) and td["level"].dtype == torch.float32
    for key, dtype in (("return", torch.float32), ("violations", torch.int64), ("length", torch.int64)):
        assert td["episode", key].shape == (3, 1) and td["episode", key].dtype == dtype
    assert env.action_spec.n == len(HEALTH_ACTIONS) == 5
    td = env.rand_step(td)
    nxt = td["next"]
    assert nxt["reward"].shape == (3, 1)
    for key in ("done", "terminated", "truncated"):
        assert nxt[key].shape == (3, 1) and nxt[key].dtype == torch.bool
    np.testing.assert_allclose(nxt["hr_features"][:, 1:9].sum(-1).numpy(), 1.0)


def test_reset_features_match_the_loader_layout():
    env = make(6, seed=5)
    td = env.reset()
    feats = {s: pamap2_features(synthetic_recording(s, duration_s=DUR, seed=0)) for s in env.subjects}
    for b in range(6):
        f = feats[env.subjects[int(env.subject_index[b])]]
        t = int(env.cursor[b])
        got = td["hr_features"][b].numpy()
        ref = f.hr_features[t]
        idx = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15]  # rate of change / cumulative exertion restart at 0
        np.testing.assert_allclose(got[idx], ref[idx], rtol=1e-5, atol=1e-5)
        assert got[13] == 0 and got[14] == 0
        np.testing.assert_allclose(td["imu"][b].numpy(), f.imu[t], rtol=1e-5, atol=1e-6)
        assert int(td["activity"][b]) == int(f.activity[t])
        assert float(td["heart_rate"][b]) == pytest.approx(float(f.heart_rate[t]))


def test_feature_recursions_match_the_loader():
    p = HRFeatureParams()
    rng = np.random.default_rng(0)
    hr = 70 + np.cumsum(rng.normal(0, 2, size=300)).clip(-30, 120)
    group = np.zeros(300, dtype=np.int64)
    ref = hr_feature_sequence(hr, group, np.full(300, 2.0), 1.0, 65.0, p)
    h = torch.tensor(hr, dtype=torch.float64)
    rest = torch.tensor(65.0, dtype=torch.float64)
    f = torch.zeros((), dtype=torch.float64)
    mean, var = h[0].clone(), torch.zeros((), dtype=torch.float64)
    for t in range(300):
        e = exertion(h[t], rest, p)
        f = fatigue_update(f, e, 1.0, p)
        mean, var = hrv_update(mean, var, h[t], 1.0, p)
        assert float(e) == pytest.approx(float(ref[t, 10]), abs=1e-5)
        assert float(f) == pytest.approx(float(ref[t, 11]), abs=1e-5)
        assert min(math.sqrt(float(var)) / p.hrv_scale, p.hrv_max) == pytest.approx(float(ref[t, 12]), abs=1e-4)


def test_partial_reset_only_resets_masked_elements():
    env = make(4, seed=1)
    td = env.reset()
    for _ in range(5):
        td = step_mdp(env.step(td.set("action", torch.full((4,), CONTINUE))))
    cursor_before = env.cursor
    subj_before = env.subject_index
    td["_reset"] = torch.tensor([[True], [False], [True], [False]])
    out = env.reset(td)
    lengths = out["episode", "length"].squeeze(-1)
    assert lengths.tolist() == [0, 5, 0, 5]
    keep = torch.tensor([False, True, False, True])
    assert torch.equal(env.cursor[keep], cursor_before[keep])
    assert torch.equal(env.subject_index[keep], subj_before[keep])
    assert not out["done"].any()
    nxt = env.step(out.set("action", torch.full((4,), CONTINUE)))["next"]
    assert nxt["episode", "length"].squeeze(-1).tolist() == [1, 6, 1, 6]


def test_truncation_autoreset_and_episode_metrics():
    env = make(3, episode_length=7, seed=2)
    td = env.rollout(20, break_when_any_done=False)
    nxt = td["next"]
    length = nxt["episode", "length"].squeeze(-1)
    expected = torch.tensor([1, 2, 3, 4, 5, 6, 7] * 2 + [1, 2, 3, 4, 5, 6])
    assert torch.equal(length, expected.expand(3, -1))
    trunc = nxt["truncated"].squeeze(-1)
    assert torch.equal(trunc, length == 7) and torch.equal(nxt["done"].squeeze(-1), trunc)
    # ("episode", "return") is the running sum of the episode's rewards, violations the count of HR > 160
    reward = nxt["reward"].squeeze(-1)
    viol = (nxt["heart_rate"].squeeze(-1) > 160).long()
    for b in range(3):
        for start in (0, 7, 14):
            sl = slice(start, min(start + 7, 20))
            ret = nxt["episode", "return"][b, sl, 0]
            torch.testing.assert_close(ret, reward[b, sl].cumsum(0), rtol=1e-5, atol=1e-4)
            assert torch.equal(nxt["episode", "violations"][b, sl, 0], viol[b, sl].cumsum(0))


def test_reward_sign_sanity_increase_vs_rest_when_high():
    results = {}
    for name, policy in (("increase", const_policy(INCREASE)), ("rest_when_high", rest_when_high)):
        env = make(16, episode_length=240, seed=7)
        td = env.rollout(240, policy, break_when_any_done=False)
        nxt = td["next"]
        done = nxt["done"].squeeze(-1)
        results[name] = (
            nxt["episode", "return"][done].mean().item(),
            nxt["episode", "violations"][done].float().mean().item(),
            (nxt["heart_rate"] > 160).sum().item(),
        )
    inc, rest = results["increase"], results["rest_when_high"]
    assert inc[2] > 10 * max(rest[2], 1)  # many more danger-zone steps
    assert inc[1] > rest[1]
    assert inc[0] < rest[0]


def _hr_after(action: int, steps: int = 20) -> torch.Tensor:
    env = make(16, seed=8)
    td = env.reset()
    for _ in range(steps):
        td = step_mdp(env.step(td.set("action", torch.full((16,), action))))
    return td["heart_rate"].squeeze(-1)


def test_rest_and_increase_move_heart_rate():
    cont, rest, inc = _hr_after(CONTINUE), _hr_after(REST), _hr_after(INCREASE)
    assert rest.mean() < cont.mean() - 2
    assert inc.mean() > cont.mean() + 2


def test_alert_costs_only_outside_danger_and_holds_the_stop():
    env = make(2, seed=3, reward_weights=(1.0, 0.0, 0.0))  # reward = R_safe only
    td = env.reset()
    env._st.hr = torch.tensor([90.0, 175.0])  # element 1 is in the danger zone
    td = env.step(td.set("action", torch.tensor([ALERT, ALERT])))
    r = td["next", "reward"].squeeze(-1)
    hr = td["next", "heart_rate"].squeeze(-1)
    assert hr[0] < 160 and r[0].item() == pytest.approx(-0.2)  # alert cost, no danger
    expected = -(1.0 + (hr[1].item() - 160.0) / 20.0) if hr[1] > 160 else 0.0
    assert r[1].item() == pytest.approx(expected, abs=1e-4)  # no alert cost in danger
    assert (env.level == 0).all()
    td = step_mdp(td)
    for _ in range(10):  # the emergency stop (30 s) holds the intensity down even when the agent increases
        td = step_mdp(env.step(td.set("action", torch.tensor([INCREASE, INCREASE]))))
        assert (env.level <= 0.25).all()


def test_level_observation_is_the_prescribed_intensity():
    """``"level"`` is 1 after a reset, follows Rest (-0.25) and Increase (+0.25, at most 2) on the step they act,
    is 0 after an Alert, back to 1 at a new activity segment (0.25 while an Alert's stop runs), and always equals
    the env's own ``level``."""
    env = make(6, seed=5, rate_hz=0.2)  # 5 s a step: the Alert's 30 s stop lasts 6 steps
    td = env.reset()
    assert torch.equal(td["level"], torch.ones(6, 1))
    seen_boundary = False
    for action in (REST, REST, INCREASE, ALERT, CONTINUE) + (INCREASE,) * 12:
        before = env.level.clone()
        planned, hold = env._st.planned.clone(), env._st.hold.clone()
        td = env.step(td.set("action", torch.full((6,), action)))
        nxt = td["next"]
        assert torch.equal(nxt["level"].squeeze(-1), env.level)
        moved = env._st.planned == planned  # no new segment on this step: the action's level is observed
        seen_boundary |= bool((~moved).any())
        delta = {REST: -0.25, INCREASE: 0.25}.get(action, 0.0)
        want = (before + delta).clamp(0.0, 2.0) if action != ALERT else torch.zeros(6)
        if action in (INCREASE, CONTINUE):  # the Alert's stop caps the level at 0.25 for 30 s
            want = torch.where(hold > 0, want.clamp_max(0.25), want)
        assert torch.allclose(nxt["level"].squeeze(-1)[moved], want[moved]), action
        at_plan = torch.where(env._st.hold > 0, 0.25, 1.0)  # a running Alert stop still caps a new segment's level
        assert torch.equal(nxt["level"].squeeze(-1)[~moved], at_plan[~moved])
        td = step_mdp(td)
    assert seen_boundary  # a new segment's reset of the level was checked too
    assert (env.level > 1.0).any()  # Increase goes above plan once the stop has passed


def test_change_switches_the_activity_type():
    env = make(16, seed=9)
    td = env.reset()
    before = td["activity"].clone()
    td = step_mdp(env.step(td.set("action", torch.full((16,), CHANGE))))
    switched = [int(a) == CHANGE_TO[int(b)] for a, b in zip(td["activity"], before)]
    assert sum(switched) >= 12  # all but the elements whose timeline started a new segment on that step


def test_heart_rate_follows_intensity_with_a_lag():
    env = make(16, seed=4, episode_length=500)
    td = env.reset()
    for _ in range(40):
        td = step_mdp(env.step(td.set("action", torch.full((16,), INCREASE))))
    hr0 = td["heart_rate"].squeeze(-1)
    trace = []
    for _ in range(60):
        td = step_mdp(env.step(td.set("action", torch.full((16,), ALERT))))
        trace.append(td["heart_rate"].squeeze(-1))
    hr = torch.stack(trace, 1)
    drop1, drop60 = hr0 - hr[:, 0], hr0 - hr[:, -1]
    sel = drop60 > 15
    assert sel.sum() >= 4
    assert (drop1[sel] < 0.3 * drop60[sel]).all()  # not at once (first-order lag, tau 12-25 s) ...
    assert (hr[sel, 30] < hr0[sel] - 0.5 * drop60[sel]).all()  # ... but most of the way within 30 s


def test_seeding_is_reproducible():
    actions = torch.randint(5, (30, 4), generator=torch.Generator().manual_seed(0))

    def run(seed):
        env = make(4, seed=seed)
        td = env.reset()
        outs = []
        for t in range(30):
            td = env.step(td.set("action", actions[t]))
            outs.append(td["next"].select("imu", "hr_features", "heart_rate", "reward").clone())
            td = step_mdp(td)
        return torch.stack(outs)

    a, b, c = run(11), run(11), run(12)
    assert (a == b).all()
    assert not torch.equal(a["heart_rate"], c["heart_rate"])
    env = make(4, seed=0)
    env.set_seed(5)
    r1 = env.rollout(10, const_policy(CONTINUE))
    env.set_seed(5)
    r2 = env.rollout(10, const_policy(CONTINUE))
    assert (r1 == r2).all()


def test_real_data_folder(tmp_path):
    write_synthetic_pamap2(tmp_path, subjects=(104,), duration_s=200.0, seed=1)
    env = make_health_env(data_dir=str(tmp_path), batch_size=2, seed=0, episode_length=50)
    assert env.subjects == (104,)
    check_env_specs(env)
    td = env.rollout(60, break_when_any_done=False)
    assert td["next", "heart_rate"].isfinite().all()


def test_invalid_arguments():
    with pytest.raises(ValueError, match="reward_weights"):
        make(2, reward_weights=(1.0, 2.0))
    with pytest.raises(ValueError, match="subjects"):
        make(2, subjects=[99])
    with pytest.raises(ValueError, match="health env id"):
        make_health_env("MiniGrid-Empty-5x5-v0")
    with pytest.raises(ValueError, match="batch_size"):
        make(0)


def test_gain_jitter_scales_each_episodes_gain_and_the_dynamics_use_it():
    """``gain_jitter=j``: each reset draws the episode's gain in ``gain_subject * [1 - j, 1 + j]``; the next heart
    rate follows Eq. 3 with that gain (noise-free step), not the subject's own; ``j = 0`` leaves episodes as they
    were (no extra random draw); the planning copy keeps the option."""
    env = make(256, seed=2, gain_jitter=0.25)
    td = env.reset()
    st = env._st
    ratio = st.gain / env._gain[st.subject_index]
    assert 0.75 <= ratio.min() < 0.8 and 1.2 < ratio.max() <= 1.25
    level = st.level.clone()
    met_eff = (env._met[env._effective_activity()] - 1.0) * level
    hr0, fatigue0, gain = st.hr.clone(), st.fatigue.clone(), st.gain.clone()
    td.set("action", torch.full((256,), CONTINUE)).set("hr_noise", torch.zeros(256))
    out = env.step(td)
    expected = hr0 + st.alpha * (st.hr_rest + gain * met_eff + st.drift * fatigue0 - hr0)
    own = hr0 + st.alpha * (st.hr_rest + env._gain[st.subject_index] * met_eff + st.drift * fatigue0 - hr0)
    hr = out["next", "heart_rate"].squeeze(-1)
    assert torch.allclose(hr, expected.clamp(35.0, 230.0), atol=1e-3)
    assert (hr - own).abs().max() > 1.0
    assert env.planning_copy(2).gain_jitter == 0.25

    plain, zero = make(4, seed=7), make(4, seed=7, gain_jitter=0.0)
    actions = torch.randint(5, (25, 4), generator=torch.Generator().manual_seed(1))
    runs = []
    for e in (plain, zero):
        td, trace = e.reset(), []
        for t in range(25):
            td = e.step(td.set("action", actions[t]))
            trace.append(td["next", "heart_rate"].clone())
            td = step_mdp(td)
        runs.append(torch.stack(trace))
    assert torch.equal(runs[0], runs[1])
    with pytest.raises(ValueError, match=r"gain_jitter: expected a fraction in \[0, 1\)"):
        make(2, gain_jitter=1.5)
