"""Reference policies of the health env (the yardstick of the imagination-trained policy)."""

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from freamer_rl.health.config import load_health_config
from freamer_rl.health.evaluation import rollout_metrics
from freamer_rl.health.reference import (
    ACTION_NAMES,
    REFERENCE_POLICIES,
    ConstantActionPolicy,
    HeartRateControllerPolicy,
    HeartRateThresholdPolicy,
    UniformRandomPolicy,
    evaluate_reference,
    make_reference_policy,
)
from freamer_rl.run import env_registry

ROOT = Path(__file__).resolve().parents[2]
BATCH_SHAPES = [(), (2,), (3, 2)]


@pytest.fixture(autouse=True)
def health_adapter(monkeypatch):
    if "health" not in env_registry.available_adapters():
        from freamer_rl_envs.health import make_health_env as factory

        orig = env_registry.get_env_factory
        monkeypatch.setattr(env_registry, "get_env_factory", lambda a: factory if a == "health" else orig(a))


def tiny_cfg():
    return load_health_config(
        ROOT / "recipes" / "health" / "health_mlp.yaml",
        [
            "env.episode_length=40",
            "eval.num_envs=3",
            "eval.horizon_context=4",
            "eval.horizon_max=8",
            "world_model.seq_len=8",
        ],
    )


def test_action_names_match_env():
    from freamer_rl_envs.health import HEALTH_ACTIONS

    assert ACTION_NAMES == HEALTH_ACTIONS


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_policies_write_actions_of_the_batch_shape(batch):
    hr = torch.tensor([100.0, 155.0, 190.0, 120.0, 170.0, 80.0]).reshape(-1)[: max(1, torch.Size(batch).numel())]
    td = TensorDict({"heart_rate": hr.reshape(*batch, 1)}, batch_size=batch)
    for a, name in enumerate(ACTION_NAMES):
        out = make_reference_policy(name)(td.clone())
        assert out["action"].shape == batch and out["action"].dtype == torch.int64
        assert (out["action"] == a).all()
    out = UniformRandomPolicy(seed=0)(td.clone())
    assert out["action"].shape == batch and ((out["action"] >= 0) & (out["action"] < 5)).all()
    out = HeartRateThresholdPolicy(rest_above=150.0, alert_above=185.0)(td.clone())
    expected = torch.where(hr > 185, 4, torch.where(hr > 150, 1, 0)).reshape(batch)
    assert torch.equal(out["action"], expected)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_controller_increases_only_below_its_threshold_and_below_plan(batch):
    """The rule's Rest / Alert above 150 / 185 bpm wherever the level is; Increase below 145 bpm only where the level
    is below 1 (never above plan); Continue from 145 to 150 and wherever the level is at plan."""
    hr = torch.tensor([100.0, 100.0, 144.9, 145.0, 149.0, 155.0, 190.0, 120.0])
    level = torch.tensor([0.75, 1.0, 0.5, 0.5, 0.25, 0.5, 0.0, 1.25])
    expected = torch.tensor([2, 0, 2, 0, 0, 1, 4, 0])
    n = max(1, torch.Size(batch).numel())
    idx = torch.arange(n) % len(hr)
    td = TensorDict(
        {"heart_rate": hr[idx].reshape(*batch, 1), "level": level[idx].reshape(*batch, 1)}, batch_size=batch
    )
    out = make_reference_policy("hr_controller")(td)
    assert out["action"].shape == batch and torch.equal(out["action"], expected[idx].reshape(batch))
    with pytest.raises(ValueError, match="increase_below"):
        HeartRateControllerPolicy(increase_below=155.0)


def test_controller_restores_the_level_the_rule_leaves_down():
    """On the same episodes of the most active synthetic subject the rule rests and its level stays below plan
    until the next activity segment; the controller brings it back (more steps at plan) and returns more."""
    cfg = load_health_config(
        ROOT / "recipes" / "health" / "health_mlp.yaml",
        ["env.id=pamap2-health-varied", "env.rate_hz=0.2", "env.episode_length=120", "env.subjects=[106]"]
        + ["eval.num_envs=8", "eval.horizon_context=4", "eval.horizon_max=8", "world_model.seq_len=8"],
    )
    from freamer_rl.health.reference import reference_rollout

    rule, ctrl = reference_rollout(cfg, "hr_threshold"), reference_rollout(cfg, "hr_controller")
    rule_below = (rule.get("level") < 1.0).float().mean()
    ctrl_below = (ctrl.get("level") < 1.0).float().mean()
    assert (rule.get("action") == 1).any() and (ctrl.get("action") == 2).any()
    assert ctrl_below < 0.5 * rule_below
    assert rollout_metrics(ctrl)["return_mean"] > rollout_metrics(rule)["return_mean"] + 3.0


def test_oracle_is_registered_with_its_defaults():
    from freamer_rl.health.oracle import ORACLE_DEFAULTS, OraclePlanner

    assert "oracle" in REFERENCE_POLICIES
    planner = make_reference_policy("oracle")
    assert isinstance(planner, OraclePlanner)
    assert (planner.horizon, planner.depth) == (ORACLE_DEFAULTS["horizon"], ORACLE_DEFAULTS["depth"])
    assert [type(t).__name__ for t in planner.tails] == ["ConstantActionPolicy", "HeartRateThresholdPolicy"]
    assert planner.num_candidates == 5**planner.depth * 2
    assert make_reference_policy("oracle", depth=1, horizon=3, tails=("rest",)).num_candidates == 5


def test_random_policy_is_seeded_and_covers_actions():
    td = TensorDict({}, batch_size=(500,))
    a1 = UniformRandomPolicy(seed=3)(td.clone())["action"]
    a2 = UniformRandomPolicy(seed=3)(td.clone())["action"]
    assert torch.equal(a1, a2)
    assert set(a1.tolist()) == set(range(5))


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="unknown reference policy"):
        make_reference_policy("sprint")
    with pytest.raises(ValueError, match="action"):
        ConstantActionPolicy(7)
    with pytest.raises(ValueError, match="rest_above"):
        HeartRateThresholdPolicy(rest_above=190.0, alert_above=180.0)
    with pytest.raises(ValueError, match="heart_rate"):
        HeartRateThresholdPolicy()(TensorDict({"heart_rate": torch.zeros(2, 3)}, batch_size=(2,)))


def test_evaluate_reference_protocol():
    """Same episodes for every policy (env seed eval.seed); Rest never enters the danger zone; metrics are those of
    the episode ends; a rollout shorter than an episode is an error, not a silent number."""
    cfg = tiny_cfg()
    small = {"oracle": {"depth": 2, "horizon": 6}}  # a smaller search than the default keeps the test fast
    res = {
        name: evaluate_reference(cfg, make_reference_policy(name, **small.get(name, {}))) for name in REFERENCE_POLICIES
    }
    for m in res.values():
        assert m["episodes"] == 3 and m["length_mean"] <= 40
    assert res["rest"]["violations_mean"] == 0.0
    assert res["continue"] == evaluate_reference(cfg, "continue")  # deterministic given the env seed
    assert res["increase"]["violations_mean"] >= res["continue"]["violations_mean"]
    assert res["oracle"]["return_mean"] >= max(m["return_mean"] for m in res.values())  # the ceiling
    from freamer_rl.health.agent import make_health_env

    env = make_health_env(cfg, num_envs=2, seed=0)
    traj = env.rollout(10, make_reference_policy("continue"), break_when_any_done=False)
    with pytest.raises(ValueError, match="never reached done"):
        rollout_metrics(traj)
