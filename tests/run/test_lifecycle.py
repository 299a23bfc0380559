"""The run-directory lifecycle every trainer shares (freamer_rl.run.lifecycle) and what it writes: storage errors as one
line, valid summary JSON, wall time from the trainer's start, progress <= 100 %, honest curve labels and titles, the
metrics logger's folder and its missing-extra hint."""

from __future__ import annotations

import errno
import json
import logging
import math
import time
from pathlib import Path

import matplotlib.figure
import pytest
import torch

from freamer_rl import cli
from freamer_rl.errors import FreamerError
from freamer_rl.run import checkpoint as checkpoint_mod
from freamer_rl.run import files
from freamer_rl.run.checkpoint import atomic_write_text, read_checkpoint
from freamer_rl.run.lifecycle import RunLifecycle
from freamer_rl.run.metrics import ProgressReporter, plot_learning_curve
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
ENOSPC = OSError(errno.ENOSPC, "No space left on device")


def _strict_json(text: str):
    """json.loads that refuses NaN / Infinity (they are not JSON)."""

    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def _lifecycle(run: Path) -> RunLifecycle:
    return RunLifecycle(run, trainer_name="t", config={"a": 1}, read_checkpoint=read_checkpoint, structural=())


# ----------------------------------------------------------------------------------------------------------------------
# storage errors: one FreamerError line naming the file and saying the run resumes
# ----------------------------------------------------------------------------------------------------------------------
def _assert_storage_line(err: BaseException, name: str) -> None:
    text = str(err)
    assert name in text and "resumes from its latest checkpoint" in text and "\n" not in text, text


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EACCES])
def test_summary_write_error_is_one_line_naming_the_file(tmp_path, monkeypatch, code):
    life = _lifecycle(tmp_path)

    def no_temp_file(*a, **k):
        raise OSError(code, "refused")

    monkeypatch.setattr(checkpoint_mod.tempfile, "mkstemp", no_temp_file)
    with pytest.raises(FreamerError) as info:
        life.write_summary({"frames": 1})
    _assert_storage_line(info.value, str(tmp_path / "summary.json"))


def test_other_os_errors_are_not_disguised(tmp_path, monkeypatch):
    def broken(*a, **k):
        raise OSError(errno.EBADF, "bad file descriptor")  # a bug, not the disk: stays a traceback

    monkeypatch.setattr(checkpoint_mod.tempfile, "mkstemp", broken)
    with pytest.raises(OSError) as info:
        atomic_write_text(tmp_path / "x.txt", "x")
    assert not isinstance(info.value, FreamerError)


def test_progress_append_error_is_one_line(tmp_path, monkeypatch):
    life = _lifecycle(tmp_path)
    life.log_row({"frames": 1, "x": 0.5}, None, 1)  # creates the file
    real_open = Path.open

    def full_disk_append(self, mode="r", *a, **k):
        if mode == "a":
            raise ENOSPC
        return real_open(self, mode, *a, **k)

    monkeypatch.setattr(Path, "open", full_disk_append)
    with pytest.raises(FreamerError) as info:
        life.log_row({"frames": 2, "x": 0.25}, None, 2)
    _assert_storage_line(info.value, str(tmp_path / "progress.csv"))


def test_learning_curve_write_error_is_one_line_and_leaves_no_temp(tmp_path, monkeypatch):
    def full_disk(self, *a, **k):
        raise ENOSPC  # what PIL raises when the disk fills while it writes the PNG

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full_disk)
    rows = [{"frames": 64 * i, "episodes": i, "success_rate": math.nan, "return_mean": 0.1 * i} for i in range(3)]
    with pytest.raises(FreamerError) as info:
        plot_learning_curve(rows, tmp_path / "learning_curve.png")
    _assert_storage_line(info.value, "learning_curve.png")
    assert list(tmp_path.iterdir()) == []


