"""Benchmark suites (freamer_rl.experiments.suite): recipes x envs x seeds in worker processes, resumable, with a report."""

import csv
import shutil
from pathlib import Path

import pytest

from freamer_rl.cli import main
from freamer_rl.errors import ConfigError
from freamer_rl.experiments.suite import env_folder, load_suite, plan_suite, run_suite

ROOT = Path(__file__).resolve().parents[2]
ENV = "MiniGrid-Empty-5x5-v0"


def _suite(folder: Path, entries: str, *, total_frames: int = 256, name: str = "demo", extra: str = "") -> Path:
    shutil.copy(ROOT / "recipes" / "tiny.yaml", folder / "tiny.yaml")
    path = folder / f"{name}_{total_frames}.yaml"
    path.write_text(
        f"name: {name}\nseeds: [0, 1]\ntotal_frames: {total_frames}\noverrides: [ppo.epochs=1]\n{extra}"
        f"entries:\n{entries}"
    )
    return path


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_suite_trains_resumes_skips_and_reports(tmp_path, capsys):
    out = tmp_path / "out"
    first = _suite(tmp_path, "  - {label: a, recipe: tiny.yaml}\n", total_frames=128)
    result = run_suite(first, jobs=2, output=out)  # "interrupted": only entry a, half the budget
    assert sorted(result["trained"]) == [f"a/{ENV}/seed0", f"a/{ENV}/seed1"]

    full = _suite(
        tmp_path,
        "  - {label: a, recipe: tiny.yaml}\n"
        "  - {label: b, recipe: tiny.yaml, overrides: [optim.lr=1e-3]}\n"
        "  - {label: bad, recipe: tiny.yaml, overrides: [optim.lr=fast]}\n"
        "  - {label: noenv, recipe: tiny.yaml, envs: [MiniGrid-Nope-v0]}\n",
    )
    assert main(["suite", str(full), "--output", str(out), "--dry-run"]) == 0
    listing = capsys.readouterr().out
    assert "partial (128 frames)" in listing and " new" in listing and "failed: " in listing and "optim.lr" in listing

    # the larger budget resumes a's runs, trains b's; the failing entries are reported and the others finish
    assert main(["suite", str(full), "--jobs", "1", "--output", str(out)]) == 1
    assert "4 of 8 runs failed" in capsys.readouterr().err
    runs = {(r["label"], r["seed"]): r for r in _rows(out / "runs.csv")}
    assert len(runs) == 8
    for label in ("a", "b"):
        for seed in ("0", "1"):
            assert runs[label, seed]["status"] == "done" and runs[label, seed]["frames"] == "256"
            assert runs[label, seed]["env"] == ENV and runs[label, seed]["success_rate"] != ""
    assert (out / "runs" / "a" / ENV / "seed0" / "metrics" / "attempt_02").is_dir()  # resumed, not restarted
    assert runs["bad", "0"]["status"] == "failed" and "optim.lr" in runs["bad", "0"]["error"]
    assert runs["noenv", "1"]["status"] == "failed" and "MiniGrid-Nope-v0" in runs["noenv", "1"]["error"]
    summary = (out / "summary.md").read_text()
    assert "| a | MiniGrid-Empty-5x5-v0 | 2/2 (0 1) |" in summary and "| b |" in summary and "## Failed runs" in summary
    assert {r["label"] for r in _rows(out / "summary.csv")} == {"a", "b", "bad", "noenv"}
    curves = _rows(out / "curves.csv")
    assert {"label", "env", "seed", "frames", "success_rate", "return_mean"} <= set(curves[0])
    assert len([r for r in curves if r["label"] == "b"]) == 4  # 2 seeds x 2 batches
    plots = [out / f"curve_{ENV}_{m}.png" for m in ("success_rate", "return_mean")]
    assert all(p.stat().st_size > 1000 for p in plots)

    # rerunning the same command trains nothing: finished runs are skipped
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("[ab]/*/seed*/summary.json")}
    assert len(stamps) == 4
    again = run_suite(full, output=out)
    assert again["trained"] == [] and len(again["failed"]) == 4
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps

    # --report-only rebuilds the tables and plots from the run folders alone
    for p in [out / "summary.md", out / "runs.csv", *plots]:
        p.unlink()
    assert main(["suite", str(full), "--output", str(out), "--report-only"]) == 0
    assert (out / "summary.md").read_text() == summary and all(p.stat().st_size > 1000 for p in plots)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps


