"""Smoke tests of benchmarks/throughput_benchmark.py (tiny settings; the figures come from the benchmark command)."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import throughput_benchmark as tb  # noqa: E402


def test_throughput_benchmark_writes_tables(tmp_path):
    """One round, one thread, 16 envs, one timed batch of 256 frames: current code + baseline (given the recipe's
    batch size); 256 envs is skipped with a note (one step per batch is shorter than a sequence)."""
    text = tb.main(
        [
            "--rounds",
            "1",
            "--batches",
            "1",
            "--threads",
            "1",
            "--num-envs",
            "16",
            "256",
            "--skip-old",
            "--out",
            str(tmp_path),
            # small batches, eager: the smoke test checks the tables, not the speed (compiling alone takes ~40 s)
            "model.compile=false",
            "ppo.frames_per_batch=256",
            "ppo.minibatch_size=128",
            "ppo.epochs=1",
        ]
    )
    assert (tmp_path / "results.md").read_text() == text
    assert "FreamerV1 current" in text and "TorchRL PPO-MLP" in text and "overall vs baseline" in text
    assert "env.num_envs=256 skipped" in text and "sequence_length" in text
    with (tmp_path / "results.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == tb.CSV_FIELDS
    assert [(r["method"], r["threads"], r["num_envs"]) for r in rows] == [
        ("current", "1", "16"),
        ("baseline", "1", "16"),
    ]
    for r in rows:
        for m in tb.METRICS:
            assert float(r[f"{m}_min"]) <= float(r[f"{m}_mean"]) <= float(r[f"{m}_max"])
            assert float(r[f"{m}_mean"]) > 0
    cur = rows[0]
    assert cur["overall_vs_old"] == "" and float(cur["overall_vs_baseline"]) > 0
    # overall = frames / (collection + update): below both parts' rates
    assert float(cur["overall_fps_mean"]) < min(float(cur["collect_fps_mean"]), float(cur["update_fps_mean"]))
    with (tmp_path / "rounds.csv").open() as f:
        rounds = list(csv.DictReader(f))
    assert [r["method"] for r in rounds] == ["current", "baseline"]
    assert all(r["error"] == "" and r["num_threads"] == "1" for r in rounds)
    assert rounds[0]["source"].startswith(str(ROOT / "src"))  # the current code is this checkout's


def test_ratios_are_per_round_and_old_rows_appear(tmp_path):
    """The report logic with made-up rounds: ratios pair measurements of the same round; errors become notes."""
    rounds = []
    for rnd, (cur, old, base) in enumerate([(100.0, 50.0, 200.0), (300.0, 100.0, 300.0)]):
        for m, v in (("current", cur), ("old", old), ("baseline", base)):
            rounds.append(
                {
                    "round": rnd,
                    "threads": 1,
                    "num_envs": 16,
                    "method": m,
                    "collect_fps": 2 * v,
                    "update_fps": 2 * v,
                    "overall_fps": v,
                }
            )
    rounds.append({"round": 2, "threads": 1, "num_envs": 16, "method": "old", "error": "exit 1: boom"})
    codes = {"current": "abc", "old": "411f9a7", "baseline": "ppo_baseline"}
    rows = tb.summarise(rounds, [(1, 16)], ["current", "old", "baseline"], codes)
    cur = rows[0]
    assert cur["overall_fps_mean"] == 200.0 and (cur["overall_fps_min"], cur["overall_fps_max"]) == (100.0, 300.0)
    assert cur["overall_vs_old"] == pytest.approx((2.0 + 3.0) / 2)  # not 200 / 75
    assert cur["overall_vs_baseline"] == pytest.approx((0.5 + 1.0) / 2)
    meta = {
        "date": "now",
        "machine": "test",
        "load_start": "0",
        "load_end": "0",
        "codes": codes,
        "rounds": 2,
        "batches": 1,
        "warmup": 1,
        "frames_per_batch": 2048,
        "overrides": "",
        "command": "x",
    }
    text = tb.write_report(rows, rounds, [], tmp_path, meta)
    assert "FreamerV1 old" in text and "2.50 (2.00-3.00)" in text and "boom" in text


def test_old_commit_extracts_with_its_envs_package(tmp_path):
    try:
        sha = tb.extract_commit("411f9a7", tmp_path)
    except (subprocess.CalledProcessError, FileNotFoundError):
        pytest.skip("commit 411f9a7 not in this checkout's history")
    assert sha.startswith("411f9a7")
    assert (tmp_path / "src" / "freamer_rl" / "train.py").is_file()
    assert (tmp_path / "envs" / "minigrid.py").is_file()
