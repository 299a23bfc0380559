"""Robustness evaluation of suites (freamer_rl.experiments.robustness): conditions, resumable evaluation, report."""

import csv
import json
import shutil
from pathlib import Path

import pytest

from freamer_rl.errors import ConfigError
from freamer_rl.experiments.suite import dry_run_listing, load_suite, run_suite

ROOT = Path(__file__).resolve().parents[2]
ENV = "MiniGrid-Empty-5x5-v0"
ENTRIES = "entries: [{label: a, recipe: tiny.yaml}, {label: b, recipe: tiny.yaml}]\n"


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _is_png(path: Path) -> bool:
    return path.is_file() and path.stat().st_size > 1000 and path.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize(
    ("evaluate", "field"),
    [
        ("conditions: [{label: clean}, {label: ../x, corrupt: [{key: grid}]}]", r"evaluate.conditions\[1\].label"),
        ("conditions: [{label: g, corrupt: [{key: grid, kind: salt, level: 0.5}]}]", "a clean condition"),
        ("conditions: [{label: clean}, {label: clean, corrupt: [{key: grid}]}]", "'clean' is used twice"),
        ("conditions: [{label: clean}]\n  compare: [[a, c]]", r"evaluate.compare\[0\]: 'c' is not an entry label"),
        ("conditions: [{label: clean}]\n  compare: [[a]]", r"evaluate.compare\[0\]: expected two"),
        ("conditions: [{label: clean}]\n  compare_on: [R, gain]", "evaluate.compare_on: expected entries of R, score"),
        ("conditions: [{label: clean}]\n  compare_on: [R, R]", "evaluate.compare_on: expected distinct entries"),
        ("conditions: [{label: clean}]\n  compare_on: []", "evaluate.compare_on: expected distinct entries"),
        (
            "conditions: [{label: clean}, {label: g, corrupt: [{key: grid, kind: blur, level: 1}]}]",
            r"evaluate.conditions\[1\].corrupt\[0\].kind",
        ),
        (
            "conditions: [{label: clean}, {label: g, corrupt: [{key: grid, kind: dropout, level: 2}]}]",
            r"evaluate.conditions\[1\].corrupt\[0\].level",
        ),
        ("conditions: [{label: clean, corrupt: [{key: grid, knd: salt}]}]", r"evaluate.conditions\[0\].corrupt\[0\]"),
        ("metric: score\n  conditions: [{label: clean}]", "evaluate.metric"),
        ("episodes: 0\n  conditions: [{label: clean}]", "evaluate.episodes"),
        ("episodes: 10", "evaluate.conditions: list the conditions"),
    ],
)
def test_evaluate_validation_names_the_field(tmp_path, evaluate, field):
    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    path = tmp_path / "suite.yaml"
    path.write_text(f"name: demo\n{ENTRIES}evaluate:\n  {evaluate}\n")
    with pytest.raises(ConfigError, match=field):
        load_suite(path)


