"""Benchmark suites (freamer_rl.experiments.suite): recipes x envs x seeds in worker processes, resumable, with a report."""

import csv
import json
import shutil
from pathlib import Path

import pytest

from freamer_rl.cli import main
from freamer_rl.errors import ConfigError
from freamer_rl.experiments.report import RunRecord, write_report
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
        ("name: demo\nentries: [{label: a, recipe: tiny.yaml, seeds: []}]\n", r"entries\[0\].seeds: "),
        ("name: demo\nentries: [{label: a, recipe: tiny.yaml, seeds: [0, 2, 0]}]\n", r"entries\[0\].seeds\[2\]"),
        ("name: demo\nentries: [{label: a, recipe: tiny.yaml, seeds: [-1]}]\n", r"entries\[0\].seeds\[0\]"),
        ("name: demo\ntotal_frames: 0\nentries: [{label: a, recipe: tiny.yaml}]\n", "total_frames: "),
        ("name: demo\nentries: []\n", "entries: "),
        ("name: ../demo\nentries: [{label: a, recipe: tiny.yaml}]\n", "name: "),
        (
            "name: demo\nentries: [{label: c, recipe: c.chain.yaml, envs: [MiniGrid-Empty-5x5-v0]}]\n",
            r"entries\[0\].envs: 'c.chain.yaml' is a chain",
        ),
        ("name: demo\nentries: [{label: c, recipe: c.chain.yaml, overrides: [seed=3]}]\n", r"entries\[0\].overrides"),
        (
            "name: demo\nevaluate: {conditions: [{label: clean}]}\nentries: [{label: c, recipe: c.chain.yaml}]\n",
            r"entries\[0\].recipe: .* cannot evaluate",
        ),
        (
            "name: demo\ncompare: [[a, b]]\nentries: [{label: a, recipe: tiny.yaml}]\n",
            r"compare\[0\]: 'b' is not an entry",
        ),
        (
            "name: demo\ncompare: [[a, a]]\nentries: [{label: a, recipe: tiny.yaml}]\n",
            r"compare\[0\]: expected two different",
        ),
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


ROOMS = "MiniGrid-MultiRoom-N1-S4-v0"


def test_a_chain_entry_trains_beside_a_recipe_resumes_and_reports_across_its_stages(tmp_path, capsys):
    """A ``.chain.yaml`` entry: each seed runs the whole chain in its run folder (the last stage's env), the suite's
    total_frames does not apply to it, its row counts frames across the stages, a rerun trains nothing."""
    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    (tmp_path / "c.chain.yaml").write_text(
        "name: demo_chain\nstages:\n  - {name: empty, recipe: tiny.yaml, overrides: [run.total_frames=128]}\n"
        f"  - {{name: rooms, recipe: tiny.yaml, overrides: [env.id={ROOMS}]}}\n"
    )
    path = tmp_path / "mixed.yaml"
    path.write_text(
        "name: mixed\nseeds: [0]\ntotal_frames: 128\noverrides: [ppo.epochs=1]\nentries:\n"
        "  - {label: plain, recipe: tiny.yaml}\n  - {label: cur, recipe: c.chain.yaml}\n"
    )
    out = tmp_path / "out"
    _, _, runs = plan_suite(path, out)
    assert [(r.label, r.env, r.target_frames) for r in runs] == [("plain", ENV, 128), ("cur", ROOMS, 128 + 256)]
    result = run_suite(path, output=out)
    assert sorted(result["trained"]) == [f"cur/{ROOMS}/seed0", f"plain/{ENV}/seed0"]
    run_dir = out / "runs" / "cur" / ROOMS / "seed0"
    assert json.loads((run_dir / "done.json").read_text())["frames"] == 384
    assert f"init_from: {run_dir / 'empty'}" in (run_dir / "rooms" / "config.yaml").read_text()
    assert "epochs: 1" in (run_dir / "rooms" / "config.yaml").read_text()  # the suite's overrides reach the stages
    rows = {r["label"]: r for r in _rows(out / "runs.csv")}
    assert rows["cur"]["status"] == "done" and rows["cur"]["frames"] == "384" and rows["cur"]["env"] == ROOMS
    assert rows["cur"]["episodes"] != "" and rows["plain"]["frames"] == "128"
    curve = [r for r in _rows(out / "curves.csv") if r["label"] == "cur"]
    assert [int(r["frames"]) for r in curve] == [128 + 128, 128 + 256]  # the last stage, after the first's frames
    assert f"| cur (chain) | {ROOMS} | 1/1 (0) | 384 |" in (out / "summary.md").read_text()

    stamps = {p: p.stat().st_mtime_ns for p in run_dir.glob("*/summary.json")}
    assert run_suite(path, output=out)["trained"] == []  # done: skipped
    (run_dir / "done.json").unlink()  # finished stages but no marker: partial, and the rerun reads them back
    assert main(["suite", str(path), "--output", str(out), "--dry-run"]) == 0
    assert "partial (384 frames)" in capsys.readouterr().out
    assert run_suite(path, output=out)["trained"] == [f"cur/{ROOMS}/seed0"]
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps and (run_dir / "done.json").is_file()


