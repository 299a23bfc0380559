"""A short smoke run of every recipe (shrunk by overrides to a couple of tiny batches)."""

from __future__ import annotations

from pathlib import Path

import pytest

from freamer_rl.run import env_registry
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
RECIPES = [
    r
    for r in sorted((ROOT / "recipes").glob("*.yaml")) + sorted((ROOT / "recipes" / "gym").glob("*.yaml"))
    if not r.name.endswith(".chain.yaml")
]  # chains: tests/test_chain.py

SHRINK = [
    "env.num_envs=2",
    "ppo.frames_per_batch=32",
    "ppo.sequence_length=8",
    "ppo.minibatch_size=16",
    "ppo.epochs=1",
    "run.total_frames=64",
    "logging.progress_bar=false",
    "logging.checkpoint_every_frames=1000000",
]


@pytest.mark.parametrize("recipe", RECIPES, ids=[r.stem for r in RECIPES])
def test_recipe_smoke(recipe, tmp_path):
    cfg = load_config(recipe)
    extra = []
    if "vision" in cfg.model.modalities and cfg.model.vision.backbone == "clip":
        from freamer_rl.layers.clip_backbone import ClipNotInstalledError, import_open_clip

        try:
            import_open_clip()
        except ClipNotInstalledError as err:
            pytest.skip(f"CLIP backbone unavailable here: {err}")
        # No CLIP weights can be downloaded here: exercise the recipe with explicitly random weights.
        extra = ["model.vision.clip_pretrained=null", "model.vision.allow_random_weights=true"]
    cfg = load_config(recipe, SHRINK + extra)
    summary = Trainer(cfg, tmp_path / recipe.stem).train()
    assert summary["frames"] == 64
    assert (tmp_path / recipe.stem / "learning_curve.png").is_file()
    if env_registry.get_adapter(cfg.env.adapter).achievements:  # Crafter: the official score and its report
        score = summary["crafter_score"]  # none (JSON null) until an episode ends (a 64-frame run rarely sees one)
        assert 0 <= score <= 100 if summary["episodes"] else score is None
        for name in ("crafter_score.json", "crafter_achievements.md", "crafter_achievements.png"):
            assert (tmp_path / recipe.stem / name).is_file()