def test_plan_folders_and_overrides(tmp_path, monkeypatch):
    path = _suite(
        tmp_path,
        "  - {label: a, recipe: tiny.yaml, overrides: [optim.lr=1e-3]}\n"
        "  - {label: b, recipe: tiny.yaml, envs: [MiniGrid-Empty-8x8-v0]}\n",
        extra="envs: [MiniGrid-Empty-6x6-v0, ALE/Pong-v5]\n",
    )
    monkeypatch.chdir(tmp_path)
    suite, root, runs = plan_suite(path)
    assert root == Path("results/demo")
    assert [(r.label, r.env_dir, r.seed) for r in runs] == [
        ("a", "MiniGrid-Empty-6x6-v0", 0),
        ("a", "MiniGrid-Empty-6x6-v0", 1),
        ("a", "ALE_Pong-v5", 0),
        ("a", "ALE_Pong-v5", 1),
        ("b", "MiniGrid-Empty-8x8-v0", 0),
        ("b", "MiniGrid-Empty-8x8-v0", 1),
    ]
    assert runs[1].run_dir == Path("results/demo/runs/a/MiniGrid-Empty-6x6-v0/seed1")
    assert runs[1].overrides == [
        "env.id=MiniGrid-Empty-6x6-v0",
        "run.total_frames=256",
        "ppo.epochs=1",
        "optim.lr=1e-3",
        "run.seed=1",
        "logging.progress_bar=false",
    ]
    assert runs[1].target_frames == 256 and runs[1].error is None
    assert env_folder("ALE/Pong-v5") == "ALE_Pong-v5"


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("name: demo\nentries: [{label: a, recipe: tiny.yaml}]\nseed: [0]\n", "unknown key 'seed'"),
        (
            "name: demo\nentries: [{label: a, recipe: tiny.yaml, overide: [x=1]}]\n",
            r"unknown key 'entries\[0\].overide'",
        ),
        ("name: demo\nentries: [{label: ../a, recipe: tiny.yaml}]\n", r"entries\[0\].label"),
        (
            "name: demo\nentries: [{label: a, recipe: tiny.yaml}, {label: a, recipe: tiny.yaml}]\n",
            r"entries\[1\].label: 'a' is used twice",
        ),
        ("name: demo\nentries: [{label: a, recipe: nope.yaml}]\n", r"entries\[0\].recipe: no such recipe file"),
        ("name: demo\nenvs: [MiniGrid-Empty-5x5-v0, ..]\nentries: [{label: a, recipe: tiny.yaml}]\n", r"envs\[1\]"),
        ("name: demo\nentries: [{label: a, recipe: tiny.yaml, envs: [a/b, a_b]}]\n", r"entries\[0\].envs\[1\]"),
        ("name: demo\nseeds: []\nentries: [{label: a, recipe: tiny.yaml}]\n", "seeds: "),
        ("name: demo\ntotal_frames: 0\nentries: [{label: a, recipe: tiny.yaml}]\n", "total_frames: "),
        ("name: demo\nentries: []\n", "entries: "),
        ("name: ../demo\nentries: [{label: a, recipe: tiny.yaml}]\n", "name: "),
    ],
)
def test_suite_validation_names_the_field(tmp_path, text, field):
    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    path = tmp_path / "suite.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=field):
        load_suite(path)


def test_suite_cli_user_error_is_one_line(tmp_path, capsys):
    path = tmp_path / "suite.yaml"
    path.write_text("name: demo\nentries: [{label: a, recipe: tiny.yaml}]\nsedes: [0]\n")
    assert main(["suite", str(path), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "suite.yaml" in err and "sedes" in err and err.count("\n") == 1
    assert main(["suite", str(ROOT / "recipes" / "suites" / "n2s4_baselines.yaml"), "--jobs", "0"]) == 2


def test_example_suite_plans(tmp_path):
    suite, _, runs = plan_suite(ROOT / "recipes" / "suites" / "n2s4_baselines.yaml", tmp_path)
    labels = ["freamer", "freamer_machinery", "ppo_mlp", "impala", "dreamer_v3"]
    assert [r.label for r in runs] == [lab for lab in labels for _ in range(3)]
    assert [r.seed for r in runs] == [0, 1, 2] * len(labels)
    assert all(r.error is None and r.env == "MiniGrid-MultiRoom-N2-S4-v0" for r in runs)
    # every suite shipped in recipes/suites plans without a config error (recipes of every trainer load)
    for path in sorted((ROOT / "recipes" / "suites").glob("*.yaml")):
        assert all(r.error is None for r in plan_suite(path, tmp_path / path.stem)[2]), path