def test_chain_run_report_counts_to_95_across_the_stages(tmp_path):
    run_dir = tmp_path / "runs" / "c" / "e" / "seed0"
    stages = {"a": (1000, 40, None, None), "b": (500, 10, 300, 6)}  # frames, episodes, frames / episodes to 95%
    for name, (frames, episodes, f95, e95) in stages.items():
        (run_dir / name).mkdir(parents=True)
        summary = {"frames": frames, "episodes": episodes, "frames_to_95": f95, "episodes_to_95": e95}
        extra = {"final_success_rate": 0.97, "trainable_params": 1234, "privileged": ["x"] if name == "a" else []}
        (run_dir / name / "summary.json").write_text(json.dumps({**summary, **extra}))
        (run_dir / name / "progress.csv").write_text(f"frames,episodes,success_rate\n{frames},{episodes},0.97\n")
    (run_dir / "done.json").write_text(json.dumps({"total_frames": 1500, "frames": 1500}))
    record = RunRecord(label="c", env="e", env_dir="e", seed=0, run_dir=run_dir, target_frames=1500, stages=["a", "b"])
    (row,) = write_report(tmp_path, "demo", [record])
    assert (row["frames"], row["episodes"], row["frames_to_95"], row["episodes_to_95"]) == (1500, 50, 1300, 46)
    assert row["success_rate"] == 0.97 and [(r["frames"], r["episodes"]) for r in row["rows"]] == [(1500, 50)]
    assert row["trainable_params"] == 1234 and row["privileged"] == "x"  # the model's size; any stage's privilege


def _chain_records(root: Path, plan: dict) -> list[RunRecord]:
    """Chain runs of stages "a" and "b" from ``plan``: {(label, seed): [(stage, frames, success, frames to 95%)]};
    a run with both stages is done."""
    records = []
    for (label, seed), stages in plan.items():
        run_dir = root / "runs" / label / "e" / f"seed{seed}"
        for name, frames, success, f95 in stages:
            (run_dir / name).mkdir(parents=True)
            summary = {"frames": frames, "final_success_rate": success, "frames_to_95": f95, "episodes_to_95": None}
            (run_dir / name / "summary.json").write_text(json.dumps(summary))
            (run_dir / name / "progress.csv").write_text(f"frames,episodes,success_rate\n{frames},10,{success}\n")
        if len(stages) == 2:
            (run_dir / "done.json").write_text(json.dumps({"total_frames": None, "frames": 400}))
        records.append(
            RunRecord(
                label=label, env="e", env_dir="e", seed=seed, run_dir=run_dir, target_frames=None, stages=["a", "b"]
            )
        )
    return records


def test_the_chain_stage_table_says_where_each_arm_stalled(tmp_path):
    records = _chain_records(
        tmp_path,
        {  # the learner passes both stages, the staller sticks at stage b; its seed 1 still trains stage b
            ("learner", 0): [("a", 100, 0.9, None), ("b", 300, 0.99, 50)],
            ("learner", 1): [("a", 200, 0.92, None), ("b", 300, 0.97, 80)],
            ("staller", 0): [("a", 150, 0.91, None), ("b", 300, 0.0, None)],
            ("staller", 1): [("a", 250, 0.93, None)],
        },
    )
    write_report(tmp_path, "demo", records)
    table = (tmp_path / "summary.md").read_text().split("## Chain stages")[1]
    assert "| arm | a | b |" in table
    assert (
        "| learner | 2/2: 150 (100–200) frames, success 0.91 (0.90–0.92) | 2/2: 300 frames, success 0.98 (0.97–0.99) |"
        in table
    )
    assert "| staller | 2/2: 200 (150–250) frames, success 0.92 (0.91–0.93) | 1/2: 300 frames, success 0.00 |" in table


