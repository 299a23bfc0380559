"""A suite's results folder: checked up front, locked for the whole suite; its workers die with it (kill -9)."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from freamer_rl.cli import main
from freamer_rl.experiments.progress import OverallProgress
from freamer_rl.run.rundir import LOCK_NAME, RunDirLock

ROOT = Path(__file__).resolve().parents[2]
ENV = "MiniGrid-Empty-5x5-v0"


def _suite(folder: Path, total_frames: int, seeds: str = "[0]") -> Path:
    shutil.copy(ROOT / "recipes" / "tiny.yaml", folder / "tiny.yaml")
    path = folder / "suite.yaml"
    path.write_text(
        f"name: safety\nseeds: {seeds}\ntotal_frames: {total_frames}\noverrides: [ppo.epochs=1]\n"
        "entries:\n  - {label: a, recipe: tiny.yaml}\n"
    )
    return path


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_an_output_that_cannot_be_created_is_one_line_before_training(tmp_path, capsys):
    (tmp_path / "afile").write_text("in the way")
    out = tmp_path / "afile" / "results"
    assert main(["suite", str(_suite(tmp_path, 128)), "--output", str(out)]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("error: --output: cannot create or write the folder") and str(out) in line


def test_a_second_suite_on_the_same_folder_is_refused_with_the_holders_pid(tmp_path, capsys):
    out = tmp_path / "out"
    with RunDirLock(out):  # what a running suite holds on its results folder
        assert main(["suite", str(_suite(tmp_path, 128)), "--output", str(out)]) == 2
        line = _one_error_line(capsys)
    assert f"pid {os.getpid()}" in line and "in use by another suite" in line and str(out) in line
    assert not (out / "runs").exists()  # nothing trained


def _children(pid: int) -> list[int]:
    """Pids whose parent is ``pid`` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie trains nothing; reaping it is init's job


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_of_the_suite_ends_its_workers_and_frees_the_run_locks(tmp_path):
    out = tmp_path / "out"
    run_dir = out / "runs" / "a" / ENV / "seed0"
    suite = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "freamer_rl.cli",
            "--log-level",
            "WARNING",
            "suite",
            str(_suite(tmp_path, 10_000_000)),
            "--output",
            str(out),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 180
        lock = run_dir / LOCK_NAME
        while not (lock.is_file() and lock.stat().st_size):  # the worker is training: it holds the run's lock
            assert suite.poll() is None and time.monotonic() < deadline, "the suite never started its run"
            time.sleep(0.5)
        workers = _children(suite.pid)
        assert workers
        os.kill(suite.pid, signal.SIGKILL)
        suite.wait()
        deadline = time.monotonic() + 120  # SIGTERM lets the trainer checkpoint first
        while any(_alive(w) for w in workers):
            assert time.monotonic() < deadline, f"workers still running after kill -9 of the suite: {workers}"
            time.sleep(0.5)
        with RunDirLock(run_dir):  # a rerun may take the run at once
            pass
    finally:
        for pid in [suite.pid, *workers]:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_of_the_suite_stops_it_without_starting_the_queued_runs(tmp_path):
    out = tmp_path / "out"
    command = [sys.executable, "-m", "freamer_rl.cli", "--log-level", "WARNING", "suite"]
    suite = subprocess.Popen(
        [*command, str(_suite(tmp_path, 10_000_000, "[0, 1, 2]")), "--output", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 180
        progress = out / "runs" / "a" / ENV / "seed0" / "progress.csv"
        while not (progress.is_file() and len(progress.read_text().splitlines()) > 1):  # training, handler set
            assert suite.poll() is None and time.monotonic() < deadline, "the suite never started its run"
            time.sleep(0.5)
        suite.terminate()
        suite.wait(timeout=120)  # the run checkpoints, and the job queued behind it returns at once
        assert suite.returncode != 0
        assert not (out / "runs" / "a" / ENV / "seed1").exists()  # ProcessPoolExecutor had queued it: never started
        assert list((out / "runs" / "a" / ENV / "seed0" / "checkpoints").glob("*.pt"))  # SIGTERM checkpointed
    finally:
        if suite.poll() is None:
            suite.kill()


def test_overall_progress_logs_share_and_eta_per_finished_item(caplog):
    caplog.set_level(logging.INFO, logger="freamer_rl.experiments.progress")
    progress = OverallProgress("suite demo", [100, 300], item="runs")  # pytest's output is not a terminal
    progress.advance(1, "a/env/seed1 done")
    progress.advance(0, "a/env/seed0 done")
    progress.close()
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0].startswith("suite demo: 1/2 runs finished (75% of the frames) | ETA ")
    assert lines[0].endswith("| a/env/seed1 done") and "ETA n/a" not in lines[0]
    assert lines[1].startswith("suite demo: 2/2 runs finished (100% of the frames) | ETA 0m00s")


def test_overall_progress_counts_items_when_a_budget_is_unknown(caplog):
    caplog.set_level(logging.INFO, logger="freamer_rl.experiments.progress")
    progress = OverallProgress("chain c", [100, None, 50], item="stages")
    progress.advance(0, "stage a")
    assert caplog.records[-1].getMessage().startswith("chain c: 1/3 stages finished (33%) | ETA ")
