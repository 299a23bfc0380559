"""benchmarks/robustness_across.py: two arms of two suites' robustness.csv compared with the suite statistics."""

import csv
import importlib.util
from pathlib import Path

import pytest

from freamer_rl.experiments.stats import iqm_ci, probability_of_improvement

ROOT = Path(__file__).resolve().parents[2]
FIELDS = [
    "label",
    "env",
    "seed",
    "condition",
    "group",
    "level",
    "score",
    "clean_score",
    "R",
    "checkpoint_frames",
    "error",
]


def _module():
    spec = importlib.util.spec_from_file_location("robustness_across", ROOT / "benchmarks" / "robustness_across.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _suite(folder: Path, label: str, values: dict[str, list[float]]) -> None:
    folder.mkdir()
    with (folder / "robustness.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, FIELDS)
        w.writeheader()
        for condition, rs in values.items():
            for seed, r in enumerate(rs):
                w.writerow({"label": label, "env": "E", "seed": seed, "condition": condition, "R": r, "score": r})
        w.writerow({"label": "other", "env": "E", "seed": 0, "condition": "salt", "R": 0.0, "score": 0.0})


def test_compares_two_suites_with_the_suite_statistics(tmp_path):
    a, b = [0.9, 0.8, 0.95, 0.85, 0.9], [0.5, 0.6, 0.7, 0.55, 0.65]
    _suite(tmp_path / "new", "x", {"salt": a})
    _suite(tmp_path / "old", "y", {"salt": b, "drop": b})
    lines = _module().compare(f"{tmp_path / 'new'}:x", f"{tmp_path / 'old'}:y", ["salt"], "R")
    point, low, high = iqm_ci({"E": a})
    p, p_low, p_high = probability_of_improvement({"E": a}, {"E": b})
    assert p == 1.0
    assert lines[2].startswith(f"| salt | {point:.3f} [{low:.3f}, {high:.3f}] (5) |")
    assert lines[2].endswith(f"| {p:.2f} [{p_low:.2f}, {p_high:.2f}] |")


def test_a_condition_one_arm_lacks_is_one_line(tmp_path):
    _suite(tmp_path / "new", "x", {"salt": [0.9]})
    _suite(tmp_path / "old", "y", {"drop": [0.5]})
    with pytest.raises(SystemExit, match="error: condition 'salt' is not evaluated for both arms"):
        _module().compare(f"{tmp_path / 'new'}:x", f"{tmp_path / 'old'}:y", ["salt"], "R")
    with pytest.raises(SystemExit, match="no evaluated runs of arm 'z'"):
        _module().compare(f"{tmp_path / 'new'}:z", f"{tmp_path / 'old'}:y", ["salt"], "R")
