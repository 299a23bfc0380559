"""The oracle planner (issue 22): plans on the env's own simulator, leaves the real env untouched, beats the rules."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from freamer_rl.data import HRFeatureParams, met_table
from freamer_rl.health.agent import make_health_env as make_cfg_env
from freamer_rl.health.config import load_health_config
from freamer_rl.health.evaluation import rollout_metrics
from freamer_rl.health.oracle import OraclePlanner, planning_env
from freamer_rl.health.reference import (
    ACTION_NAMES,
    bootstrap_mean_ci,
    ceiling_table,
    episode_returns,
    evaluate_reference,
    format_ceiling_table,
    make_reference_policy,
    reference_rollout,
)
from freamer_rl.run import env_registry
from freamer_rl_envs.health import ALERT, CHANGE_TO, HealthDynamics, exertion, fatigue_update, make_health_env

ROOT = Path(__file__).resolve().parents[2]
SMALL = {"horizon": 6, "depth": 2}  # 50 candidates: fast, and enough to beat the rules on the tiny config


@pytest.fixture(autouse=True)
def health_adapter(monkeypatch):
    if "health" not in env_registry.available_adapters():
        orig = env_registry.get_env_factory
        monkeypatch.setattr(env_registry, "get_env_factory", lambda a: make_health_env if a == "health" else orig(a))


def tiny_cfg(*extra):
    overrides = ["env.episode_length=40", "eval.num_envs=3", "eval.horizon_context=4", "eval.horizon_max=8"]
    return load_health_config(ROOT / "recipes" / "health" / "health_mlp.yaml", [*overrides, *extra])


def random_rollout(env, steps=60, seed=7):
    g = torch.Generator().manual_seed(seed)

    def policy(td):
        td["action"] = torch.randint(0, 5, td.batch_size, generator=g)
        return td

    return env.rollout(steps, policy, break_when_any_done=False)


def test_env_numerics_unchanged_by_the_planning_seam():
    """Recorded on envs/health.py before snapshot/restore/planning_copy/hr_noise were added (random actions,
    auto-resets after truncation and termination included)."""
    traj = random_rollout(make_health_env(batch_size=4, episode_length=25, rate_hz=0.2, seed=3))
    r = traj["next", "reward"].squeeze(-1)
    assert int(traj["next", "done"].sum()) == 8
    torch.testing.assert_close(r.sum(1), torch.tensor([13.42441, 34.73177, 8.65194, 7.23967]), atol=2e-4, rtol=0)
    expected = [
        [0.6459, -0.13369, 0.32126, 0.10523],
        [0.82024, 0.38452, 0.87513, 0.40042],
        [0.61126, -0.1678, -0.14754, 0.67978],
        [0.04328, -0.13339, 0.34007, -0.54399],
    ]
    torch.testing.assert_close(r[:, ::15], torch.tensor(expected), atol=2e-5, rtol=0)


def test_snapshot_restore_replays_exactly():
    env = make_health_env(batch_size=3, episode_length=30, rate_hz=0.2, seed=1)
    env.reset()
    random_rollout(env, steps=7, seed=2)  # somewhere mid-episode, with Change / Alert state
    state = env.snapshot()
    first = random_rollout(env, steps=10, seed=5)
    env.restore(state)
    again = random_rollout(env, steps=10, seed=5)
    assert torch.equal(first["next", "reward"], again["next", "reward"])
    assert torch.equal(first["next", "imu"], again["next", "imu"])  # the generator state came back too


def test_restore_with_index_and_its_errors():
    env = make_health_env(batch_size=3, episode_length=30, rate_hz=0.2, seed=1)
    env.reset()
    copy = env.planning_copy(5)
    assert copy.batch_size == (5,) and copy.dyn == env.dyn and copy.episode_length == 30
    index = torch.tensor([2, 2, 0, 1, 0])
    copy.restore(env.snapshot(), index=index)
    assert torch.equal(copy.cursor, env.cursor[index]) and torch.equal(copy.subject_index, env.subject_index[index])
    state = env.snapshot()
    with pytest.raises(KeyError, match="hr"):
        copy.restore({k: v for k, v in state.items() if k != "hr"}, index=index)
    with pytest.raises(ValueError, match="index"):
        copy.restore(state, index=index[:3])
    with pytest.raises(ValueError, match=r"'subject_index' must be torch.int64 \(5,\), got torch.int64 \(3,\)"):
        copy.restore(state)  # 3 rows into a 5-row env
    assert env.planning_copy(2, hr_noise=0.0).dyn.hr_noise == 0.0


def test_injected_noise_replaces_the_draw():
    """Zero injected noise is the noise-free env; the given draw is used as N(0, 1) (scaled by hr_noise sqrt(dt))."""
    env = make_health_env(batch_size=2, episode_length=30, rate_hz=0.2, seed=4)
    env.reset()
    quiet, noisy = env.planning_copy(2, hr_noise=0.0), env.planning_copy(2)
    for e in (quiet, noisy):
        e.restore(env.snapshot(), index=torch.arange(2))
    a = torch.zeros(2, dtype=torch.int64)
    hr_quiet = quiet.step(TensorDict({"action": a}, batch_size=[2]))["next", "heart_rate"]
    z = torch.tensor([1.0, -2.0])
    hr_noisy = noisy.step(TensorDict({"action": a, "hr_noise": z}, batch_size=[2]))["next", "heart_rate"]
    torch.testing.assert_close(hr_noisy.squeeze(-1) - hr_quiet.squeeze(-1), z * math.sqrt(5.0), atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="hr_noise"):
        noisy.step(TensorDict({"action": a, "hr_noise": torch.zeros(2, 1)}, batch_size=[2]))


def test_first_action_is_the_argmax_of_the_closed_form_returns():
    """Horizon 1, one step per action from a hand-set state (running, HR 175 in the danger zone, level 1): the
    planner's returns are Eq. A11 of the noise-free heart-rate step, computed here by hand, and it plays the argmax
    (Alert: free above 160 bpm and it drops the heart rate most)."""
    env = make_health_env(batch_size=1, episode_length=30, rate_hz=0.2, seed=0)
    env.reset()
    state = env.snapshot()
    state.update(
        planned=torch.tensor([5]), override=torch.tensor([-1]), level=torch.ones(1), hold=torch.zeros(1).long()
    )
    state.update(hr=torch.tensor([175.0]), fatigue=torch.tensor([0.2]), steps=torch.zeros(1).long())
    env.restore(state)
    planner = OraclePlanner([make_reference_policy("continue")], horizon=1, depth=1).bind(env)
    obs = TensorDict({}, batch_size=[1])
    returns, first = planner.plan(obs)
    assert torch.equal(first, torch.arange(5)[None])

    dyn, p, met = HealthDynamics(), HRFeatureParams(), torch.as_tensor(met_table(), dtype=torch.float32)
    hr_rest, gain, alpha, drift = (state[k] for k in ("hr_rest", "gain", "alpha", "drift"))
    level = {0: 1.0, 1: 0.75, 2: 1.25, 3: 1.0, 4: 0.0}
    activity = {a: 5 for a in range(5)} | {3: CHANGE_TO[5]}
    target = min(float(hr_rest + gain * (met[5] - 1.0)), dyn.hr_target_cap)
    expected = []
    for a in range(5):
        hr_ss = hr_rest + gain * (met[activity[a]] - 1.0) * level[a] + drift * 0.2
        hr = 175.0 + alpha * (hr_ss - 175.0)
        fat = fatigue_update(torch.tensor([0.2]), exertion(hr, hr_rest, p), 5.0, p)
        danger = float(hr > 160.0) * (1.0 + (hr - 160.0) / 20.0)
        r = 2.0 * -danger + math.exp(-0.5 * ((float(hr) - target) / 10.0) ** 2) - 0.5 * fat
        expected.append(float(r))
    torch.testing.assert_close(returns[0], torch.tensor(expected), atol=1e-4, rtol=0)
    out = planner(obs)
    assert int(out["action"]) == int(np.argmax(expected)) == ALERT


def test_planning_leaves_the_real_env_untouched():
    """Two envs from the same seed take the same actions; one is planned on before every step: same rollout."""
    a = make_health_env(batch_size=2, episode_length=20, rate_hz=0.2, seed=9)
    b = make_health_env(batch_size=2, episode_length=20, rate_hz=0.2, seed=9)
    planner = make_reference_policy("oracle", noise_samples=2, **SMALL).bind(a)
    td_a, td_b = a.reset(), b.reset()
    for t in range(12):
        before = a.snapshot()
        planner.plan(td_a)
        after = a.snapshot()
        assert all(torch.equal(before[k], after[k]) for k in before)
        act = torch.tensor([t % 5, (3 * t) % 5])
        td_a = a.step(td_a.set("action", act))["next"]
        td_b = b.step(td_b.set("action", act))["next"]
        assert torch.equal(td_a["reward"], td_b["reward"]) and torch.equal(td_a["imu"], td_b["imu"])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_oracle_beats_the_rules_on_the_same_episodes(seed):
    cfg = tiny_cfg()
    oracle = evaluate_reference(cfg, make_reference_policy("oracle", **SMALL), seed=seed)
    for name in ("hr_threshold", "continue", "rest", "increase", "change", "alert", "random"):
        assert oracle["return_mean"] >= evaluate_reference(cfg, name, seed=seed)["return_mean"], name


def test_protocol_identical_to_evaluate_reference():
    """The oracle's numbers are evaluate_policy's protocol: a fresh env of eval.num_envs from eval.seed,
    env.episode_length steps, metrics at each env's first done."""
    cfg = tiny_cfg()
    env = make_cfg_env(cfg, num_envs=cfg.eval.num_envs, seed=cfg.eval.seed)
    planner = make_reference_policy("oracle", **SMALL).bind(env)
    by_hand = rollout_metrics(env.rollout(cfg.env.episode_length, planner, break_when_any_done=False))
    assert evaluate_reference(cfg, make_reference_policy("oracle", **SMALL)) == by_hand
    traj = reference_rollout(cfg, "continue")
    assert traj.shape == (3, 40)
    assert float(episode_returns(traj).mean()) == pytest.approx(evaluate_reference(cfg, "continue")["return_mean"])


