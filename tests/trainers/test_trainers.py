"""Trainer registry: every entry trains a tiny recipe through ``freamer-rl train``, writes a checkpoint, resumes from
it, refuses ``--no-resume`` on it, evaluates through ``freamer-rl eval`` and counts its parameters."""

import json
import sys
from pathlib import Path

import pytest

from freamer_rl import cli
from freamer_rl.errors import ConfigError
from freamer_rl.health.config import HealthConfig
from freamer_rl.run import env_registry
from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint
from freamer_rl.trainers.minigrid_ppo import FreamerConfig
from freamer_rl.trainers.registry import TRAINERS, load_config, trainer_of_checkpoint

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "health"))
from test_health_pipeline import TINY as HEALTH_TINY  # noqa: E402

# one tiny recipe per registry entry: (recipe, overrides of the first run, overrides that extend it for the resume)
TINY = {
    "minigrid_ppo": (
        ROOT / "recipes" / "tiny.yaml",
        ["run.total_frames=128", "logging.progress_bar=false"],
        ["run.total_frames=256"],
    ),
    "health": (
        ROOT / "recipes" / "health" / "health_mlp.yaml",
        [*HEALTH_TINY, "collect.iterations=1"],
        ["collect.iterations=2"],
    ),
    "ppo_baseline": (
        ROOT / "recipes" / "baselines" / "ppo_mlp_n2s4.yaml",
        [
            "env.id=MiniGrid-Empty-5x5-v0",
            "env.num_envs=2",
            "ppo.frames_per_batch=64",
            "ppo.minibatch_size=32",
            "ppo.sequence_length=8",
            "network.hidden=16",
            "run.total_frames=64",
            "logging.checkpoint_every_frames=64",
            "logging.progress_bar=false",
        ],
        ["run.total_frames=128"],
    ),
    "dreamer_v3": (
        ROOT / "recipes" / "baselines" / "dreamer_v3_n2s4.yaml",
        [
            "env.id=MiniGrid-Empty-5x5-v0",
            "env.num_envs=2",
            "dreamer.stoch_categoricals=4",
            "dreamer.stoch_classes=4",
            "dreamer.deter=32",
            "dreamer.hidden=32",
            "dreamer.mlp_layers=1",
            "dreamer.frames_per_batch=64",
            "dreamer.batch_size=4",
            "dreamer.sequence_length=8",
            "dreamer.train_every=32",
            "dreamer.prefill_frames=64",
            "dreamer.replay_capacity=1000",
            "dreamer.horizon=5",
            "run.total_frames=64",
            "logging.checkpoint_every_frames=64",
            "logging.progress_bar=false",
        ],
        ["run.total_frames=128"],
    ),
    # keeps the recipe's two asynchronous actor processes
    "impala": (
        ROOT / "recipes" / "baselines" / "impala_n2s4.yaml",
        [
            "env.id=MiniGrid-Empty-5x5-v0",
            "env.num_envs=2",
            "collector.num_collectors=1",  # one actor: no worker start-up (test_impala.py runs the two-actor path)
            "network.hidden=16",
            "impala.frames_per_batch=64",
            "run.total_frames=128",
            "logging.checkpoint_every_frames=64",
            "logging.progress_bar=false",
        ],
        ["run.total_frames=256"],
    ),
}


@pytest.fixture(autouse=True)
def health_adapter(monkeypatch):
    if "health" not in env_registry.available_adapters():
        from freamer_rl_envs.health import make_health_env as factory

        orig = env_registry.get_env_factory
        monkeypatch.setattr(env_registry, "get_env_factory", lambda a: factory if a == "health" else orig(a))


def test_every_trainer_has_a_tiny_recipe():
    assert set(TINY) == set(TRAINERS)


@pytest.mark.parametrize("name", sorted(TRAINERS))
def test_train_checkpoint_resume_eval(name, tmp_path, capsys):
    recipe, first, extend = TINY[name]
    run = tmp_path / "run"
    assert cli.main(["train", str(recipe), *first, "--run-dir", str(run)]) == 0
    ckpt = latest_checkpoint(run)
    assert ckpt is not None and trainer_of_checkpoint(ckpt) == name
    frames = read_checkpoint(ckpt)["frames"]
    assert frames > 0
    # --no-resume on a directory with checkpoints is refused (nothing deleted)
    assert cli.main(["train", str(recipe), *first, *extend, "--run-dir", str(run), "--no-resume"]) == 2
    assert "already holds checkpoints" in capsys.readouterr().err
    assert latest_checkpoint(run) == ckpt
    # a rerun with a longer budget resumes from the checkpoint and goes on
    assert cli.main(["train", str(recipe), *first, *extend, "--run-dir", str(run)]) == 0
    resumed = read_checkpoint(latest_checkpoint(run))
    assert resumed["frames"] > frames
    info = json.loads((run / "run_info.json").read_text())
    assert info["resumed_from"] == str(ckpt)
    for out in ("progress.csv", "summary.json", "learning_curve.png", "config.yaml"):
        assert (run / out).is_file(), out
    assert any((run / "metrics").glob("attempt_02")), "one logger folder per attempt"
    capsys.readouterr()
    assert cli.main(["eval", str(run), "--episodes", "2", "--deterministic"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert "return_mean" in result or "success_rate" in result
    assert cli.main(["params", str(recipe), *first]) == 0
    assert "Total" in capsys.readouterr().out


def test_health_progress_rows_continue_after_resume(tmp_path):
    recipe, first, extend = TINY["health"]
    run = tmp_path / "run"
    assert cli.main(["train", str(recipe), *first, "--run-dir", str(run)]) == 0
    assert cli.main(["train", str(recipe), *first, *extend, "--run-dir", str(run)]) == 0
    rows = (run / "progress.csv").read_text().splitlines()
    assert len(rows) == 1 + 3  # header, prefill, iterations 1 and 2 (none repeated)
    assert [r.split(",")[0] for r in rows[1:]] == ["0", "1", "2"]
    assert (run / "checkpoint.pt").is_file()


def test_recipes_name_their_trainer_and_load_with_one_loader():
    for path in sorted((ROOT / "recipes" / "health").glob("*.yaml")):
        assert isinstance(load_config(path), HealthConfig), path
        assert isinstance(load_config(path, schema=HealthConfig), HealthConfig)
        with pytest.raises(ConfigError, match="trainer"):
            load_config(path, schema=FreamerConfig)
    for path in sorted(ROOT.glob("recipes/*.yaml")) + sorted(ROOT.glob("recipes/gym/*.yaml")):
        if not path.name.endswith(".chain.yaml"):  # chain files are not recipes (tests/test_chain.py)
            assert isinstance(load_config(path), FreamerConfig), path
    with pytest.raises(ConfigError, match="unknown trainer 'nope'"):
        load_config(None, ["trainer=nope"])
    assert isinstance(load_config(None, ["trainer=health"]), HealthConfig)
