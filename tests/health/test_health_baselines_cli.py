"""``freamer-rl health baselines RECIPE``: the ceiling table from the command line."""

from __future__ import annotations

import json
from pathlib import Path

from freamer_rl import cli

RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "health" / "health_mlp.yaml"
SMALL = ["env.episode_length=40", "eval.num_envs=3", "eval.horizon_context=4", "eval.horizon_max=8"]


def test_baselines_prints_the_table_and_writes_its_rows(tmp_path, capsys):
    out = tmp_path / "ceiling.json"
    code = cli.main(["health", "baselines", str(RECIPE), *SMALL, "--depth", "1", "--horizon", "4", "--json", str(out)])
    assert code == 0
    table = capsys.readouterr().out
    rows = json.loads(out.read_text())
    names = [r["policy"] for r in rows]
    assert names[0] == "oracle" and {"hr_controller", "hr_threshold", "continue"} <= set(names)
    for r in rows:  # every row printed, with the value written beside it
        assert f"| {r['policy']} | {r['return_mean']:.1f}" in table and r["episodes"] == 3
    assert rows[0]["fraction_of_oracle"] == 1.0


def test_baselines_refuses_a_depth_below_one(capsys):
    assert cli.main(["health", "baselines", str(RECIPE), "--depth", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: --depth: expected an integer >= 1, got 0"]
