"""Frames / episodes to 80% and 95% success: the exact episode at which the trailing window first reaches the level
(issue 21 part 3: the project's one definition), its checkpoint round trip and how the reports read it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from freamer_rl.experiments.report import RunRecord, write_report
from freamer_rl.run.metrics import SUCCESS_LEVELS, EpisodeStats


def _batch(success: list[list[int]]) -> TensorDict:
    """``[B, T]`` steps that all end an episode; ``success[b][t]`` its outcome (read back by ``success_fn``)."""
    s = torch.tensor(success, dtype=torch.bool)
    B, T = s.shape
    nxt = TensorDict(
        {
            "done": torch.ones(B, T, 1, dtype=torch.bool),
            "episode_reward": s.float().unsqueeze(-1),
            "step_count": torch.ones(B, T, 1, dtype=torch.long),
            "success": s.unsqueeze(-1),
        },
        batch_size=[B, T],
    )
    return TensorDict({"next": nxt}, batch_size=[B, T])


def _stats() -> EpisodeStats:
    return EpisodeStats(window=5, success_fn=lambda ends: ends["success"])


def test_each_level_is_the_exact_episode_and_its_frame():
    stats = _stats()
    stats.update(_batch([[0, 0], [0, 0]]), frames_before=0)  # 4 failures: window not full, then all 0
    # episodes 5..10, ordered by time then env: (t0,e0)=5 (t0,e1)=6 (t1,e0)=7 (t1,e1)=8 (t2,e0)=9 (t2,e1)=10
    stats.update(_batch([[1, 1, 1], [1, 1, 1]]), frames_before=4)
    # window after episode 8: [0,1,1,1,1] = 0.8 (level 0.8 at episode 8, time step 1: 4 + 2 * 2 = 8 frames);
    # after episode 9: [1,1,1,1,1] = 1.0 (level 0.95 at episode 9, time step 2: 4 + 3 * 2 = 10 frames)
    assert stats.first_reached == {0.8: (8, 8), 0.95: (10, 9)}
    assert stats.level_summary() == {"frames_to_80": 8, "episodes_to_80": 8, "frames_to_95": 10, "episodes_to_95": 9}
    stats.update(_batch([[0, 0, 0], [0, 0, 0]]), frames_before=10)  # falling back does not move the first reaching
    assert stats.frames_to(0.95) == 10 and stats.success_rate == 0.0


def test_a_partial_window_never_counts():
    stats = _stats()
    stats.update(_batch([[1, 1], [1, 1]]), frames_before=0)  # 4 successes of a 5-episode window
    assert stats.first_reached == {} and stats.level_summary()["frames_to_80"] is None


def test_levels_survive_a_checkpoint_and_old_checkpoints_know_only_95():
    stats = _stats()
    stats.update(_batch([[1, 1, 1], [1, 1, 1]]), frames_before=0)
    back = _stats()
    back.load_state_dict(json.loads(json.dumps(stats.state_dict())))  # what torch.save / weights_only keeps
    assert back.first_reached == stats.first_reached == {0.8: (6, 5), 0.95: (6, 5)}
    old = {k: v for k, v in stats.state_dict().items() if k != "first_reached"}
    old.update(first_target_frames=6, first_target_episodes=5)
    back = _stats()
    back.load_state_dict(old)
    assert back.level_summary() == {
        "frames_to_80": None,
        "episodes_to_80": None,
        "frames_to_95": 6,
        "episodes_to_95": 5,
    }
    back.update(_batch([[1], [1]]), frames_before=6)
    assert back.first_reached[0.8] is None  # not known, and not recorded later as if it were the first time
    assert set(back.first_reached) == set(SUCCESS_LEVELS)


def _run(root, name, summary):
    run = root / name
    run.mkdir(parents=True)
    (run / "summary.json").write_text(
        json.dumps({"frames": 1000, "episodes": 50, "final_success_rate": 0.97, **summary})
    )
    (run / "progress.csv").write_text("frames,episodes,success_rate\n1000,50,0.97\n")
    (run / "done.json").write_text(json.dumps({"total_frames": 1000, "frames": 1000}))
    return RunRecord(label=name, env="e", env_dir="e", seed=0, run_dir=run, target_frames=1000)


def test_the_report_tells_not_reached_from_not_recorded(tmp_path):
    new = _run(
        tmp_path, "new", {"frames_to_80": 600, "episodes_to_80": 30, "frames_to_95": None, "episodes_to_95": None}
    )
    old = _run(tmp_path, "old", {"frames_to_95": 900, "episodes_to_95": 45})  # written before frames_to_80 existed
    write_report(tmp_path / "out", "demo", [new, old])
    md = (tmp_path / "out" / "summary.md").read_text()
    new_line = next(line for line in md.splitlines() if line.startswith("| new |"))
    old_line = next(line for line in md.splitlines() if line.startswith("| old |"))
    assert "| not reached [—] | not reached [—] | 600 [600] |" in new_line  # 95% not reached; 80% at 600 frames
    assert "| 45 [45] | 900 [900] | n/a [n/a] |" in old_line


def test_return_target_is_the_exact_episode_of_the_windowed_mean_return():
    stats = EpisodeStats(window=2, return_target=0.5)  # episode_reward = success here (0 or 1)
    stats.update(_batch([[0, 1], [0, 1]]), frames_before=0)
    # episodes: (t0,e0)=1 r0, (t0,e1)=2 r0, (t1,e0)=3 r1 -> window [0, 1] mean 0.5 at episode 3, frame 2 * 2 = 4
    assert stats.first_return == (4, 3)
    assert stats.level_summary()["frames_to_return"] == 4 and stats.level_summary()["return_target"] == 0.5
    back = EpisodeStats(window=2, return_target=0.5)
    back.load_state_dict(stats.state_dict())
    assert back.first_return == (4, 3)
    other = EpisodeStats(window=2, return_target=0.9)  # a resumed run with another target does not inherit it
    other.load_state_dict(stats.state_dict())
    assert other.first_return is None and "frames_to_return" not in EpisodeStats(window=2).level_summary()


def test_the_report_has_a_frames_to_return_column_when_runs_set_a_target(tmp_path):
    a = _run(tmp_path, "a", {"return_target": 475.0, "frames_to_return": 900, "episodes_to_return": 40})
    b = _run(tmp_path, "b", {"return_target": 475.0, "frames_to_return": None, "episodes_to_return": None})
    write_report(tmp_path / "out", "demo", [a, b])
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "frames to return 475 [per seed]" in md
    assert "| 900 [900] |" in next(line for line in md.splitlines() if line.startswith("| a |"))
    assert "| not reached [—] |" in next(line for line in md.splitlines() if line.startswith("| b |"))


def test_an_arm_with_privileged_information_is_marked_in_the_report(tmp_path):
    plain = _run(tmp_path, "plain", {"privileged": []})
    oracle = _run(tmp_path, "oracle", {"privileged": ["shaping.language.distance=oracle"]})
    write_report(tmp_path / "out", "demo", [plain, oracle])
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "| oracle (privileged) |" in md and "| plain |" in md
    assert "- oracle: shaping.language.distance=oracle" in md


@pytest.mark.parametrize("distance, expected", [("oracle", ["shaping.language.distance=oracle"]), ("observed", [])])
def test_a_run_with_the_oracle_distance_says_so_in_its_summary(tmp_path, distance, expected):
    from freamer_rl.trainers.minigrid_ppo import Trainer
    from freamer_rl.trainers.registry import load_config

    tiny = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"
    cfg = load_config(tiny, ["shaping.language.weight=0.2", f"shaping.language.distance={distance}"])
    summary = Trainer(cfg, tmp_path / "run").train()
    assert summary["privileged"] == expected
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["privileged"] == expected


def test_every_trainer_reports_its_trainable_parameters_and_the_suite_tables_them(tmp_path):
    from freamer_rl.trainers.minigrid_ppo import Trainer
    from freamer_rl.trainers.registry import load_config

    tiny = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"
    trainer = Trainer(load_config(tiny), tmp_path / "run")
    summary = trainer.train()
    assert summary["trainable_params"] == sum(p.numel() for p in trainer.params if p.requires_grad) > 0
    record = RunRecord(label="t", env="e", env_dir="e", seed=0, run_dir=tmp_path / "run", target_frames=None)
    (tmp_path / "run" / "done.json").write_text(json.dumps({"total_frames": summary["frames"]}))
    write_report(tmp_path / "out", "demo", [record])
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "trainable params" in md and f"{summary['trainable_params']:,}" in md


def test_a_task_without_success_reports_the_return_iqm_and_every_seed(tmp_path):
    runs = []
    for seed, ret in enumerate((100.0, 200.0, 300.0, 400.0)):
        run = tmp_path / f"seed{seed}"
        run.mkdir()
        (run / "summary.json").write_text(
            json.dumps({"frames": 1000, "episodes": 50, "final_success_rate": None, "final_return_mean": ret})
        )
        (run / "progress.csv").write_text("frames,episodes,return_mean\n1000,50,1.0\n")
        (run / "done.json").write_text(json.dumps({"total_frames": 1000, "frames": 1000}))
        runs.append(RunRecord(label="a", env="e", env_dir="e", seed=seed, run_dir=run, target_frames=1000))
    write_report(tmp_path / "out", "demo", runs)
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "final return IQM [95% CI] [per seed]" in md and "final success" not in md
    line = next(line for line in md.splitlines() if line.startswith("| a |"))
    # the IQM of 4 values is the mean of the middle two: (200 + 300) / 2
    assert "| 250.00 [" in line and line.rstrip().endswith("[100.00 / 200.00 / 300.00 / 400.00] |"), line