def test_suite_evaluates_each_run_resumably_and_records_failures(tmp_path):
    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    path = tmp_path / "suite.yaml"
    path.write_text(
        "name: rob\nseeds: [0]\ntotal_frames: 128\noverrides: [ppo.epochs=1]\n"
        "entries: [{label: a, recipe: tiny.yaml}]\n"
        "evaluate:\n  episodes: 2\n  num_envs: 2\n  conditions:\n    - {label: clean}\n"
        "    - {label: state_2, corrupt: [{key: embed.state, kind: gaussian, level: 2.0}]}\n"
        "    - {label: nokey, corrupt: [{key: nope, kind: salt, level: 0.5}]}\n"
    )
    out = tmp_path / "out"
    assert "state_2                  waiting for training" in dry_run_listing(path, out)
    first = run_suite(path, output=out)
    run_dir = out / "runs" / "a" / ENV / "seed0"
    assert sorted(first["evaluated"]) == [f"a/{ENV}/seed0 eval clean", f"a/{ENV}/seed0 eval state_2"]
    assert first["eval_failed"] == [f"a/{ENV}/seed0 eval nokey"]
    noisy = json.loads((run_dir / "eval" / "state_2.json").read_text())
    assert noisy["condition"] == "state_2" and noisy["group"] == "embed.state:gaussian" and noisy["level"] == 2.0
    assert noisy["checkpoint_frames"] == 128 and noisy["embedding_noise"] == {"state": 2.0}
    assert {"return_mean", "success_rate", "gate_state", "fm_displacement_state"} <= set(noisy)
    # the episodes behind the means, in the evaluator's order (a one-seed report's intervals resample them)
    assert len(noisy["episode_returns"]) == len(noisy["episode_successes"]) == noisy["episodes"] == 2
    assert sum(noisy["episode_returns"]) / 2 == pytest.approx(noisy["return_mean"], abs=1e-5)
    assert sum(noisy["episode_successes"]) / 2 == pytest.approx(noisy["success_rate"])
    assert "nope" in json.loads((run_dir / "eval" / "nokey.json").read_text())["error"]
    listing = dry_run_listing(path, out)
    assert "state_2                  done" in listing and "nokey                    failed: " in listing

    # a rerun evaluates only what failed; the results for the same checkpoint stay
    stamps = {p: p.stat().st_mtime_ns for p in (run_dir / "eval").glob("[cs]*.json")}
    again = run_suite(path, output=out)
    assert again["trained"] == [] and again["evaluated"] == [] and again["eval_failed"] == [f"a/{ENV}/seed0 eval nokey"]
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    rows = {r["condition"]: r for r in _rows(out / "robustness.csv")}
    assert float(rows["state_2"]["score"]) == pytest.approx(noisy["return_mean"])
    assert rows["nokey"]["error"] and "nokey" in (out / "robustness.md").read_text()


def _fake_run(out: Path, label: str, seed: int, summary: dict, evals: dict[str, dict]) -> None:
    run_dir = out / "runs" / label / ENV / f"seed{seed}"
    (run_dir / "eval").mkdir(parents=True)
    (run_dir / "done.json").write_text(json.dumps({"total_frames": 256, "frames": 256}))
    (run_dir / "summary.json").write_text(json.dumps({"frames": 256, **summary}))
    for cond, data in evals.items():
        (run_dir / "eval" / f"{cond}.json").write_text(json.dumps({"condition": cond, **data}))


def test_report_numbers_on_synthetic_runs(tmp_path):
    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    path = tmp_path / "suite.yaml"
    path.write_text(
        f"name: syn\nseeds: [0, 1, 2, 3, 4]\ntotal_frames: 256\n{ENTRIES}"
        "evaluate:\n  conditions:\n    - {label: clean}\n"
        "    - {label: grid_salt_0.5, corrupt: [{key: grid, kind: salt, level: 0.5}]}\n"
        "    - {label: mission_drop_0.5, corrupt: [{key: mission_tokens, kind: dropout, level: 0.5}]}\n"
        "  compare: [[a, b]]\n"
    )
    out = tmp_path / "out"
    r_grid = {"a": [0.9, 0.8, 0.7, 0.95, 0.85], "b": [0.1, 0.2, 0.3, 0.15, 0.25]}  # IQMs 0.85, 0.2
    r_mission = {"a": [0.5, 0.6, 0.4, 0.55, 0.45], "b": [0.9, 1.0, 0.8, 0.95, 0.85]}  # IQMs 0.5, 0.9
    success = [1.0, 0.9, 0.8, 0.7, 0.6]  # IQM 0.8
    to95 = {"a": [100, 200, 300, 400, 500], "b": [100, 200, None, 400, 500]}  # a: IQM 300; b: 4 of 5 reached
    for label in ("a", "b"):
        for seed in range(5):
            gates = {"gate_state": 0.5 - 0.1 * seed, "fm_displacement_state": 0.01} if label == "a" else {}
            evals = {
                "clean": {"return_mean": 0.5, **gates},
                "grid_salt_0.5": {"return_mean": 0.5 * r_grid[label][seed], **gates},
                "mission_drop_0.5": {"return_mean": 0.5 * r_mission[label][seed], **gates},
            }
            frames95 = None if to95[label][seed] is None else 32 * to95[label][seed]
            summary = {
                "final_success_rate": success[seed],
                "episodes_to_95": to95[label][seed],
                "frames_to_95": frames95,
            }
            _fake_run(out, label, seed, summary, evals)
    result = run_suite(path, output=out, report_only=True)
    assert result["trained"] == [] and result["evaluated"] == []

    rows = _rows(out / "robustness.csv")
    assert len(rows) == 2 * 5 * 3
    got = {(r["label"], r["seed"], r["condition"]): float(r["R"]) for r in rows}
    assert got["a", "3", "grid_salt_0.5"] == pytest.approx(0.95) and got["b", "1", "mission_drop_0.5"] == 1.0
    assert got["b", "4", "clean"] == 1.0

    md = (out / "robustness.md").read_text()
    assert "| a | grid_salt_0.5 | grid:salt | 0.5 | 5 | 0.425 [" in md and "| 0.850 [" in md
    assert "| b | grid_salt_0.5 | grid:salt | 0.5 | 5 | 0.100 [" in md and "| 0.200 [" in md
    assert "| a | mission_drop_0.5 | 0.500 [" in md  # a's worst condition
    assert "| b | grid_salt_0.5 | 0.200 [" in md  # b's worst condition
    assert "| a | b | grid_salt_0.5 | 1.00 [1.00, 1.00] | a ahead of b |" in md
    assert "| a | b | mission_drop_0.5 | 0.00 [0.00, 0.00] | b ahead of a |" in md

    summary = (out / "summary.md").read_text()
    a_row = next(line for line in summary.splitlines() if line.startswith("| a |"))
    b_row = next(line for line in summary.splitlines() if line.startswith("| b |"))
    assert "| 0.800 [" in a_row and "| 300 [" in a_row and "| 9,600 [" in a_row  # frames to 95%: IQM of 32x
    assert b_row.count("4/5 seeds reached") == 2 and "[100 / 200 / — / 400 / 500]" in b_row

    for group in ("grid_salt", "mission_tokens_dropout"):
        assert _is_png(out / f"robustness_{group}.png")
        assert _is_png(out / f"gates_{group}.png")  # a reports gates


