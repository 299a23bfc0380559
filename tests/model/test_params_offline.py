"""``freamer-rl params`` never downloads: it counts a randomly initialised model of the same architecture."""

from __future__ import annotations

from pathlib import Path

import pytest

from freamer_rl import cli
from freamer_rl.trainers.minigrid_ppo import build_modules
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]


def test_params_on_the_clip_recipe_is_offline(monkeypatch, capsys):
    clip = pytest.importorskip("freamer_rl.layers.clip_backbone")
    try:
        clip.import_open_clip()
    except clip.ClipNotInstalledError as err:
        pytest.skip(f"open_clip unavailable: {err}")

    def no_download(*args, **kwargs):
        raise AssertionError("freamer-rl params tried to fetch CLIP weights")

    open_clip = clip.import_open_clip()
    monkeypatch.setattr(open_clip.pretrained, "download_pretrained", no_download)  # open_clip's own fetch
    assert cli.main(["params", str(ROOT / "recipes" / "minigrid_multiroom_n2s4_clip.yaml")]) == 0
    out = capsys.readouterr().out
    assert "Vision backbone" in out and "randomly initialised model of the same architecture" in out
    frozen = next(line for line in out.splitlines() if line.startswith("Vision backbone")).split()
    assert frozen[-1].endswith("M")  # the ~88M frozen tower is counted


def _count(line: str) -> list[int]:
    """The Trainable / Frozen / Total numbers at the end of a table row."""
    return [int(tok.replace(",", "")) for tok in line.split()[-3:]]


def test_params_counts_a_gym_recipe(capsys):
    """The table's rows are the model's parameters: the Total is the built model's count, the rows add up to it."""
    recipe = ROOT / "recipes" / "gym" / "cartpole.yaml"
    assert cli.main(["params", str(recipe)]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {
        line.split("  ")[0]: _count(line)
        for line in lines
        if line and line.split()[-1].replace(",", "").isdigit() and not line.startswith("Component")
    }
    assert "Vector encoder (MLP)" in rows and "DNC memory" in rows
    total = rows.pop("Total")
    assert [sum(r[i] for r in rows.values()) for i in range(3)] == total
    model = build_modules(load_config(recipe)).actor_value
    assert total == [
        sum(q.numel() for q in model.parameters() if q.requires_grad),
        0,
        sum(q.numel() for q in model.parameters()),
    ]
