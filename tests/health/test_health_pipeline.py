"""Health run pipeline: recipes/config validation, the online posterior filter of the policy, the imagination-horizon
metric, a tiny end-to-end run of the registry entry (``trainers.health.train``) and the anomaly report."""

import json
import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import ExplorationType, set_exploration_type

from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.health.agent import build_agent, load_agent, make_health_env
from freamer_rl.health.anomaly_report import anomaly_report, record_episode
from freamer_rl.health.config import HealthConfig, health_config_from_dict, load_health_config
from freamer_rl.run import env_registry
from freamer_rl.trainers.health import STRUCTURAL
from freamer_rl.trainers.health import train as train_health
from freamer_rl.world_model.metrics import imagination_horizon

ROOT = Path(__file__).resolve().parents[2]
RECIPES = {k: ROOT / "recipes" / "health" / f"health_{k}.yaml" for k in ("mlp", "cnn", "slotattn", "foundation")}

TINY = [
    "env.num_envs=4",
    "env.episode_length=48",
    "collect.iterations=2",
    "collect.prefill_frames=128",
    "collect.frames_per_iter=64",
    "world_model.seq_len=12",
    "world_model.batch_size=4",
    "world_model.train_steps=2",
    "world_model.prefill_train_steps=2",
    "world_model.deter_dim=16",
    "world_model.stoch_dim=4",
    "world_model.hidden=16",
    "encoder.embed_dim=12",
    "encoder.dim=8",
    "encoder.heads=2",
    "encoder.hr_tokens=2",
    "encoder.hidden=16",
    "encoder.fm_hidden=16",
    "encoder.fm_steps=2",
    "encoder.fno_modes=4",
    "encoder.memory_slots=4",
    "encoder.memory_width=6",
    "imagination.num_seeds=16",
    "imagination.updates=1",
    "imagination.epochs=1",
    "imagination.num_minibatches=2",
    "imagination.policy_hidden=16",
    "eval.num_envs=2",
    "eval.horizon_context=4",
    "eval.horizon_max=8",
    "eval.mse_windows=4",
    "eval.horizon_windows=4",
    "eval.references=[continue]",  # the oracle planner of the default list: test_world_model_options
    "logging.progress_bar=false",
]


@pytest.fixture(autouse=True)
def health_adapter(monkeypatch):
    """Use the registered ``health`` entry point; until the project is reinstalled with it, register it here."""
    if "health" not in env_registry.available_adapters():
        from freamer_rl_envs.health import make_health_env as factory

        orig = env_registry.get_env_factory
        monkeypatch.setattr(env_registry, "get_env_factory", lambda a: factory if a == "health" else orig(a))


@pytest.mark.parametrize("kind", sorted(RECIPES))
def test_recipes_load(kind):
    cfg = load_health_config(RECIPES[kind])
    assert isinstance(cfg, HealthConfig)
    assert cfg.encoder.kind == kind
    assert cfg.imagination.horizon == 15 and cfg.imagination.clip_epsilon == 0.2
    assert cfg.imagination.lr == pytest.approx(1e-4)
    cfg = load_health_config(RECIPES[kind], ["run.seed=3", "collect.iterations=1"])
    assert cfg.run.seed == 3 and cfg.collect.iterations == 1


def test_recipes_share_the_rssm_core():
    cfgs = [load_health_config(p) for p in RECIPES.values()]
    for name in ("world_model", "imagination", "collect", "env"):
        assert len({json.dumps(getattr(c, name).__dict__, sort_keys=True) for c in cfgs}) == 1, name


