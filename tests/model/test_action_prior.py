"""``model.action_prior`` / ``network.action_prior``: a threshold rule added to the actor's logits (closed form,
validation, and end to end: a policy carrying the heart-rate rule evaluates to exactly the rule's return)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.objectives import ClipPPOLoss

from freamer_rl import cli
from freamer_rl.errors import ConfigError, EnvSetupError
from freamer_rl.health.reference import make_reference_policy
from freamer_rl.model.action_prior import ActionPriorConfig, ThresholdRulePrior, check_prior_key
from freamer_rl.model.heads import build_actor, build_critic
from freamer_rl.run.evaluation import run_episodes
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
HR_RULE = ["action_prior.key=heart_rate", "action_prior.thresholds=[150, 185]", "action_prior.actions=[0, 1, 4]"]
# freamer_rl.health.reference.HeartRateControllerPolicy as a prior: Increase below 145 bpm while the level is below plan
HR_CONTROLLER = [
    "action_prior.key=heart_rate",
    "action_prior.thresholds=[145, 150, 185]",
    "action_prior.actions=[2, 0, 1, 4]",
    "action_prior.condition.key=level",
    "action_prior.condition.threshold=0.99",
    "action_prior.condition.actions=[0, 0, 1, 4]",
]


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
@pytest.mark.parametrize("trailing_one", [False, True])
def test_threshold_rule_prior_closed_form(batch, trailing_one):
    """Strict ``>``: 150 stays Continue, 150.5 is Rest, 185 stays Rest, 185.5 is Alert; ``logit`` on that action."""
    prior = ThresholdRulePrior([150.0, 185.0], [0, 1, 4], num_actions=5, logit=2.5)
    values = torch.tensor([20.0, 150.0, 150.5, 185.0, 185.5, 230.0])
    expected_actions = torch.tensor([0, 0, 1, 1, 4, 4])
    for v, a in zip(values, expected_actions):
        x = v.expand(*batch, 1) if trailing_one else v.expand(batch)
        out = prior(x, torch.zeros(*batch, 5))
        assert out.shape == (*batch, 5)
        want = torch.zeros(5)
        want[a] = 2.5
        assert torch.equal(out.reshape(-1, 5), want.expand(out.reshape(-1, 5).shape)), (v, a)


def test_an_interval_without_prior_adds_nothing():
    """``actions: [-1, 1, 4]``: below the first threshold the head alone decides (a zero row), above it the rule."""
    prior = ThresholdRulePrior([150.0, 185.0], [-1, 1, 4], num_actions=5, logit=5.0)
    out = prior(torch.tensor([[120.0], [150.0], [160.0], [190.0]]), torch.zeros(4, 5))
    want = torch.zeros(4, 5)
    want[2, 1] = want[3, 4] = 5.0
    assert torch.equal(out, want)


@pytest.mark.parametrize("batch", [(), (4,), (2, 4)])
def test_a_condition_picks_the_row_of_actions(batch):
    """``y <= threshold``: the first row (Increase below 145); ``y > threshold``: the condition's row (Continue
    there); the heart-rate buckets are the same in both rows. Without ``y`` a conditioned prior refuses to run."""
    prior = ThresholdRulePrior([145.0, 150.0, 185.0], [2, 0, 1, 4], 5, 5.0, 0.99, [-1, 0, 1, 4])
    cases = [(100.0, 0.5, 2), (100.0, 1.0, None), (147.0, 0.5, 0), (147.0, 1.25, 0), (160.0, 0.0, 1), (190.0, 1.0, 4)]
    for hr, level, action in cases:
        out = prior(torch.full((*batch, 1), hr), torch.zeros(*batch, 5), torch.full((*batch, 1), level))
        want = torch.zeros(5)
        if action is not None:  # -1 in the condition's row: no prior there
            want[action] = 5.0
        assert out.shape == (*batch, 5) and torch.equal(out.reshape(-1, 5), want.expand(out.reshape(-1, 5).shape))
    with pytest.raises(ValueError, match="has a condition: pass its observation y"):
        prior(torch.full((3, 1), 100.0), torch.zeros(3, 5))
    plain = ThresholdRulePrior([150.0, 185.0], [0, 1, 4], 5, 2.0)
    assert set(plain.state_dict()) == {"thresholds", "actions"}  # checkpoints of unconditioned priors unchanged


def _spec() -> Composite:
    return Composite(
        hidden=Unbounded(shape=(8,)),
        heart_rate=Unbounded(shape=(1,)),
        level=Unbounded(shape=(1,)),
        imu=Unbounded(shape=(36,)),
    )


def test_actor_with_the_prior_starts_as_the_rule_and_ppo_trains_its_head():
    """The initial head is near zero, so the mode is the rule's action; ``ClipPPOLoss`` runs on the actor unchanged
    and its gradient reaches the head (the prior has no parameters)."""
    torch.manual_seed(0)
    prior = ActionPriorConfig(key="heart_rate", thresholds=[150.0, 185.0], actions=[0, 1, 4], logit=2.0)
    actor = build_actor(Categorical(5), 8, 16, prior=prior)
    critic = build_critic(8, 16)
    assert sum(p.numel() for p in actor.parameters()) == 8 * 16 + 16 + 16 * 5 + 5
    hr = torch.tensor([[120.0], [160.0], [190.0], [150.0]])
    from tensordict import TensorDict

    td = TensorDict({"hidden": torch.randn(4, 8), "heart_rate": hr}, batch_size=[4])
    out = actor(td.clone())
    assert torch.equal(out["logits"].argmax(-1), torch.tensor([0, 1, 4, 0]))
    probs = out["logits"].softmax(-1).gather(-1, torch.tensor([[0], [1], [4], [0]]))
    assert torch.allclose(probs, torch.full_like(probs, 7.389 / (7.389 + 4)), atol=0.02)  # e^2 / (e^2 + 4)
    batch = out.detach()
    batch.set(("next", "reward"), torch.ones(4, 1))
    batch.set(("next", "done"), torch.zeros(4, 1, dtype=torch.bool))
    batch.set(("next", "terminated"), torch.zeros(4, 1, dtype=torch.bool))
    batch.set("advantage", torch.tensor([[1.0], [-1.0], [1.0], [-1.0]]))
    batch.set("value_target", torch.ones(4, 1))
    loss = ClipPPOLoss(actor, critic)
    terms = loss(batch)
    terms["loss_objective"].backward()
    assert actor.module[0].module.head[2].weight.grad.abs().sum() > 0


@pytest.mark.parametrize(
    ("prior", "message"),
    [
        (["action_prior.key=heart_rate", "action_prior.thresholds=[]"], r"thresholds: give at least one"),
        (
            ["action_prior.key=heart_rate", "action_prior.thresholds=[185, 150]"],
            r"thresholds: expected strictly ascending",
        ),
        (
            ["action_prior.key=heart_rate", "action_prior.thresholds=[150]", "action_prior.actions=[0]"],
            r"actions: expected len\(thresholds\) \+ 1 = 2",
        ),
        ([*HR_RULE[:2], "action_prior.actions=[0, -2, 4]"], r"actions: expected action indices >= 0"),
        ([*HR_RULE, "action_prior.logit=-1.0"], r"logit: expected a value >= 0"),
        ([*HR_RULE[:2], "action_prior.actions=[-1, -1, -1]"], r"actions: expected action indices >= 0 \(or -1"),
        (["action_prior.thresholds=[150]", "action_prior.actions=[0, 1]"], r"key: thresholds/actions are set"),
        ([*HR_RULE, "action_prior.condition.actions=[0, 1, 4]"], r"condition\.key: actions are set but key is null"),
        ([*HR_RULE, "action_prior.condition.key=heart_rate"], r"condition\.key: 'heart_rate' is the prior's own key"),
        (
            [*HR_CONTROLLER[:5], "action_prior.condition.actions=[0, 1, 4]"],
            r"condition\.actions: expected one action per",
        ),
        ([*HR_CONTROLLER[:5], "action_prior.condition.actions=[0, -3, 1, 4]"], r"condition\.actions: expected action"),
        (
            [*HR_CONTROLLER[:4], "action_prior.condition.threshold=.nan"],
            r"condition\.threshold: got nan, expected a finite",
        ),
    ],
)
@pytest.mark.parametrize(
    ("recipe", "section"), [("baselines/ppo_mlp_health.yaml", "network"), ("health_model_free.yaml", "model")]
)
def test_bad_prior_fields_are_named(recipe, section, prior, message):
    with pytest.raises(ConfigError, match=rf"{section}\.action_prior\.{message}"):
        load_config(ROOT / "recipes" / recipe, [f"{section}.{o}" for o in prior])


def test_prior_key_must_be_one_scalar_observation_with_known_actions():
    check_prior_key(ActionPriorConfig("heart_rate", [150.0], [0, 1]), _spec(), Categorical(5), "network")
    with pytest.raises(EnvSetupError, match=r"network\.action_prior\.key: 'pulse' is not an observation"):
        check_prior_key(ActionPriorConfig("pulse", [150.0], [0, 1]), _spec(), Categorical(5), "network")
    with pytest.raises(EnvSetupError, match=r"model\.action_prior\.key: 'imu' has shape \[36\]"):
        check_prior_key(ActionPriorConfig("imu", [150.0], [0, 1]), _spec(), Categorical(5), "model")
    with pytest.raises(EnvSetupError, match=r"network\.action_prior\.actions: \[0, 7\] names an action >= the env's 5"):
        check_prior_key(ActionPriorConfig("heart_rate", [150.0], [0, 7]), _spec(), Categorical(5), "network")
    controller = ActionPriorConfig("heart_rate", [145.0, 150.0], [2, 0, 1])
    controller.condition.key, controller.condition.threshold, controller.condition.actions = "level", 0.99, [0, 0, 1]
    check_prior_key(controller, _spec(), Categorical(5), "network")
    controller.condition.key = "imu"
    with pytest.raises(EnvSetupError, match=r"network\.action_prior\.condition\.key: 'imu' has shape \[36\]"):
        check_prior_key(controller, _spec(), Categorical(5), "network")
    controller.condition.key, controller.condition.actions = "level", [0, 6, 1]
    with pytest.raises(EnvSetupError, match=r"network\.action_prior\.condition\.actions: \[0, 6, 1\] names an action"):
        check_prior_key(controller, _spec(), Categorical(5), "network")
    with pytest.raises(EnvSetupError, match=r"model\.action_prior: needs a discrete action"):
        check_prior_key(ActionPriorConfig("heart_rate", [150.0], [0, 1]), _spec(), Unbounded(shape=(2,)), "model")
    with pytest.raises(EnvSetupError, match=r"action_prior: needs a discrete action"):
        build_actor(Unbounded(shape=(2,)), 8, 16, prior=ActionPriorConfig("heart_rate", [150.0], [0, 1]))


@pytest.mark.parametrize(("rule_name", "rule_overrides"), [("hr_threshold", HR_RULE), ("hr_controller", HR_CONTROLLER)])
@pytest.mark.parametrize(
    ("recipe", "section"), [("baselines/ppo_mlp_health.yaml", "network"), ("health_model_free.yaml", "model")]
)
def test_a_policy_with_the_heart_rate_prior_scores_exactly_the_rule(
    recipe, section, rule_name, rule_overrides, tmp_path, capsys
):
    """Trained on one tiny batch, the deterministic policy is still the rule: its held-out evaluation return is the
    rule's on the same episodes (the prior is in the saved policy, read back by ``freamer-rl eval``); the heart-rate
    rule as a one-key prior, the controller as a prior with a condition on the env's ``"level"``."""
    common = [
        "env.options.synthetic_duration_s=300.0",
        "env.options.episode_length=40",
        "env.options.subjects=[102, 108]",
        "env.eval_options.subjects=[106]",
    ]
    tiny = ["env.num_envs=2", "ppo.frames_per_batch=64", "ppo.minibatch_size=32", "ppo.epochs=1"]
    tiny += ["run.total_frames=64", "logging.progress_bar=false"]
    run = tmp_path / "run"
    overrides = [*common, *tiny, *(f"{section}.{o}" for o in rule_overrides)]
    assert cli.main(["train", str(ROOT / "recipes" / recipe), *overrides, "--run-dir", str(run)]) == 0
    capsys.readouterr()
    assert cli.main(["eval", str(run), "--episodes", "4", "--num-envs", "4", "--deterministic"]) == 0
    ours = json.loads(capsys.readouterr().out)
    cfg = load_config(ROOT / "recipes" / recipe, common)
    rule = run_episodes(cfg, make_reference_policy(rule_name), [], episodes=4, deterministic=True, num_envs=4)
    cont = run_episodes(cfg, make_reference_policy("continue"), [], episodes=4, deterministic=True, num_envs=4)
    assert rule["return_mean"] != pytest.approx(cont["return_mean"], abs=1.0)  # the rule acts on these episodes
    assert ours["return_mean"] == pytest.approx(rule["return_mean"], abs=1e-4)
    if rule_name == "hr_controller":  # the controller's Increase acts on these episodes: not the plain rule's return
        plain = run_episodes(cfg, make_reference_policy("hr_threshold"), [], episodes=4, deterministic=True, num_envs=4)
        assert ours["return_mean"] != pytest.approx(plain["return_mean"], abs=0.1)
    if (
        section == "network" and rule_name == "hr_threshold"
    ):  # benchmarks/health_action_profile.py: its actions per heart-rate bucket are the rule's
        spec = importlib.util.spec_from_file_location("profile", ROOT / "benchmarks" / "health_action_profile.py")
        script = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(script)
        assert script.main([str(run), "--episodes", "2"]) == 0
        profile = json.loads((run / "action_profile.json").read_text())
        assert profile["counts"] == profile["rule_counts"]
        assert sum(sum(c) for c in profile["counts"].values()) == 80  # 2 episodes of 40 steps
        assert sum(profile["counts"]["<130"]) < 80  # the rule has more than one bucket to act on
