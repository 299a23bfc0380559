"""Sensor corruption in a health recipe (``env.corrupt``, issue 22 part 5): ``when: train`` corrupts the collected
data, ``when: eval`` the final evaluation, the running statistics survive a resume, and a key the world model does
not read is refused with the field named."""

import sys
from pathlib import Path

import pytest
import torch

from freamer_rl.errors import ConfigError
from freamer_rl.health.config import load_health_config
from freamer_rl.health.evaluation import evaluate_checkpoint
from freamer_rl.health.trainer import HealthTrainer
from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint
from freamer_rl.trainers.health import STRUCTURAL

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_health_pipeline import RECIPES, health_adapter  # noqa: E402, F401  (the fixture registers the adapter)
from test_health_pipeline import TINY as PIPELINE_TINY  # noqa: E402

TINY = [*PIPELINE_TINY, "collect.iterations=1"]


def _trainer(tmp_path, *overrides, resume=True):
    torch.manual_seed(0)
    cfg = load_health_config(RECIPES["mlp"], [*TINY, *overrides])
    return HealthTrainer(cfg, tmp_path / "run", resume=resume, structural=STRUCTURAL)


def test_train_corruption_reaches_the_replay_buffer_only_on_its_slice(tmp_path):
    trainer = _trainer(tmp_path, "env.corrupt=[{key: 'imu[0:12]', kind: dropout, level: 1.0, when: train}]")
    trainer.train()
    imu = trainer.rb[:].get("imu")  # every collected step, as the world model was trained on it
    assert imu.shape[0] == trainer.frames
    assert bool((imu[..., 0:12] == 0).all())  # the hand IMU dropped at every step
    assert bool((imu[..., 12:] != 0).any())  # chest and ankle untouched
    assert bool((trainer.rb[:].get("hr_features") != 0).any())


def test_eval_corruption_applies_to_the_final_evaluation_not_to_training(tmp_path):
    trainer = _trainer(tmp_path, "env.corrupt=[{key: hr_features, kind: dropout, level: 1.0, when: eval}]")
    summary = trainer.train()
    assert bool((trainer.rb[:].get("hr_features") != 0).any())  # training saw the heart rate
    cfg = trainer.cfg
    options = {"episodes": cfg.eval.num_envs, "seed": cfg.eval.seed}
    recipe_eval = evaluate_checkpoint(tmp_path / "run", corrupt=None, **options)  # the recipe's eval corruption
    clean = evaluate_checkpoint(tmp_path / "run", corrupt=[], **options)
    assert recipe_eval["corrupt"] and not clean["corrupt"]
    assert summary["eval_return_mean"] == pytest.approx(recipe_eval["return_mean"])
    assert summary["eval_kl_mean"] == pytest.approx(recipe_eval["kl_mean"])
    assert recipe_eval["kl_mean"] != pytest.approx(clean["kl_mean"])  # the dropped heart rate changes what it saw


def test_resume_restores_the_running_std_of_the_training_corruption(tmp_path):
    corrupt = "env.corrupt=[{key: 'imu[12:24]', kind: gaussian, level: 1.0, when: train}]"
    first = _trainer(tmp_path, corrupt)
    first.train()
    saved = read_checkpoint(latest_checkpoint(tmp_path / "run"))["corruption"]
    assert len(saved) == 1 and saved[0]["key"] == "imu" and saved[0]["channels"] == [12, 24]
    assert float(saved[0]["stats"][0]) > 0  # it measured the chest IMU's values
    resumed = _trainer(tmp_path, corrupt, "collect.iterations=2")
    # the count goes on from the checkpoint's: building the collector reset the env once more, num_envs x 12 values
    # (a fresh statistic would hold those 4 x 12 only)
    count = float(resumed.train_corruption[0].stats_state()["stats"][0])
    assert count == float(saved[0]["stats"][0]) + resumed.cfg.env.num_envs * 12
    resumed.life.lock.release()


def test_a_corruption_the_world_model_does_not_read_names_the_field(tmp_path):
    with pytest.raises(ConfigError, match=r"env\.corrupt\[0\]\.key"):
        _trainer(tmp_path, "env.corrupt=[{key: heart_rate, kind: gaussian, level: 1.0, when: train}]")


def test_a_sigterm_that_a_library_turns_into_its_own_error_still_checkpoints_and_stops(tmp_path, monkeypatch):
    """SIGTERM during the imagined PPO update once came back from inside TorchRL as another error, and the suite
    recorded the run as failed. An error whose context is the interrupt is re-raised as the interrupt: the
    trainer warns, keeps the last iteration's checkpoint and raises Terminated; the rerun resumes from it."""
    from freamer_rl.run.rundir import Terminated

    trainer = _trainer(tmp_path, "collect.iterations=2")
    real_update, calls = trainer.algo.update, []

    def wrapped_by_a_library(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1 + trainer.cfg.imagination.updates:  # the first update of iteration 2
            try:
                raise Terminated("SIGTERM")
            except KeyboardInterrupt:
                raise RuntimeError("a library's cleanup failed while the interrupt unwound") from None
        return real_update(*args, **kwargs)

    monkeypatch.setattr(trainer.algo, "update", wrapped_by_a_library)
    with pytest.raises(Terminated):
        trainer.train()
    assert read_checkpoint(latest_checkpoint(tmp_path / "run"))["iteration"] == 1
    resumed = _trainer(tmp_path, "collect.iterations=2")
    assert resumed.iteration == 1
    resumed.life.lock.release()