def test_bad_keys_and_types_name_the_field():
    with pytest.raises(ConfigError, match=r"world_model\.lr_typo"):
        health_config_from_dict({"world_model": {"lr_typo": 1e-3}})
    with pytest.raises(ConfigError, match=r"collect\.iterations"):
        health_config_from_dict({"collect": {"iterations": "many"}})
    with pytest.raises(ConfigError, match=r"encoder\.kind"):
        health_config_from_dict({"encoder": {"kind": "resnet"}})
    with pytest.raises(ConfigError, match=r"encoder\.gate_init"):
        health_config_from_dict({"encoder": {"gate_init": {"vision": 0.0}}})
    with pytest.raises(ConfigError, match=r"collect\.frames_per_iter"):
        health_config_from_dict({"env": {"num_envs": 8}, "collect": {"frames_per_iter": 100}})
    with pytest.raises(ConfigError, match="unknown key 'bogus'"):
        load_health_config(None, ["bogus=1"])
    with pytest.raises(ConfigError, match=r"logging\.backend: expected csv, wandb or tensorboard"):
        load_health_config(None, ["logging.backend=mlflow"])


@pytest.mark.parametrize(
    ("old", "new"), [("run.logger=csv", "logging.backend"), ("run.progress_bar=false", "logging.progress_bar")]
)
def test_health_uses_the_shared_logging_keys(old, new):
    """One key per setting across trainers: the health-only keys of earlier releases are refused naming the new one."""
    with pytest.raises(ConfigError, match=rf"{old.split('=')[0]}: this key was renamed; use {new}"):
        load_health_config(RECIPES["mlp"], [old])
    cfg = load_health_config(RECIPES["mlp"], [f"{new}={old.split('=')[1]}"])
    assert cfg.logging.progress_bar is False if "progress" in new else cfg.logging.backend == "csv"


def test_recipes_explore_and_normalise():
    """The recipes use the non-uniform exploration, the epsilon and the standardised reconstruction targets (the
    fixes of the "always Rest" collapse); the world model built from them has recon_norm on."""
    for path in RECIPES.values():
        cfg = load_health_config(path)
        probs = cfg.collect.explore_probs
        assert probs is not None and len(probs) == 5 and probs[0] == max(probs) and probs[4] == min(probs)
        assert 0.0 < cfg.collect.random_action_prob < 1.0
        assert cfg.world_model.recon_norm
    agent = build_agent(load_health_config(RECIPES["mlp"], TINY))
    assert agent.world_model.recon_norm and agent.world_model.reward_scale == 5.0


def test_exploration_config_errors():
    with pytest.raises(ConfigError, match=r"collect\.random_action_prob"):
        health_config_from_dict({"collect": {"random_action_prob": 1.5}})
    with pytest.raises(ConfigError, match=r"collect\.explore_probs"):
        health_config_from_dict({"collect": {"explore_probs": [1.0, 0.0]}})
    with pytest.raises(ConfigError, match=r"collect\.explore_probs"):
        health_config_from_dict({"collect": {"explore_probs": [1.0, -1.0, 0.0, 0.0, 0.0]}})


def test_policy_exploration_draws_from_explore_probs():
    """random_actions draws from explore_probs; random_action_prob=0 keeps the actor's action; 1 replaces all."""
    torch.manual_seed(0)
    cfg = load_health_config(None, [*TINY, "encoder.kind=mlp"])
    agent = build_agent(cfg)
    only_rest = [0.0, 1.0, 0.0, 0.0, 0.0]
    for kwargs, check in (
        ({"random_actions": True, "explore_probs": only_rest}, lambda a, g: (a == 1).all()),
        ({"random_action_prob": 1.0, "explore_probs": [0.0, 0.0, 0.0, 0.0, 1.0]}, lambda a, g: (a == 4).all()),
        ({"random_action_prob": 0.0, "explore_probs": only_rest}, lambda a, g: torch.equal(a, g)),
    ):
        policy = agent.policy(sample_latent=False, **kwargs)
        env = make_health_env(cfg, num_envs=3, seed=1, primer=policy.make_tensordict_primer())
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            traj = env.rollout(6, policy, break_when_any_done=False)
        greedy = traj["logits"].argmax(-1)
        assert check(traj["action"], greedy), kwargs
    with pytest.raises(ValueError, match="explore_probs"):
        agent.policy(explore_probs=[0.5, 0.5])
    with pytest.raises(ValueError, match="random_action_prob"):
        agent.policy(random_action_prob=-0.1)


