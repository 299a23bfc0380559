"""What a user sees: start and end lines, plain progress lines when piped, no library noise, the learning curve."""

import json
import logging
import math
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from freamer_rl.run import metrics
from freamer_rl.run.metrics import (
    ProgressReporter,
    format_duration,
    format_rate,
    plot_learning_curve,
    quiet_library_logs,
)

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"


def test_piped_tiny_run_shows_start_progress_and_summary(tmp_path):
    """The tiny recipe on run.device=cpu with stdout and stderr piped (not a terminal): no tqdm, no TorchRL INFO."""
    run = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "freamer_rl.cli",
            "train",
            str(TINY),
            "run.device=cpu",
            "logging.progress_bar=true",
            "--run-dir",
            str(run),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    lines = out.splitlines()
    start = [ln for ln in lines if f"run dir {run}" in ln and "trainable parameters" in ln]
    assert len(start) == 1 and "device cpu" in start[0]
    progress = [ln for ln in lines if "frames 128/256" in ln]
    assert len(progress) == 1 and "frames/s" in progress[0] and "episodes" in progress[0]
    end = [ln for ln in lines if "finished: 256 frames" in ln]
    assert len(end) == 1
    for part in ("episodes", "success", "return", "wall time", f"run dir {run}"):
        assert part in end[0]
    assert "Initialized LazyTensorStorage" not in out
    assert "[torchrl]" not in out
    assert "\r" not in out  # no progress bar redraws in a log file
    summary = json.loads((run / "summary.json").read_text())
    assert summary["frames"] == 256
    assert (run / "learning_curve.png").stat().st_size > 0


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def test_learning_curve_with_and_without_success(tmp_path):
    rows = [
        {
            "frames": 128 * i,
            "episodes": 100 * i,
            "success_rate": math.nan if i == 1 else i / 10,
            "return_mean": math.nan if i == 1 else i,
        }
        for i in range(1, 8)
    ]
    both = tmp_path / "both.png"
    plot_learning_curve(rows, both, title="MiniGrid-Empty-5x5-v0", window=100)
    no_success = [{**r, "success_rate": math.nan} for r in rows]
    ret_only = tmp_path / "return_only.png"
    plot_learning_curve(no_success, ret_only, title="CartPole-v1")
    w_both, h_both = _png_size(both)
    w_ret, h_ret = _png_size(ret_only)
    assert w_both == w_ret and h_ret < h_both  # two stacked panels vs the return panel only
    assert not list(tmp_path.glob("*.tmp.png"))


def test_plain_progress_lines_are_rate_limited(caplog, monkeypatch):
    monkeypatch.setattr(metrics, "_is_terminal", lambda: False)
    stats = metrics.EpisodeStats(window=10)
    reporter = ProgressReporter(total=1000, initial=0, bar=True, interval_s=3600.0)
    with caplog.at_level(logging.INFO, logger="freamer_rl.run.metrics"):
        for frames in range(100, 1001, 100):
            reporter.update(frames, 100, stats)
    reporter.close()
    lines = [r.getMessage() for r in caplog.records if r.name == "freamer_rl.run.metrics"]
    assert len(lines) == 1  # the first batch, then nothing until interval_s has passed
    assert "frames 100/1000 (10%)" in lines[0] and "success n/a" in lines[0] and "return n/a" in lines[0]
    fast = ProgressReporter(total=1000, initial=0, bar=False, interval_s=0.0)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="freamer_rl.run.metrics"):
        fast.update(100, 100, stats)
        fast.update(200, 100, stats)
    assert len([r for r in caplog.records if r.name == "freamer_rl.run.metrics"]) == 2


def test_quiet_library_logs_hides_info_and_restores_the_level(caplog):
    lib = logging.getLogger("torchrl")
    before = lib.level
    with quiet_library_logs():
        assert not lib.isEnabledFor(logging.INFO)
        assert lib.isEnabledFor(logging.WARNING)
    assert lib.level == before


def test_formatting_helpers():
    assert format_rate(0.625) == "0.62" and format_rate(math.nan) == "n/a"
    assert format_duration(9.42) == "9.4 s"
    assert format_duration(725) == "12 min 5 s"
    assert format_duration(3780) == "1 h 3 min"


@pytest.mark.parametrize(
    "path",
    ["run/loop.py", "run/lifecycle.py", "run/metrics.py", "health/trainer.py", "config/loader.py", "config/checks.py"],
)
def test_modules_stay_under_600_lines(path):
    assert len((ROOT / "src" / "freamer_rl" / path).read_text().splitlines()) < 600
