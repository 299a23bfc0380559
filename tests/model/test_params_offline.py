"""``freamer-rl params`` never downloads: it counts a randomly initialised model of the same architecture."""

from __future__ import annotations

from pathlib import Path

import pytest

from freamer_rl import cli

ROOT = Path(__file__).resolve().parents[2]


def test_params_on_the_clip_recipe_is_offline(monkeypatch, capsys):
    clip = pytest.importorskip("freamer_rl.layers.clip_backbone")
    try:
        clip.import_open_clip()
    except clip.ClipNotInstalledError as err:
        pytest.skip(f"open_clip unavailable: {err}")

    def no_download(*args, **kwargs):
        raise AssertionError("freamer-rl params tried to fetch CLIP weights")

    monkeypatch.setattr(clip.ClipBackbone, "_download", no_download)
    assert cli.main(["params", str(ROOT / "recipes" / "minigrid_multiroom_n2s4_clip.yaml")]) == 0
    out = capsys.readouterr().out
    assert "Vision backbone" in out and "randomly initialised model of the same architecture" in out
    frozen = next(line for line in out.splitlines() if line.startswith("Vision backbone")).split()
    assert frozen[-1].endswith("M")  # the ~88M frozen tower is counted


def test_params_counts_a_gym_recipe(capsys):
    assert cli.main(["params", str(ROOT / "recipes" / "gym" / "cartpole.yaml")]) == 0
    out = capsys.readouterr().out
    assert "Vector encoder (MLP)" in out and "DNC memory" in out
