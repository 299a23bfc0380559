"""The published health numbers use synthetic subjects; the same command runs on real PAMAP2 files
(``env.data_dir=...``): here on files in PAMAP2's own layout and text format that the test writes itself."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from freamer_rl import cli
from freamer_rl.data import write_synthetic_pamap2

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_health_pipeline import TINY  # noqa: E402


def test_the_shipped_recipe_trains_on_a_pamap2_folder(tmp_path, capsys):
    data = tmp_path / "PAMAP2_Dataset"
    write_synthetic_pamap2(data, subjects=(101, 105), duration_s=300.0, seed=3)  # Protocol/subject101.dat, ...
    assert sorted(p.name for p in (data / "Protocol").glob("*.dat")) == ["subject101.dat", "subject105.dat"]
    recipe = ROOT / "recipes" / "health" / "health_mlp.yaml"
    run = tmp_path / "run"
    code = cli.main(
        ["train", str(recipe), *TINY, "collect.iterations=1", f"env.data_dir={data}", "--run-dir", str(run)]
    )
    assert code == 0
    config = (run / "config.yaml").read_text()
    assert str(data) in config  # the run read the folder, not the embedded synthetic subjects
    summary = json.loads((run / "summary.json").read_text())
    assert summary["frames"] > 0 and summary["eval_return_mean"] is not None
    capsys.readouterr()


def test_a_folder_without_subject_files_is_one_line(tmp_path, capsys):
    (tmp_path / "empty" / "Protocol").mkdir(parents=True)
    recipe = ROOT / "recipes" / "health" / "health_mlp.yaml"
    code = cli.main(
        ["train", str(recipe), *TINY, f"env.data_dir={tmp_path / 'empty'}", "--run-dir", str(tmp_path / "r")]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("error: "), err
    assert "subject" in err[0], err[0]
