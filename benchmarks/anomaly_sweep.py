"""Anomaly detection on labelled scenarios: each per-step score (KL, prediction error, largest channel residual,
heart-rate lag predictor) with its threshold chosen on one scenario and scored on another.

    python benchmarks/anomaly_sweep.py RUN [RUN ...] --out DIR [--hours 48] [--calibration-seed 1] [--test-seed 0]
        [--stale-steps 2]

Two 48-hour synthetic recordings with injected, labelled anomalies (:func:`freamer_rl.data.anomaly_labels.
write_anomaly_scenario`: 6 each of heart-rate spikes at rest, sensor dropouts, slow drift, arrhythmia) are written
into ``--out``, one per seed. For every run and score (:data:`freamer_rl.health.anomaly_report.SCORES`) the
detector ``score > mean + k std`` (running statistics) is swept over ``--k``; the smallest k with at most
``--max-fa-per-hour`` false alarms per hour on the calibration scenario is then scored on the test scenario, so the
threshold never sees the events it is scored on. ``--stale-steps N`` scores each once more with the frozen-sensor
check (``<score>+stale``). The ``hr_lag`` score reads the recording only, so it is the same for every run. Writes
``anomaly_sweep.json`` (every k on both scenarios) and ``anomaly_sweep.md`` (the calibrated rows: event-level recall,
false alarms per hour, recall per kind, mean delay from an event's start to its first flag, and the threshold-free
step-level AUROC / AUC-PR of the raw score, strict and point-adjusted).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from freamer_rl.data.anomaly_labels import write_anomaly_scenario
from freamer_rl.health.agent import load_agent
from freamer_rl.health.anomaly_report import SCORES, filter_labelled, score_filtered

DEFAULT_K = (2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 16.0)


def sweep(
    run: Path, scenarios: dict[str, tuple[Path, Path]], ks: list[float], out: Path, stale_steps: int = 0
) -> list[dict]:
    """Every score x k x scenario of one run (each scenario filtered once): the report's summary, without the
    picture; with ``stale_steps`` each score also once more with the frozen-sensor check (score ``<score>+stale``)."""
    agent = load_agent(run)
    filtered = {name: filter_labelled(agent, dat, labels) for name, (dat, labels) in scenarios.items()}
    keep = ("recall", "precision", "fa_per_hour", "auroc", "auc_pr", "auroc_point_adjusted", "delay_s")
    rows = []
    for score in SCORES:
        for stale in sorted({0, stale_steps}):
            label = score if stale == 0 else f"{score}+stale"
            for k in ks:
                for name, f in filtered.items():
                    summary = score_filtered(f, out / "reports", k_sigma=k, score=score, stale_steps=stale, plot=False)
                    rows.append(
                        {"run": str(run), "score": label, "k": k, "scenario": name, **{m: summary[m] for m in keep}}
                        | {"recall_by_kind": summary["recall_by_kind"], "encoder": summary["encoder"]}
                    )
    return rows


def calibrated(rows: list[dict], max_fa: float) -> list[dict]:
    """Per run and score: the smallest k with ``fa_per_hour <= max_fa`` on the calibration scenario, its test row."""
    out = []
    for key in sorted({(r["run"], r["score"]) for r in rows}):
        cal = [r for r in rows if (r["run"], r["score"]) == key and r["scenario"] == "calibration"]
        ok = sorted(r["k"] for r in cal if r["fa_per_hour"] is not None and r["fa_per_hour"] <= max_fa)
        k = ok[0] if ok else max(r["k"] for r in cal)
        test = next(r for r in rows if (r["run"], r["score"], r["k"]) == (*key, k) and r["scenario"] == "test")
        out.append({**test, "calibrated": bool(ok)})
    return out


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}"


def markdown(best: list[dict], max_fa: float) -> str:
    lines = [
        f"Threshold: the smallest k with <= {max_fa:g} false alarm(s) per hour on the calibration scenario "
        "(* none reached it: the largest k). Scored on the test scenario.",
        "",
        "| run | encoder | score | k | recall | false alarms / h | recall by kind | delay (s) | AUROC | AUC-PR "
        "| AUROC (point-adj.) |",
        "|---|---|---|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in best:
        kinds = ", ".join(f"{k} {_fmt(v)}" for k, v in r["recall_by_kind"].items())
        lines.append(
            f"| {Path(r['run']).name} | {r['encoder']} | {r['score']} | {r['k']:g}{'' if r['calibrated'] else '*'} | "
            f"{_fmt(r['recall'])} | {_fmt(r['fa_per_hour'])} | {kinds} | {_fmt(r.get('delay_s'))} | "
            f"{_fmt(r['auroc'])} | {_fmt(r['auc_pr'])} | "
            f"{_fmt(r['auroc_point_adjusted'])} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="trained health run directories")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--hours", type=float, default=48.0)
    parser.add_argument("--calibration-seed", type=int, default=1)
    parser.add_argument("--test-seed", type=int, default=0)
    parser.add_argument("--k", type=float, nargs="+", default=list(DEFAULT_K))
    parser.add_argument("--max-fa-per-hour", type=float, default=1.0)
    parser.add_argument(
        "--stale-steps", type=int, default=0, help="also score each with the frozen-sensor check of N steps (0: off)"
    )
    args = parser.parse_args(argv)
    scenarios = {
        name: write_anomaly_scenario(args.out / f"scenario_seed{seed}", hours=args.hours, seed=seed)
        for name, seed in (("calibration", args.calibration_seed), ("test", args.test_seed))
    }
    rows = [row for run in args.runs for row in sweep(run, scenarios, args.k, args.out, args.stale_steps)]
    best = calibrated(rows, args.max_fa_per_hour)
    (args.out / "anomaly_sweep.json").write_text(json.dumps({"rows": rows, "calibrated": best}, indent=2))
    text = markdown(best, args.max_fa_per_hour)
    (args.out / "anomaly_sweep.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