def test_full_disk_during_training_is_one_error_line_exit_2(tmp_path, monkeypatch, capsys):
    real_save = torch.save

    def full_disk(obj, f, *a, **k):
        if isinstance(obj, dict) and "frames" in obj:  # checkpoints only
            raise ENOSPC
        return real_save(obj, f, *a, **k)

    monkeypatch.setattr(torch, "save", full_disk)
    run = tmp_path / "run"
    assert cli.main(["train", str(TINY), "--run-dir", str(run), "run.total_frames=128"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and "checkpoint_000000128.pt" in err[0] and "No space left on device" in err[0], err
    assert "rerun the same command" in err[0]


# ----------------------------------------------------------------------------------------------------------------------
# summary.json, wall time, labels, progress (one tiny run)
# ----------------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("lifecycle") / "run"
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    root = logging.getLogger("freamer_rl")
    old_level = root.level
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        # run.total_frames=200 is not a whole number of 128-frame batches: the collector delivers 256
        cfg = load_config(TINY, ["run.total_frames=200"])
        t_start = time.perf_counter()
        trainer = Trainer(cfg, run)
        trainer.cfg.model.compile = True  # only the log line is wanted here: the model was built without compiling
        time.sleep(1.0)  # start-up time (model building, compiling) belongs to the run's wall time
        t_train = time.perf_counter()
        summary = trainer.train()
        t_end = time.perf_counter()
        train_s, total_s = t_end - t_train, t_end - t_start
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
    return run, summary, (train_s, total_s), [r.getMessage() for r in records], trainer


def test_summary_is_valid_json_with_null_for_nan(tiny_run):
    run, summary, *_ = tiny_run
    on_disk = _strict_json((run / "summary.json").read_text())
    # MiniGrid-Empty-5x5 ends few episodes in 256 frames; whatever is undefined must be null, never NaN
    for key, value in on_disk.items():
        assert not (isinstance(value, float) and not math.isfinite(value)), key
    assert on_disk["frames"] == summary["frames"] == 256


def test_summary_nan_becomes_null(tmp_path):
    life = _lifecycle(tmp_path)
    out = life.write_summary({"rate": math.nan, "nested": {"x": math.inf}, "rows": [1.0, math.nan]})
    assert _strict_json((tmp_path / "summary.json").read_text()) == {
        "rate": None,
        "nested": {"x": None},
        "rows": [1.0, None],
    }
    assert out["rate"] is None


def test_wall_time_counts_from_the_trainer_start(tiny_run):
    _, summary, (train_s, total_s), *_ = tiny_run
    # train() alone (loop, final checkpoint, curve, summary) took train_s: more means the start-up (the model build
    # and the 1 s before train()) is counted; the whole life of the trainer bounds it
    assert train_s < summary["wall_time_s"] <= total_s
    assert summary["fps"] == pytest.approx(summary["frames"] / summary["wall_time_s"], rel=1e-6)


def test_compiling_is_announced_before_the_first_batch(tiny_run):
    *_, messages, _ = tiny_run
    compiling = [i for i, m in enumerate(messages) if m.startswith("compiling")]
    progress = [i for i, m in enumerate(messages) if m.startswith("frames ")]
    assert compiling and progress and compiling[0] < progress[0], messages


def test_progress_never_passes_100_percent(tiny_run):
    *_, messages, _ = tiny_run
    lines = [m for m in messages if m.startswith("frames ")]
    assert lines and all("/256 (" in m for m in lines), lines  # the collector's real total, not run.total_frames
    percents = [float(m.split("(")[1].split("%")[0]) for m in lines]
    assert max(percents) <= 100


def test_reporter_caps_the_share_at_100(caplog):
    reporter = ProgressReporter(total=1000, initial=0, bar=False, interval_s=0.0)
    with caplog.at_level(logging.INFO, logger="freamer_rl.run.metrics"):
        reporter.update(1100, 1100, extra={"iteration": "3/3"})
    assert "(100%)" in caplog.records[-1].getMessage() and "iteration 3/3" in caplog.records[-1].getMessage()


def test_labels_name_the_algorithm_not_an_env_family(tiny_run):
    run, summary, *_, trainer = tiny_run
    assert summary["trainer"] == "minigrid_ppo"  # the registry key: freamer-rl eval and the suites read it
    assert summary["algorithm"] == "FreamerV1 PPO"
    assert trainer.life.title == "MiniGrid-Empty-5x5-v0 -- FreamerV1 PPO, seed 0"
    assert (run / "learning_curve.png").is_file()


# ----------------------------------------------------------------------------------------------------------------------
# the learning curve's labels
# ----------------------------------------------------------------------------------------------------------------------
def _axis_labels(monkeypatch, rows, **kwargs) -> list[str]:
    seen: list[list[str]] = []

    def capture(self, fname, *a, **k):
        seen.append([ax.get_ylabel() for ax in self.axes] + [t.get_text() for ax in self.axes for t in ax.texts])
        Path(fname).write_bytes(b"png")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    plot_learning_curve(rows, Path(kwargs.pop("path")), **kwargs)
    return seen[0]


def test_curve_says_last_100_episodes_only_once_they_exist(tmp_path, monkeypatch):
    early = [{"frames": 64, "episodes": 2, "success_rate": 1.0, "return_mean": 0.9}]
    labels = _axis_labels(monkeypatch, early, path=tmp_path / "a.png", window=100)
    assert not any("last 100 episodes" in t for t in labels), labels
    assert any("n/a" in t for t in labels) and any("2 episodes so far" in t for t in labels), labels
    later = [*early, {"frames": 6400, "episodes": 120, "success_rate": 0.5, "return_mean": 0.4}]
    labels = _axis_labels(monkeypatch, later, path=tmp_path / "b.png", window=100)
    assert labels[0] == "success rate\n(last 100 episodes)", labels


def test_curve_draws_sparse_health_columns(tmp_path, monkeypatch):
    rows = [{"frames": 64, "train_return": 1.0}, {"frames": 128, "train_return": 2.0, "eval_return_mean": 3.0}]
    lines: list[int] = []

    def capture(self, fname, *a, **k):
        lines.extend(len(ax.get_lines()) for ax in self.axes)
        Path(fname).write_bytes(b"png")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    plot_learning_curve(
        rows,
        tmp_path / "c.png",
        returns=(("train_return", "train"), ("eval_return_mean", "eval")),
        return_label="episode return",
    )
    assert lines == [2]  # one panel (no success), both series


# ----------------------------------------------------------------------------------------------------------------------
# the metrics logger
# ----------------------------------------------------------------------------------------------------------------------
def test_wandb_files_land_under_metrics(tmp_path, monkeypatch):
    calls = []

    class FakeLogger:
        def log_hparams(self, cfg):
            pass

    def fake_get_logger(backend, **kwargs):
        calls.append((backend, kwargs))
        return FakeLogger()

    monkeypatch.setattr(files, "get_logger", fake_get_logger)
    files.make_metrics_logger(tmp_path, "wandb", {"a": 1}, option="logging.backend")
    backend, kwargs = calls[0]
    # torchrl's WandbLogger hands its log_dir to wandb as `dir`; nothing may override it with the run dir
    assert kwargs["logger_name"] == str(tmp_path / "metrics" / "attempt_01")
    assert "dir" not in kwargs["wandb_kwargs"]


def test_missing_logger_extra_gives_a_checkout_command(tmp_path, monkeypatch):
    def missing(backend, **kwargs):
        raise ImportError("wandb could not be imported")

    monkeypatch.setattr(files, "get_logger", missing)
    with pytest.raises(FreamerError) as info:
        files.make_metrics_logger(tmp_path, "wandb", {}, option="logging.backend")
    assert 'pip install -c constraints.txt -e ".[wandb]"' in str(info.value)
    assert "logging.backend 'wandb'" in str(info.value)
