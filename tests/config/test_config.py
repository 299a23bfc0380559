from pathlib import Path

import pytest

from freamer_rl.config.loader import config_to_dict
from freamer_rl.errors import ConfigError
from freamer_rl.model.modalities import MODALITIES
from freamer_rl.trainers.minigrid_ppo import FreamerConfig
from freamer_rl.trainers.registry import load_config

_RECIPE_DIR = Path(__file__).resolve().parents[2] / "recipes"
RECIPES = [
    r
    for r in sorted(_RECIPE_DIR.glob("*.yaml")) + sorted((_RECIPE_DIR / "gym").glob("*.yaml"))
    if not r.name.endswith(".chain.yaml")
]  # chain files: tests/test_chain.py


def test_defaults_load():
    cfg = load_config()
    assert isinstance(cfg, FreamerConfig)
    assert cfg.optim.lr == pytest.approx(1e-4)
    # no per-recipe gate logits by default: each modality's own default (vision -5) applies
    assert cfg.model.flow.gate_init == {} and MODALITIES["vision"].gate_init == -5.0


@pytest.mark.parametrize("recipe", RECIPES, ids=[r.name for r in RECIPES])
def test_every_recipe_validates(recipe):
    cfg = load_config(recipe)
    assert cfg.model.modalities


def test_overrides_are_typed(tmp_path):
    cfg = load_config(
        None, ["optim.lr=3e-4", "run.seed=7", "model.modalities=[state, reward]", "model.dnc.enabled=false"]
    )
    assert cfg.optim.lr == pytest.approx(3e-4)
    assert cfg.run.seed == 7
    assert cfg.model.modalities == ["state", "reward"]
    assert cfg.model.dnc.enabled is False


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("ppo.lrr=1", "unknown key 'ppo.lrr'"),
        ("optim.lr=fast", "optim.lr: expected float"),
        ("run.seed=1.5", "run.seed: expected int"),
        ("model.dnc.enabled=yes please", "model.dnc.enabled: expected bool"),
        ("model.modalities=[state, smell]", "unknown modality 'smell'"),
        ("model.vision.backbone=resnet", "model.vision.backbone"),
        ("ppo.sequence_length=7", "ppo.sequence_length"),
        ("env=3", "env: expected a mapping"),
        ("novalue", "dotted.key=value"),
        ("model.freeze_encoders=[vision]", "model.freeze_encoders: 'vision' is not one of model.modalities"),
    ],
)
def test_bad_overrides_name_the_field(override, fragment):
    with pytest.raises(ConfigError, match=None) as info:
        load_config(None, [override])
    assert fragment in str(info.value)


def test_bad_recipe_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo:\n  lr: [1, 2\n")
    with pytest.raises(ConfigError, match="bad.yaml:"):
        load_config(bad)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("model:\n  slots: 3\n")
    with pytest.raises(ConfigError, match="unknown key 'model.slots'"):
        load_config(unknown)


def test_roundtrip_dict():
    cfg = load_config(None, ["env.id=MiniGrid-Empty-5x5-v0"])
    from freamer_rl.config.loader import config_from_dict

    assert config_from_dict(config_to_dict(cfg), type(cfg)) == cfg


def _old_layout(cfg_dict: dict, trainer: str) -> dict:
    """A config mapping as an earlier release (dda99dc) saved it in checkpoints: the optimiser and auxiliary-loss
    settings under ``ppo``, IMPALA's under ``ppo``, and the baselines carrying FreamerV1's sections."""
    from freamer_rl.trainers.minigrid_ppo import FreamerConfig

    old = {k: dict(v) if isinstance(v, dict) else v for k, v in cfg_dict.items()}
    optim = old.pop("optim")
    ppo = old.setdefault("ppo", {})
    ppo.update(
        lr=optim["lr"], adam_eps=optim["eps"], max_grad_norm=optim["max_grad_norm"], lr_schedule=optim["lr_schedule"]
    )
    if "aux" in old:
        ppo.update(old.pop("aux"))
    if trainer == "impala":
        for k in ("frames_per_batch", "gamma", "entropy_coeff", "critic_coeff"):
            ppo[k] = old["impala"].pop(k)
    if trainer != "minigrid_ppo":  # the baselines' schemas inherited FreamerV1's sections
        freamer = config_to_dict(FreamerConfig())
        old.update({s: freamer[s] for s in ("model", "shaping", "success_buffer", "ogm")})
    return old


@pytest.mark.parametrize("trainer", ["minigrid_ppo", "ppo_baseline", "impala"])
def test_a_checkpoint_config_of_the_earlier_layout_still_reads(trainer):
    """Checkpoints written before the optim / aux sections (and the baselines' own schemas) still evaluate: the
    saved config is migrated, while a recipe with the old keys is refused (test_config_validation)."""
    from freamer_rl.config.loader import config_from_dict
    from freamer_rl.trainers.registry import TRAINERS

    schema = TRAINERS[trainer].schema
    cfg = schema()
    cfg.optim.lr = 7e-4
    old = _old_layout(config_to_dict(cfg), trainer)
    with pytest.raises(ConfigError, match="this key was renamed"):
        config_from_dict(old, schema)
    migrated = config_from_dict(old, schema, migrate=True)
    assert migrated == cfg and migrated.optim.lr == 7e-4