def test_ceiling_table_rows_and_markdown():
    cfg = tiny_cfg()
    rows = ceiling_table(cfg, ("oracle", "continue", "rest"), resamples=200, **SMALL)
    by_name = {r["policy"]: r for r in rows}
    assert [r["policy"] for r in rows] == ["oracle", "continue", "rest"]
    assert by_name["oracle"]["fraction_of_oracle"] == 1.0
    assert by_name["oracle"]["fraction_low"] == pytest.approx(1.0) == by_name["oracle"]["fraction_high"]
    cont = evaluate_reference(cfg, "continue")
    assert by_name["continue"]["return_mean"] == pytest.approx(cont["return_mean"])
    ratio = cont["return_mean"] / by_name["oracle"]["return_mean"]
    assert by_name["continue"]["fraction_of_oracle"] == pytest.approx(ratio)
    for r in rows:
        assert r["return_low"] <= r["return_mean"] <= r["return_high"] and r["episodes"] == 3
    text = format_ceiling_table(rows)
    assert text.splitlines()[0].startswith("| policy |") and len(text.splitlines()) == 5 and "| oracle | " in text
    with pytest.raises(ValueError, match="oracle"):
        ceiling_table(cfg, ("continue",))


def test_bootstrap_mean_ci_matches_the_normal_interval():
    x = np.random.default_rng(0).normal(10.0, 2.0, size=400)
    mean, low, high = bootstrap_mean_ci(x, resamples=4000)
    half = 1.96 * x.std() / math.sqrt(x.size)
    assert mean == pytest.approx(x.mean())
    assert (high - low) / 2 == pytest.approx(half, rel=0.1) and low < mean < high
    assert bootstrap_mean_ci(np.full(5, 3.0)) == (3.0, 3.0, 3.0)
    frac = bootstrap_mean_ci(2.0 * x, reference=x, resamples=500)
    assert frac == pytest.approx((2.0, 2.0, 2.0))  # paired: every resample has the same ratio
    with pytest.raises(ValueError, match="reference"):
        bootstrap_mean_ci(x, reference=x[:3])


def test_planner_errors():
    continue_ = make_reference_policy("continue")
    with pytest.raises(ValueError, match="horizon"):
        OraclePlanner([continue_], horizon=2, depth=3)
    with pytest.raises(ValueError, match="depth"):
        OraclePlanner([continue_], depth=0)
    with pytest.raises(ValueError, match="tails"):
        OraclePlanner([])
    with pytest.raises(ValueError, match="tails"):
        make_reference_policy("oracle", tails=("oracle",))
    planner = OraclePlanner([continue_], horizon=2, depth=1)
    with pytest.raises(RuntimeError, match="bind"):
        planner(TensorDict({}, batch_size=[1]))
    with pytest.raises(TypeError, match="snapshot"):
        planning_env(object())
    env = make_health_env(batch_size=2, episode_length=10, rate_hz=0.2, seed=0)
    env.reset()
    with pytest.raises(ValueError, match=r"batch \(2,\)"):
        planner.bind(env)(TensorDict({}, batch_size=[3]))
    assert planner.num_candidates == len(ACTION_NAMES)
