"""The training corruption's running statistic in the run's checkpoint (issue 20): saved, restored on resume, and an
older checkpoint without it still loads with one logged line."""

import logging
from pathlib import Path

import pytest
import torch

from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint
from freamer_rl.run.corruption import ModalityCorruption, load_corruption_state
from freamer_rl.trainers.registry import TRAINERS, load_config

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "baselines" / "ppo_mlp_n2s4.yaml"
TINY = [
    "env.id=MiniGrid-Empty-5x5-v0",
    "env.num_envs=2",
    "ppo.frames_per_batch=64",
    "ppo.minibatch_size=32",
    "network.hidden=16",
    "logging.progress_bar=false",
    "logging.checkpoint_every_frames=64",
    "env.corrupt=[{key: reward_history, kind: gaussian, level: 1.0, when: train}]",
]


def _train(run: Path, frames: int) -> dict:
    cfg = load_config(RECIPE, [*TINY, f"run.total_frames={frames}"])
    TRAINERS["ppo_baseline"].train(cfg, run)
    return read_checkpoint(latest_checkpoint(run))


def test_resume_restores_the_saved_statistic(tmp_path, monkeypatch):
    run = tmp_path / "run"
    first = _train(run, 64)
    (saved,) = first["corruption"]
    assert (saved["key"], saved["kind"], saved["channels"]) == ("reward_history", "gaussian", [])
    count = float(saved["stats"][0])
    assert count > 0  # the training env measured the values it corrupted
    loaded = []
    original = ModalityCorruption.load_stats_state
    monkeypatch.setattr(
        ModalityCorruption, "load_stats_state", lambda self, s: (loaded.append(s["stats"].clone()), original(self, s))
    )
    second = _train(run, 128)  # resumes at 64 frames
    assert len(loaded) == 1 and torch.equal(loaded[0], saved["stats"])
    # the statistic went on from the saved one: the second segment (the same size as the first) adds to its count,
    # a statistic restarted from nothing would hold about the first segment's count again
    assert float(second["corruption"][0]["stats"][0]) > 1.5 * count


def test_an_older_checkpoint_without_it_loads_with_one_line(tmp_path, caplog):
    run = tmp_path / "run"
    _train(run, 64)
    path = latest_checkpoint(run)
    payload = torch.load(path, weights_only=True)
    del payload["corruption"]
    torch.save(payload, path)
    with caplog.at_level(logging.INFO, logger="freamer_rl.run.corruption"):
        ckpt = _train(run, 128)
    lines = [r.getMessage() for r in caplog.records if "no corruption statistics" in r.getMessage()]
    assert len(lines) == 1 and str(path) in lines[0]
    assert ckpt["frames"] == 128 and float(ckpt["corruption"][0]["stats"][0]) > 0


def test_a_statistic_of_another_corruption_is_refused():
    t = ModalityCorruption("reward_history", "gaussian", 1.0, where="env.corrupt[0]", channels=(0, 4))
    state = {"key": "reward_history", "kind": "gaussian", "channels": [], "stats": torch.tensor([1.0, 0.0, 0.0])}
    with pytest.raises(ValueError, match=r"env\.corrupt\[0\]: the checkpoint's corruption statistic"):
        load_corruption_state([t], [state], "ckpt.pt")
    with pytest.raises(ValueError, match="1 corruption statistics saved for 2"):
        load_corruption_state([t, t], [state], "ckpt.pt")
