"""Smoke tests of benchmarks/throughput_benchmark.py (tiny settings; the figures come from the benchmark command)."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import throughput_benchmark as tb  # noqa: E402
import throughput_crafter as tc  # noqa: E402


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
    assert all(r["error"] == "" and r["num_threads"] == "1" and float(r["first_batch_s"]) > 0 for r in rounds)
    assert "| first batch s |" in text
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


def test_flat_layout_commit_is_timed_from_its_own_tree(tmp_path):
    """5ad16f0 (the code of the README's first throughput table) predates the tiered sub-packages and imports its
    adapters as ``freamer_rl_envs``: the worker loads its config loader, trainer and MiniGrid adapter from its own
    tree and times one small eager batch."""
    try:
        tb.extract_commit("5ad16f0", tmp_path / "tree")
    except (subprocess.CalledProcessError, FileNotFoundError):
        pytest.skip("commit 5ad16f0 not in this checkout's history")
    tree = tmp_path / "tree"
    assert (tree / "freamer_rl_envs" / "minigrid.py").is_file()  # the envs/ package under its installed name
    small = ["model.compile=false", "ppo.frames_per_batch=256", "ppo.minibatch_size=128", "ppo.epochs=1"]
    spec = {"method": "old", "threads": 1, "num_envs": 4, "batches": 1, "warmup": 0, "seed": 0, "patch_envs": True}
    spec.update(recipe=str(tree / "recipes" / "minigrid_multiroom_n2s4.yaml"), tree=str(tree))
    spec["overrides"] = [*small, "run.threads=1", "env.num_envs=4", "run.total_frames=256"]
    res = tb.run_job(spec, tree, timeout=300)
    assert "error" not in res, res["error"]
    assert res["source"] == f"{tree.resolve() / 'src' / 'freamer_rl'} (+ envs.minigrid patch)"
    assert res["frames"] == 256 and res["overall_fps"] > 0 and res["first_batch_s"] > 0


def test_crafter_suite_writes_every_row_and_ratio(tmp_path, monkeypatch):
    """``--suite crafter``, one round, one thread, 2 envs, one timed batch of 64 frames (eager, one epoch), both
    trainers. The measurements run in this process (``measure``, what each worker subprocess runs): the subprocess
    runner is the N2-S4 test's, and four interpreter starts would triple this test's time."""
    pytest.importorskip("crafter")
    monkeypatch.setattr(tb, "run_job", lambda spec, tree, timeout: tb.measure(spec))
    small = ["ppo.minibatch_size=32", "ppo.epochs=1"]
    argv = ["--suite", "crafter", "--rounds", "1", "--batches", "1", "--threads", "1", "--num-envs", "2"]
    argv += ["--out", str(tmp_path), "model.compile=false", "ppo.frames_per_batch=64", *small]
    text = tb.main([*argv, *[f"--baseline-override={o}" for o in small]])
    assert (tmp_path / "results.md").read_text() == text
    assert all(name in text for name in tc.NAMES.values()) and "raw env, 1 thread(s):" in text
    with (tmp_path / "results.csv").open() as f:
        rows = {r["method"]: r for r in csv.DictReader(f)}
    assert list(rows) == list(tc.METHODS) and list(rows["freamer"]) == tc.CSV_FIELDS
    raw = float(rows["raw_env"]["collect_fps_mean"])  # steps/s
    assert raw > 0 and float(rows["adapter_env"]["collect_vs_raw_env"]) > 0
    for m in tc.ENV_METHODS:
        assert rows[m]["update_fps_mean"] == rows[m]["overall_fps_mean"] == ""  # an env has no update
    for m in ("freamer_inline", "freamer", "ppo_cnn"):
        adapter = tc.PAIRS[m][1]  # the adapter env of the same reset setting
        keys = ("_mean", "_vs_raw_env", f"_vs_{adapter}")
        r = {k: float(v) for k, v in rows[m].items() if k.endswith(keys) and v != ""}
        assert all(v > 0 for v in r.values()) and len(r) == 3 + 3 + 1
        # overall = frames / (collection + update): below both parts' rates
        assert r["overall_fps_mean"] < min(r["collect_fps_mean"], r["update_fps_mean"])
        # one round: each ratio is the rate over the raw env's (or the adapter env's) steps/s of that round
        assert r["overall_vs_raw_env"] == pytest.approx(r["overall_fps_mean"] / raw, rel=2e-3)
        env = float(rows[adapter]["collect_fps_mean"])
        assert r[f"collect_vs_{adapter}"] == pytest.approx(r["collect_fps_mean"] / env, rel=2e-3)
    assert "FreamerV1 (crafter_cpu), 1 thread(s): overall fps" in text  # against its resets-inline twin
    with (tmp_path / "rounds.csv").open() as f:
        rounds = list(csv.DictReader(f))
    assert [r["method"] for r in rounds] == list(tc.METHODS) and all(r["error"] == "" for r in rounds)
    assert float(rounds[0]["step_s"]) > 0 and int(rounds[0]["frames"]) == 64  # the raw env: one batch of steps


def test_crafter_ratios_pair_rounds_against_the_raw_env(tmp_path):
    """Made-up rounds: each training rate is divided by the raw env's steps/s of its own round."""
    rounds = []
    for rnd, (raw, env, fps) in enumerate([(200.0, 100.0, 40.0), (100.0, 50.0, 40.0)]):
        rounds.append({"round": rnd, "method": "raw_env", "collect_fps": raw, "frames": 10, "step_s": 1.0})
        rounds[-1].update(reset_s=1.0, resets=2)
        rounds.append({"round": rnd, "method": "adapter_env", "collect_fps": env})
        rounds.append({"round": rnd, "method": "adapter_env_inline", "collect_fps": env / 2})
        for m in ("freamer", "ppo_cnn"):
            rounds.append({"round": rnd, "method": m, "collect_fps": fps, "update_fps": 2 * fps, "overall_fps": fps})
        inline = {"collect_fps": fps / 2, "update_fps": 2 * fps, "overall_fps": fps / (1 + rnd)}
        rounds.append({"round": rnd, "method": "freamer_inline", **inline})
    for r in rounds:
        r.update(threads=1, num_envs=8)
    rows = tb.summarise(rounds, [(1, 8)], list(tc.METHODS), dict.fromkeys(tc.METHODS, "x"), tc.PAIRS, tc.REFERENCE)
    by = {r["method"]: r for r in rows}
    assert by["freamer"]["overall_vs_raw_env"] == pytest.approx((0.2 + 0.4) / 2)  # not 40 / 150
    assert by["freamer"]["update_vs_raw_env"] == pytest.approx((0.4 + 0.8) / 2)
    assert by["freamer"]["collect_vs_adapter_env"] == pytest.approx((0.4 + 0.8) / 2)
    assert by["adapter_env"]["collect_vs_raw_env"] == pytest.approx(0.5) and by["raw_env"]["update_fps_mean"] is None
    meta = {"date": "now", "machine": "test", "load_start": "0", "load_end": "0", "rounds": 2, "batches": 1}
    meta.update(codes=dict.fromkeys(tc.METHODS, "x"), warmup=1, frames_per_batch=64, overrides="", command="x")
    text = tb.write_crafter_report(rows, rounds, [], tmp_path, {**meta, "recipe": "r.yaml"})
    assert "0.30 (0.20-0.40)" in text and "100.00 ms per step, 0.50 s per reset, 4 resets in 20 steps" in text
    assert by["freamer_inline"]["collect_vs_adapter_env_inline"] == pytest.approx((0.4 + 0.8) / 2)
    # the prefetching measurement over its inline twin, round by round: overall 40/40 and 40/20
    assert "FreamerV1 (crafter_cpu), 1 thread(s): overall fps 1.50 (1.00-2.00)x" in text
    assert "adapter env (random actions), 1 thread(s): collection fps 2.00 (2.00-2.00)x" in text