def test_policy_filter_matches_world_model_posterior():
    """The online filter of HealthPolicy (foundation encoder: DNC stepped online) gives the posterior that
    WorldModel.observe computes over the recorded episode, and its KL is WorldModel.episode_kl."""
    torch.manual_seed(0)
    cfg = load_health_config(None, [*TINY, "encoder.kind=foundation"])
    agent = build_agent(cfg)
    agent.world_model.eval()
    policy = agent.policy(sample_latent=False)
    env = make_health_env(cfg, num_envs=2, seed=1, primer=policy.make_tensordict_primer())
    with torch.no_grad():
        traj = env.rollout(10, policy, break_when_any_done=False)
        out, _ = agent.world_model.observe(traj, sample=False)
        kl = agent.world_model.episode_kl(traj)
    latent = torch.cat([out["h"], out["post_mean"]], -1)  # [2, 11, L]: position t = after observation t
    torch.testing.assert_close(traj["latent"], latent[:, :-1], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(traj["kl"].squeeze(-1), kl[:, :-1], atol=1e-4, rtol=1e-4)
    assert traj["is_init"][:, 0].all() and not traj["is_init"][:, 1:].any()
    # the lean recording loop of the anomaly report computes the same thing
    env_one = make_health_env(cfg, num_envs=1, seed=3, primer=policy.make_tensordict_primer())
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        one = env_one.rollout(12, policy, break_when_any_done=False)
    rec = record_episode(agent, 12, seed=3)
    assert rec["action"].tolist() == one["action"][0].tolist()
    torch.testing.assert_close(torch.from_numpy(rec["kl"]), one["kl"][0, :, 0], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(torch.from_numpy(rec["heart_rate"]), one["heart_rate"][0, :, 0])
    assert rec["is_first"][0] and not rec["is_first"][1:].any()


def test_imagination_horizon_definition():
    cfg = load_health_config(None, [*TINY, "encoder.kind=mlp"])
    wm = build_agent(cfg).world_model
    with torch.no_grad():  # reward head predicts 0, continuation head "continue"
        wm.reward_head[-1].weight.zero_()
        wm.reward_head[-1].bias.zero_()
        wm.continue_head[-1].weight.zero_()
        wm.continue_head[-1].bias.fill_(10.0)
    N, C, H = 3, 4, 6
    reward = torch.zeros(N, C + H, 1)
    reward[0, C + 2] = 1.0  # error at imagined step 3 -> horizon 2
    reward[1, C + 0] = -0.8  # error at the first imagined step -> horizon 0
    reward[2, :C] = 5.0  # errors only inside the context -> never fails -> H
    windows = TensorDict(
        {
            "imu": torch.randn(N, C + H, 36),
            "hr_features": torch.rand(N, C + H, 16),
            "action": torch.randint(0, 5, (N, C + H)),
            "next": {
                "imu": torch.randn(N, C + H, 36),
                "hr_features": torch.rand(N, C + H, 16),
                "reward": reward,
                "done": torch.zeros(N, C + H, 1, dtype=torch.bool),
                "terminated": torch.zeros(N, C + H, 1, dtype=torch.bool),
            },
        },
        [N, C + H],
    )
    hz = imagination_horizon(wm, windows, C, reward_tol=0.5)
    assert hz.tolist() == [2.0, 0.0, float(H)]
    with torch.no_grad():  # a predicted termination that did not happen ends the horizon at once
        wm.continue_head[-1].bias.fill_(-10.0)
    assert imagination_horizon(wm, windows, C, reward_tol=0.5).tolist() == [0.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    if "health" not in env_registry.available_adapters():
        from freamer_rl_envs.health import make_health_env as factory

        orig = env_registry.get_env_factory
        env_registry.get_env_factory = lambda a: factory if a == "health" else orig(a)
    else:
        orig = None
    try:
        torch.manual_seed(0)
        run_dir = tmp_path_factory.mktemp("health_run")
        cfg = load_health_config(RECIPES["foundation"], [*TINY, "eval.every=1", "collect.iterations=2"])
        summary = train_health(cfg, run_dir)
    finally:
        if orig is not None:
            env_registry.get_env_factory = orig
    return run_dir, summary


def test_run_health_writes_outputs(tiny_run):
    run_dir, summary = tiny_run
    for name in ("config.yaml", "run_info.json", "progress.csv", "summary.json", "checkpoint.pt"):
        assert (run_dir / name).is_file(), name
    on_disk = json.loads((run_dir / "summary.json").read_text())
    assert on_disk["encoder"] == "foundation"
    for k in ("eval_return_mean", "eval_violations_mean", "eval_length_mean", "recon_mse", "imagination_horizon"):
        assert k in summary and math.isfinite(summary[k]), k
    assert summary["eval_length_mean"] <= 48
    assert 0 <= summary["imagination_horizon"] <= 8
    assert summary["frames"] == 128 + 2 * 64
    rows = (run_dir / "progress.csv").read_text().splitlines()
    assert len(rows) == 1 + 3  # header, prefill row, two iterations
    header = rows[0].split(",")
    for col in ("wm_loss_rec", "wm_loss_fm", "ppo_loss_objective", "gate_imu", "eval_return_mean"):
        assert col in header, col
    info = json.loads((run_dir / "run_info.json").read_text())
    assert "commit" in info
    agent = load_agent(run_dir)
    assert agent.cfg.encoder.kind == "foundation"
    # parameter counts of the one table helper, equal to the modules' own counts
    wm = agent.world_model
    assert summary["params_world_model"] == sum(p.numel() for p in wm.parameters())
    assert summary["params_encoder"] == sum(p.numel() for p in wm.encoder.parameters())
    assert summary["params_policy"] == sum(p.numel() for m in (agent.actor, agent.value) for p in m.parameters())
    assert on_disk["trainer"] == "health" and on_disk["algorithm"] == "RSSM world model + imagination PPO"
    assert on_disk["fps"] == pytest.approx(on_disk["frames"] / on_disk["wall_time_s"])


def test_run_health_summary_is_strict_json_and_the_curve_is_drawn(tiny_run):
    run_dir, _ = tiny_run

    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    json.loads((run_dir / "summary.json").read_text(), parse_constant=refuse)
    assert (run_dir / "learning_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # eval.every=1: the evaluation of iteration 1 stays in progress.csv after later rows without one
    rows = (run_dir / "progress.csv").read_text().splitlines()
    header = rows[0].split(",")
    iteration_1 = dict(zip(header, rows[2].split(",")))
    assert iteration_1["iteration"] == "1" and iteration_1["eval_return_mean"] != ""


def test_resume_with_other_weight_sections_is_refused(tiny_run):
    """The structural sections are the registry entry's (trainers.health.STRUCTURAL): world_model shapes weights."""
    run_dir, _ = tiny_run
    assert "world_model" in STRUCTURAL
    cfg = load_health_config(RECIPES["foundation"], [*TINY, "eval.every=1", "world_model.hidden=24"])
    with pytest.raises(CheckpointError, match=r"world_model\.hidden: checkpoint 16 vs now 24"):
        train_health(cfg, run_dir)


def test_anomaly_report_writes_png(tiny_run, tmp_path):
    run_dir, _ = tiny_run
    rate_hz = load_agent(run_dir).cfg.env.rate_hz
    hours = 100 / 3600 / rate_hz  # 100 steps (longer than the 48-step training episodes)
    out = anomaly_report(run_dir / "checkpoint.pt", tmp_path, hours=hours, warmup=5, progress_bar=False)
    png = tmp_path / "anomaly_timeline.png"
    assert png.is_file() and png.stat().st_size > 10_000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out["steps"] == 100
    assert (tmp_path / "anomaly_summary.json").is_file() and (tmp_path / "anomaly_episode.npz").is_file()
    assert 0 <= out["anomalies"] <= 100
    assert math.isfinite(out["kl_mean"])