def test_gate_points_separate_the_trained_gate_input_gate_weight_and_displacement():
    from freamer_rl.config.sections import CorruptionConfig
    from freamer_rl.experiments.robustness import EvalCondition, EvaluateConfig, gate_points

    salt = CorruptionConfig(key="grid", kind="salt", level=0.5)
    cfg = EvaluateConfig(conditions=[EvalCondition(label="clean"), EvalCondition(label="g1", corrupt=[salt])])
    extras = {"gate_state": 0.05, "gate_input_state": 0.9, "weight_state": 0.2, "fm_displacement_state": 0.3}
    rows = [
        {"label": "a", "condition": c, "extras": {k: v * (1 + seed) for k, v in extras.items()}}
        for c in ("clean", "g1")
        for seed in (0, 1)
    ]
    points = gate_points(rows, cfg, "grid:salt")
    assert set(points) == {("a", k, "state") for k in ("gate", "gate_input", "weight", "fm_displacement")}
    assert points["a", "weight", "state"] == [(0.0, pytest.approx(0.3)), (0.5, pytest.approx(0.3))]  # seed mean


def test_one_seed_report_resamples_the_evaluation_episodes(tmp_path):
    """With one seed there is nothing to resample across runs: the score and R intervals come from the run's own
    evaluation episodes (marked), and constant episodes give a zero-width interval; two seeds resample seeds."""
    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    path = tmp_path / "suite.yaml"
    path.write_text(
        f"name: one\nseeds: [0]\ntotal_frames: 256\n{ENTRIES}"
        "evaluate:\n  episodes: 8\n  conditions:\n    - {label: clean}\n"
        "    - {label: grid_salt_0.5, corrupt: [{key: grid, kind: salt, level: 0.5}]}\n"
        "  compare: [[a, b]]\n"
    )
    out = tmp_path / "out"
    clean = [2.0, 4.0] * 4  # mean 3
    noisy = [0.0, 3.0] * 4  # mean 1.5: R = 0.5
    flat = [1.0] * 8
    for label, (c, n) in {"a": (clean, noisy), "b": (flat, flat)}.items():
        evals = {
            "clean": {"return_mean": sum(c) / 8, "episode_returns": c},
            "grid_salt_0.5": {"return_mean": sum(n) / 8, "episode_returns": n},
        }
        _fake_run(out, label, 0, {"final_success_rate": 1.0}, evals)
    run_suite(path, output=out, report_only=True)
    md = (out / "robustness.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| a | grid_salt_0.5 | grid:salt"))
    score, ratio = (cell.strip() for cell in row.split("|")[6:8])
    assert score.startswith("1.500 [") and score.endswith("] (e)") and ratio.startswith("0.500 [")
    s_lo, s_hi = (float(v) for v in score[len("1.500 [") : -len("] (e)")].split(", "))
    r_lo, r_hi = (float(v) for v in ratio[len("0.500 [") : -len("] (e)")].split(", "))
    assert 0.0 <= s_lo < 1.5 < s_hi <= 3.0 and 0.0 <= r_lo < 0.5 < r_hi <= 1.0  # the episodes' spread, not [x, x]
    assert "| a | clean | clean | 0 | 1 | 3.000 [" in md and "| 1.000 [1.000, 1.000] (e) |" in md  # clean R is 1
    assert "| b | grid_salt_0.5 | grid:salt | 0.5 | 1 | 1.000 [1.000, 1.000] (e) | 1.000 [1.000, 1.000] (e) |" in md
    assert "(e): one seed, so the interval resamples that run's 8 evaluation episodes" in md
    assert "| R | a | b | grid_salt_0.5 | 0.00 | too few seeds (< 3 per arm) |" in md  # P(A > B) needs seeds

    # a second seed: the intervals resample seeds again, unmarked
    for seed, scale in ((1, 0.8),):
        evals = {
            "clean": {"return_mean": 3.0, "episode_returns": clean},
            "grid_salt_0.5": {"return_mean": 3.0 * scale, "episode_returns": noisy},
        }
        _fake_run(out, "a", seed, {"final_success_rate": 1.0}, evals)
    path.write_text(path.read_text().replace("seeds: [0]", "seeds: [0, 1]"))
    run_suite(path, output=out, report_only=True)
    md = (out / "robustness.md").read_text()
    assert "| a | grid_salt_0.5 | grid:salt | 0.5 | 2 | 1.950 [1.500, 2.400] | 0.650 [0.500, 0.800] |" in md

    # two seeds per arm, every run of b keeping all of its score: P(a > b) = 0, but a bootstrap over two seeds says
    # "0 [0, 0]", so no interval and no verdict; a third seed per arm gives both
    def add_seed(seed: int, scale: float) -> None:
        evals = {"clean": {"return_mean": 3.0, "episode_returns": clean}, "grid_salt_0.5": {"return_mean": 3.0 * scale}}
        _fake_run(out, "a", seed, {"final_success_rate": 1.0}, evals)
        flat_evals = {c: {"return_mean": 1.0, "episode_returns": flat} for c in ("clean", "grid_salt_0.5")}
        _fake_run(out, "b", seed, {"final_success_rate": 1.0}, flat_evals)

    shutil.rmtree(out / "runs" / "a" / ENV / "seed1")
    add_seed(1, 0.8)
    run_suite(path, output=out, report_only=True)
    assert "| R | a | b | grid_salt_0.5 | 0.00 | too few seeds (< 3 per arm) |" in (out / "robustness.md").read_text()
    add_seed(2, 0.6)
    path.write_text(path.read_text().replace("seeds: [0, 1]", "seeds: [0, 1, 2]"))
    run_suite(path, output=out, report_only=True)
    assert "| R | a | b | grid_salt_0.5 | 0.00 [0.00, 0.00] | b ahead of a |" in (out / "robustness.md").read_text()
    # on the score itself (compare_on: score; every condition, the clean one too) a beats b everywhere: b keeps all
    # of a score of 1, a keeps 50-80% of a score of 3
    path.write_text(path.read_text().replace("compare: [[a, b]]", "compare: [[a, b]]\n  compare_on: [R, score]"))
    run_suite(path, output=out, report_only=True)
    md = (out / "robustness.md").read_text()
    assert "| R | a | b | grid_salt_0.5 | 0.00 [0.00, 0.00] | b ahead of a |" in md
    assert "| score | a | b | clean | 1.00 [1.00, 1.00] | a ahead of b |" in md
    assert "| score | a | b | grid_salt_0.5 | 1.00 [1.00, 1.00] | a ahead of b |" in md
