"""The health env through the adapter registry for the collector-based trainers: ``env.options`` /
``env.eval_options``, the unbatched env, and held-out evaluation on the health trainer's own episodes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from freamer_rl import cli
from freamer_rl.config.loader import config_from_dict
from freamer_rl.errors import ConfigError
from freamer_rl.health.config import load_health_config
from freamer_rl.health.reference import evaluate_reference, make_reference_policy
from freamer_rl.run import env_registry
from freamer_rl.run.evaluation import run_episodes
from freamer_rl.trainers.minigrid_ppo import FreamerConfig
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
SHORT = {"synthetic_duration_s": 300.0, "rate_hz": 0.2, "episode_length": 20}
TINY_PPO = [
    "env.num_envs=2",
    "ppo.frames_per_batch=64",
    "ppo.minibatch_size=32",
    "ppo.epochs=1",
    "run.total_frames=128",
    "logging.progress_bar=false",
    "env.options.synthetic_duration_s=300.0",
    "env.options.episode_length=20",
]


@pytest.mark.parametrize("batch_size", [None, 1, 3])
def test_unbatched_and_batched_health_envs_pass_the_spec_check(batch_size):
    env = env_registry.make_env("health", "pamap2-health-varied", seed=0, batch_size=batch_size, **SHORT)
    expected = () if batch_size is None else (batch_size,)
    assert tuple(env.batch_size) == expected
    assert tuple(env.observation_spec["imu"].shape) == (*expected, 36)
    assert tuple(env.action_spec.shape) == expected
    check_env_specs(env, seed=0)


def test_the_unbatched_env_gives_the_batch_one_data():
    """Same seed, same actions: the squeezed env's observations, rewards and ends are the batch-1 env's, across
    episode ends (20-step episodes, 45 steps)."""
    single = env_registry.make_env("health", "pamap2-health", seed=3, **SHORT)
    batch1 = env_registry.make_env("health", "pamap2-health", seed=3, batch_size=1, **SHORT)
    actions = torch.randint(0, 5, (45,), generator=torch.Generator().manual_seed(0))
    ta, tb = single.reset(), batch1.reset()
    ends = 0
    for t in range(45):
        ta.set("action", actions[t])
        tb.set("action", actions[t].reshape(1))
        ta, next_a = single.step_and_maybe_reset(ta)
        tb, next_b = batch1.step_and_maybe_reset(tb)
        for key in ("imu", "hr_features", "reward", "done"):
            assert torch.equal(ta["next", key], tb["next", key][0]), (t, key)
        ends += int(ta["next", "done"].any())
        ta, tb = next_a, next_b
    assert ends == 2


def test_env_options_the_adapter_does_not_take_are_refused_in_one_line():
    with pytest.raises(ConfigError, match=r"env\.options\.subjects: the 'minigrid' adapter takes no option 'subjects'"):
        load_config(ROOT / "recipes" / "tiny.yaml", ["env.options.subjects=[101]"])
    with pytest.raises(ConfigError, match=r"env\.eval_options\.colour: the 'health' adapter takes no option 'colour'"):
        load_config(ROOT / "recipes" / "health_model_free.yaml", ["env.eval_options.colour=1"])
    with pytest.raises(ConfigError, match=r"env\.options\.x: expected YAML data"):
        config_from_dict({"env": {"options": {"x": object()}}}, FreamerConfig)


def test_held_out_evaluation_uses_the_health_trainers_episodes():
    """``env.eval_options`` moves every evaluation env to the held-out subject; the reference policies run through
    the collector-based evaluator then score exactly what the health trainer's evaluation gives them (the same
    subjects, env seed and episodes), so a model-free policy is compared with the rule on the LOSO protocol."""
    cfg = load_config(
        ROOT / "recipes" / "baselines" / "ppo_mlp_health.yaml",
        [
            "env.options.subjects=[102, 103]",
            "env.eval_options.subjects=[101]",
            "env.options.synthetic_duration_s=300.0",
            "env.options.episode_length=40",
        ],
    )
    health = load_health_config(
        ROOT / "recipes" / "health" / "health_mlp.yaml",
        [
            "env.id=pamap2-health-varied",
            "env.subjects=[102, 103]",
            "eval.subjects=[101]",
            "eval.num_envs=4",
            "env.synthetic_duration_s=300.0",
            "env.episode_length=40",
            "world_model.seq_len=8",
            "eval.horizon_context=4",
            "eval.horizon_max=8",
        ],
    )
    for name in ("hr_threshold", "continue", "rest"):
        ours = run_episodes(cfg, make_reference_policy(name), [], episodes=4, deterministic=True, num_envs=4)
        theirs = evaluate_reference(health, name)
        assert ours["env_options"]["subjects"] == [101]
        assert ours["return_mean"] == pytest.approx(theirs["return_mean"], abs=1e-4), name


@pytest.mark.parametrize("recipe", ["baselines/ppo_mlp_health.yaml", "health_model_free.yaml"])
def test_model_free_health_recipes_train_and_evaluate_on_a_held_out_subject(recipe, tmp_path, capsys):
    run = tmp_path / "run"
    overrides = [*TINY_PPO, "env.options.subjects=[102, 103]", "env.eval_options.subjects=[101]"]
    assert cli.main(["train", str(ROOT / "recipes" / recipe), *overrides, "--run-dir", str(run)]) == 0
    capsys.readouterr()
    assert cli.main(["eval", str(run), "--episodes", "2", "--num-envs", "2", "--deterministic"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["env_options"]["subjects"] == [101]
    assert result["episodes"] == 2 and len(result["episode_returns"]) == 2


def test_held_out_suite_and_its_rule_table(tmp_path):
    """A tiny leave-one-subject-out suite of both model-free recipes (two folds, one seed), then
    benchmarks/health_loso_rules.py: the table has a row per arm, and the rule's return per fold is the one the
    collector-based evaluator gives on the held-out subject."""
    import importlib.util

    from freamer_rl.experiments.suite import run_suite

    tiny = [o for o in TINY_PPO if not o.startswith("env.options.episode_length")] + ["env.options.episode_length=40"]
    entries = []
    for arm, recipe in (("mlp", "baselines/ppo_mlp_health.yaml"), ("freamer", "health_model_free.yaml")):
        for k, train in ((101, [102, 103]), (102, [101, 103])):
            over = [*tiny, f"env.options.subjects={train}", f"env.eval_options.subjects=[{k}]"]
            entries.append({"label": f"{arm}_fold{k}", "recipe": str(ROOT / "recipes" / recipe), "overrides": over})
    suite = {
        "name": "mf_tiny",
        "seeds": [0],
        "entries": entries,
        "evaluate": {"episodes": 4, "num_envs": 4, "deterministic": True, "conditions": [{"label": "clean"}]},
    }
    path = tmp_path / "mf_tiny.yaml"
    path.write_text(json.dumps(suite))
    out = tmp_path / "out"
    run_suite(path, output=out)
    spec = importlib.util.spec_from_file_location("health_loso_rules", ROOT / "benchmarks" / "health_loso_rules.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main([str(out), "--episodes", "4"]) == 0
    rows = json.loads((out / "loso_vs_rules.json").read_text())
    assert sorted((r["encoder"], r["eval_subjects"]) for r in rows) == [
        ("freamer", "101"),
        ("freamer", "102"),
        ("mlp", "101"),
        ("mlp", "102"),
    ]
    cfg = script.run_config(out / "runs" / "mlp_fold102" / "pamap2-health-varied" / "seed0")
    rule = run_episodes(cfg, make_reference_policy("hr_threshold"), [], episodes=4, deterministic=True, num_envs=4)
    assert rule["env_options"]["subjects"] == [102]
    assert all(r["eval_ref_hr_threshold_return"] == rule["return_mean"] for r in rows if r["eval_subjects"] == "102")
    ctrl = run_episodes(cfg, make_reference_policy("hr_controller"), [], episodes=4, deterministic=True, num_envs=4)
    assert all(r["eval_ref_hr_controller_return"] == ctrl["return_mean"] for r in rows if r["eval_subjects"] == "102")
    # a cache written before the controller existed: only the missing reference is scored, the rest kept
    cache_path = out / "loso_references.json"
    cache = json.loads(cache_path.read_text())
    for refs in cache.values():
        refs.pop("eval_ref_hr_controller_return")
        refs["eval_ref_oracle_return"] = -1.0  # a marker: a rescored oracle would overwrite it
    cache_path.write_text(json.dumps(cache))
    assert script.main([str(out), "--episodes", "4"]) == 0
    rescored = json.loads(cache_path.read_text())
    assert all(r["eval_ref_oracle_return"] == -1.0 and "eval_ref_hr_controller_return" in r for r in rescored.values())
    table = (out / "loso_vs_rules.md").read_text()
    assert "| mlp | 2 | 2 |" in table and "| freamer | 2 | 2 |" in table