def test_compare_pairs_read_a_stalled_arm_as_slower_not_as_missing(tmp_path):
    # three seeds each: A reaches 95% in every run, B in none (its IQM column stays empty); then B reaches it too,
    # later than A in two runs of three and sooner in one
    stalled = {("A", k): [("a", 100, 0.9, None), ("b", 300, 0.99, 50 + k)] for k in range(3)}
    stalled |= {("B", k): [("a", 100, 0.9, None), ("b", 300, 0.1, None)] for k in range(3)}
    write_report(tmp_path / "one", "demo", _chain_records(tmp_path / "one", stalled), compare=[["A", "B"]])
    text = (tmp_path / "one" / "summary.md").read_text().split("## Comparisons")[1]
    # frames to 95% across the chain: stage a's 100 frames plus the stage's own
    row = "| A vs B | e | 3 / 3 | 3 / 0 | 1.00 [1.00, 1.00] | A ahead of B | 1.00 [1.00, 1.00] (final success) | A ahead of B |"
    assert row in text
    mixed = {("A", k): [("a", 100, 0.9, None), ("b", 300, 0.99, 50 + 10 * k)] for k in range(3)}
    mixed |= {("B", k): [("a", 100, 0.9, None), ("b", 300, 0.99, [45, 90, 95][k])] for k in range(3)}
    write_report(tmp_path / "two", "demo", _chain_records(tmp_path / "two", mixed), compare=[["A", "B"]])
    text = (tmp_path / "two" / "summary.md").read_text().split("## Comparisons")[1]
    assert "| A vs B | e | 3 / 3 | 3 / 3 | 0.67 [" in text and "no clear difference" in text
    few = {key: stages for key, stages in stalled.items() if key[1] < 2}
    write_report(tmp_path / "few", "demo", _chain_records(tmp_path / "few", few), compare=[["A", "B"]])
    assert "too few seeds (< 3 per arm)" in (tmp_path / "few" / "summary.md").read_text()


def test_compare_pairs_on_a_task_without_success_read_the_final_return():
    from freamer_rl.experiments.learning_compare import learning_compare_markdown

    def run(label: str, seed: int, ret: float) -> dict:
        return {"label": label, "env": "CartPole-v1", "seed": seed, "status": "done", "success_rate": None,
                "return_mean": ret, "frames_to_95": None, "levels_unknown": []}  # fmt: skip

    results = [run("A", k, 500.0) for k in range(3)] + [run("B", k, 400.0 + k) for k in range(3)]
    (row,) = [line for line in learning_compare_markdown(results, [["A", "B"]]) if line.startswith("| A vs B")]
    assert "| n/a | n/a | n/a (no success rate" in row  # no "sooner to 95%" without a success rate
    assert "1.00 [1.00, 1.00] (final return) | A ahead of B |" in row


def test_an_entry_with_its_own_seeds(tmp_path):
    # more seeds for the arm a comparison turns on: the entry's seeds replace the suite's for that entry alone, and
    # the report counts each arm over its own seeds
    path = _suite(
        tmp_path,
        "  - {label: a, recipe: tiny.yaml}\n  - {label: more, recipe: tiny.yaml, seeds: [0, 1, 2]}\n",
        total_frames=128,
    )
    _, _, runs = plan_suite(path, tmp_path / "out")
    assert [(r.label, r.seed) for r in runs] == [("a", 0), ("a", 1), ("more", 0), ("more", 1), ("more", 2)]
    result = run_suite(path, jobs=2, output=tmp_path / "out")
    assert len(result["trained"]) == 5
    summary = (tmp_path / "out" / "summary.md").read_text()
    assert f"| a | {ENV} | 2/2 (0 1) |" in summary and f"| more | {ENV} | 3/3 (0 1 2) |" in summary


def test_only_trains_the_named_entries_and_reports_every_run(tmp_path, capsys):
    # a long suite in parts: --only trains the named entries; the others stay new, and the report lists them all
    path = _suite(
        tmp_path,
        "  - {label: a, recipe: tiny.yaml}\n  - {label: b, recipe: tiny.yaml}\n  - {label: c, recipe: tiny.yaml}\n",
        total_frames=128,
    )
    out = tmp_path / "out"
    assert main(["suite", str(path), "--output", str(out), "--only", "c", "--only", "a"]) == 0
    runs = {(r["label"], r["seed"]): r["status"] for r in _rows(out / "runs.csv")}
    assert runs == {
        ("a", "0"): "done",
        ("a", "1"): "done",
        ("b", "0"): "new",
        ("b", "1"): "new",
        ("c", "0"): "done",
        ("c", "1"): "done",
    }
    assert not (out / "runs" / "b").exists()
    capsys.readouterr()
    assert main(["suite", str(path), "--output", str(out), "--only", "d"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--only: no entry labelled d" in err and "a, b, c" in err
