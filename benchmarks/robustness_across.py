"""Compare two arms of two robustness suites run on the same task (README "Robustness"), from their robustness.csv.

A suite compares the arms it trained (``evaluate.compare``); an arm added later in its own suite (same env, frames and
evaluation) is compared with an older one here, with the same statistics: IQM over seeds with a 95%
stratified-bootstrap interval, and P(A > B) with its interval (``freamer_rl.experiments.stats``).

    python benchmarks/robustness_across.py \\
        benchmarks/robustness/robustness_presence:fm_reliable_present \\
        benchmarks/robustness/robustness_redundant:fm_reliable_drop --on R grid_salt_0.5 grid_drop_0.5
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

from freamer_rl.experiments.stats import iqm_ci, probability_of_improvement


def read_arm(spec: str, on: str) -> dict[str, dict[str, list[float]]]:
    """``SUITE_DIR:LABEL`` -> ``{condition: {env: [value per seed]}}`` of column ``on`` (R or score)."""
    folder, _, label = spec.rpartition(":")
    path = Path(folder) / "robustness.csv"
    if not folder or not label:
        raise SystemExit(f"error: {spec!r}: expected SUITE_DIR:LABEL")
    if not path.is_file():
        raise SystemExit(f"error: {path}: no robustness.csv (run the suite's --report-only first)")
    out: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    with path.open() as f:
        for row in csv.DictReader(f):
            if row["label"] == label and not row.get("error") and row[on] not in ("", "nan"):
                out[row["condition"]][row["env"]].append(float(row[on]))
    if not out:
        raise SystemExit(f"error: {path}: no evaluated runs of arm {label!r}")
    return out


def compare(a: str, b: str, conditions: list[str], on: str) -> list[str]:
    """Markdown lines: per condition, each arm's IQM [95% CI] (seed count) and P(A > B) [95% CI]."""
    arm_a, arm_b = read_arm(a, on), read_arm(b, on)
    lines = [
        f"| condition | {a} | {b} | P(A > B) [95% CI] |",
        "|---|---:|---:|---:|",
    ]
    for c in conditions:
        if c not in arm_a or c not in arm_b:
            raise SystemExit(f"error: condition {c!r} is not evaluated for both arms")
        cells = []
        for arm in (arm_a, arm_b):
            point, low, high = iqm_ci(arm[c])
            cells.append(f"{point:.3f} [{low:.3f}, {high:.3f}] ({sum(len(v) for v in arm[c].values())})")
        p, low, high = probability_of_improvement(arm_a[c], arm_b[c])
        lines.append(f"| {c} | {cells[0]} | {cells[1]} | {p:.2f} [{low:.2f}, {high:.2f}] |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", help="SUITE_DIR:LABEL of arm A")
    parser.add_argument("b", help="SUITE_DIR:LABEL of arm B")
    parser.add_argument("conditions", nargs="+", help="condition labels evaluated for both arms")
    parser.add_argument("--on", choices=("R", "score"), default="R", help="compare R (default) or the score")
    args = parser.parse_args(argv)
    print("\n".join(compare(args.a, args.b, args.conditions, args.on)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
