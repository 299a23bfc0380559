"""Every config value is validated: one ConfigError line naming the dotted field, the value and the allowed range."""

import dataclasses
import re
import typing
from pathlib import Path

import pytest
import torch
import yaml

from freamer_rl.config.checks import config_numbers, resolve_device
from freamer_rl.errors import ConfigError
from freamer_rl.trainers.minigrid_ppo import FreamerConfig
from freamer_rl.trainers.registry import TRAINERS, load_config

_RECIPE_DIR = Path(__file__).resolve().parents[2] / "recipes"
RECIPES = [
    r
    for r in sorted(_RECIPE_DIR.glob("*.yaml")) + sorted((_RECIPE_DIR / "gym").glob("*.yaml"))
    if not r.name.endswith(".chain.yaml")
]  # chain files: tests/test_chain.py

# (overrides, the dotted field the error must name)
BAD = [
    (["optim.lr=-1"], "optim.lr"),
    (["optim.lr=nan"], "optim.lr"),
    (["optim.lr=.inf"], "optim.lr"),
    (["optim.lr=0"], "optim.lr"),
    (["ppo.gamma=5"], "ppo.gamma"),
    (["ppo.gamma=0"], "ppo.gamma"),
    (["ppo.gae_lambda=1.5"], "ppo.gae_lambda"),
    (["ppo.gae_lambda=-0.1"], "ppo.gae_lambda"),
    (["ppo.clip_epsilon=0"], "ppo.clip_epsilon"),
    (["ppo.clip_epsilon=-0.2"], "ppo.clip_epsilon"),
    (["ppo.entropy_coeff=-0.01"], "ppo.entropy_coeff"),
    (["ppo.entropy_coeff=.nan"], "ppo.entropy_coeff"),
    (["ppo.critic_coeff=-1"], "ppo.critic_coeff"),
    (["ppo.critic_coeff=.inf"], "ppo.critic_coeff"),
    (["optim.max_grad_norm=0"], "optim.max_grad_norm"),
    (["optim.eps=0"], "optim.eps"),
    (["aux.lambda_fm=-1"], "aux.lambda_fm"),
    (["aux.lambda_smooth=.nan"], "aux.lambda_smooth"),
    (["ppo.epochs=0"], "ppo.epochs"),
    (["ppo.frames_per_batch=0"], "ppo.frames_per_batch"),
    (["ppo.frames_per_batch=2048", "ppo.minibatch_size=768"], "ppo.minibatch_size"),
    (["optim.lr_schedule=cosine"], "optim.lr_schedule"),
    (["logging.checkpoint_every_frames=0"], "logging.checkpoint_every_frames"),
    (["logging.checkpoint_every_frames=-100"], "logging.checkpoint_every_frames"),
    (["logging.log_every_batches=0"], "logging.log_every_batches"),
    (["logging.success_window=0"], "logging.success_window"),
    (["run.threads=0"], "run.threads"),
    (["run.seed=-1"], "run.seed"),
    (["run.seed=4294967296"], "run.seed"),
    (["run.total_frames=0"], "run.total_frames"),
    (["run.stop_at_success=2"], "run.stop_at_success"),
    (["run.stop_at_success=0"], "run.stop_at_success"),
    (["run.device=banana"], "run.device"),
    (["run.device=gpu"], "run.device"),
    (["run.device=cuda:x"], "run.device"),
    (["model.embed_dim=33"], "model.language.heads"),
    (["model.embed_dim=0"], "model.embed_dim"),
    (["model.modalities=[vision, language]", "model.cross_modal_heads=5"], "model.cross_modal_heads"),
    (["model.head_hidden=0"], "model.head_hidden"),
    (["model.flow.steps=0"], "model.flow.steps"),
    (["model.flow.hidden=0"], "model.flow.hidden"),
    (["model.flow.noise_std=-1"], "model.flow.noise_std"),
    (["model.flow.gate_init={state: .nan}"], "model.flow.gate_init.state"),
    (["model.fno.modes=1000"], "model.fno.modes"),
    (["model.fno.modes=0"], "model.fno.modes"),
    (["model.fno.residual_scale=.nan"], "model.fno.residual_scale"),
    (["model.state.modes=26"], "model.state.modes"),
    (["model.state.channels=0"], "model.state.channels"),
    (["model.dnc.memory_slots=0"], "model.dnc.memory_slots"),
    (["model.dnc.memory_width=0"], "model.dnc.memory_width"),
    (["model.language.heads=0"], "model.language.heads"),
    (["model.language.layers=0"], "model.language.layers"),
    (["model.language.num_slots=0"], "model.language.num_slots"),
    (["model.language.slot_iters=0"], "model.language.slot_iters"),
    (["model.vision.num_slots=0"], "model.vision.num_slots"),
    (["model.vision.slot_iters=0"], "model.vision.slot_iters"),
    (["model.reward.kernel=0"], "model.reward.kernel"),
    (["model.reward.channels=0"], "model.reward.channels"),
    (["model.vector.hidden=0"], "model.vector.hidden"),
    (["env.num_envs=0"], "env.num_envs"),
    (["env.reward_history=-1"], "env.reward_history"),
    (["env.reset_workers=-1"], "env.reset_workers"),
    (["env.reward_history=0"], "env.reward_history"),  # the default modalities include reward
    (["env.max_mission_tokens=0"], "env.max_mission_tokens"),
    (["collector.num_collectors=0"], "collector.num_collectors"),
    (["shaping.language.parser=gpt"], "shaping.language.parser"),
    (["shaping.language.weight=0.2", "shaping.language.parser=llm"], "shaping.language.llm_path"),
    (["shaping.language.weight=-1"], "shaping.language.weight"),
    (["shaping.time_penalty=-0.1"], "shaping.time_penalty"),
    (["shaping.novelty.weight=0.1", "shaping.novelty.keys=[]"], "shaping.novelty.keys"),
    (["model.modalities=[state]", "env.reward_history=0", "shaping.vision_language=0.1"], "shaping.vision_language"),
    (["success_buffer.mix=1"], "success_buffer.mix"),
    (["success_buffer.capacity=0"], "success_buffer.capacity"),
    (["success_buffer.rho_clip=0"], "success_buffer.rho_clip"),
    (["ogm.mode=C"], "ogm.mode"),
    (["ogm.ema=1"], "ogm.ema"),
    (["model.flow.adaptive_steps=[1, 1, 2]"], "model.flow.adaptive_steps"),
    (["model.flow.adaptive_steps=[4]"], "model.flow.adaptive_steps"),
    (["model.flow.adaptive_steps=[0, 2]"], "model.flow.adaptive_steps"),
]


@pytest.mark.parametrize("overrides, field", BAD, ids=[" ".join(o) for o, _ in BAD])
def test_bad_value_is_one_line_naming_the_field(overrides, field):
    with pytest.raises(ConfigError) as info:
        load_config(None, overrides)
    msg = str(info.value)
    assert field in msg
    assert "\n" not in msg
    value = overrides[-1].split("=", 1)[1]
    if field == overrides[-1].split("=", 1)[0] and value not in ("nan", ".nan", ".inf"):
        assert value.strip("{}").split(": ")[-1] in msg  # the value given


@pytest.mark.parametrize(
    "overrides",
    [
        ["model.cross_modal_heads=5"],  # no vision + language: no cross-modal attention
        ["model.state.modes=25", "model.fno.modes=65"],  # the largest that fit
        ["model.modalities=[state]", "env.reward_history=0"],
        ["run.seed=4294967295", "run.stop_at_success=1", "ppo.gamma=1", "ppo.gae_lambda=0", "ppo.entropy_coeff=0"],
        ["run.device=cpu"],
        ["run.device=cuda:1"],  # CUDA visibility is checked when a run starts (a GPU config loads for evaluation)
    ],
)
def test_edge_values_are_accepted(overrides):
    """The edge values load and the config holds them (nothing clamped or replaced by a default)."""
    cfg = load_config(None, overrides)
    for item in overrides:
        dotted, text = item.split("=", 1)
        node, last = _leaf(cfg, dotted)
        held = node[last] if isinstance(node, dict) else getattr(node, last)
        expected = yaml.safe_load(text)
        assert (list(held) if isinstance(held, tuple) else held) == expected, dotted


def _leaf(cfg, dotted):
    *parents, last = dotted.split(".")
    node = cfg
    for part in parents:
        node = node[part] if isinstance(node, dict) else getattr(node, part)
    return node, last


def _fields_to_try():
    out = []
    for name, value in config_numbers(FreamerConfig()):
        out.append((name, float("nan") if isinstance(value, float) else -1))
    return out


@pytest.mark.parametrize("name, bad", _fields_to_try(), ids=[n for n, _ in _fields_to_try()])
def test_every_number_field_is_checked(name, bad):
    """Generic: every int field refuses -1 and every float field refuses NaN, naming the field."""
    from freamer_rl.trainers.minigrid_ppo import validate

    cfg = FreamerConfig()
    node, last = _leaf(cfg, name)
    if isinstance(node, dict):
        node[last] = bad
    else:
        setattr(node, last, bad)
    with pytest.raises(ConfigError, match=name.replace(".", r"\.")):
        validate(cfg)


@pytest.mark.parametrize("trainer", sorted(TRAINERS))
def test_range_table_names_real_fields(trainer):
    """Every schema's one range table names number fields the schema has (a typo would check nothing)."""
    schema = TRAINERS[trainer].schema

    def fields(cls, prefix=""):
        for f in dataclasses.fields(cls):
            sub = typing.get_type_hints(cls)[f.name]
            yield from fields(sub, f"{prefix}{f.name}.") if dataclasses.is_dataclass(sub) else [prefix + f.name]

    names = set(fields(schema))
    assert set(schema.RANGES) <= names, set(schema.RANGES) - names


@pytest.mark.parametrize("trainer", sorted(TRAINERS))
def test_renamed_keys_are_refused_with_the_new_key(trainer, tmp_path):
    """An old key (``ppo.lr`` of earlier releases) is one ConfigError naming its replacement."""
    schema = TRAINERS[trainer].schema
    for old, new in getattr(schema, "RENAMED", {}).items():
        section, key = old.rsplit(".", 1)
        recipe = tmp_path / "old.yaml"
        recipe.write_text(f"trainer: {trainer}\n{section}:\n  {key}: 1\n")
        with pytest.raises(ConfigError, match=f"{re.escape(old)}: this key was renamed; use {re.escape(new)}"):
            load_config(recipe)


@pytest.mark.parametrize("recipe", RECIPES, ids=[r.name for r in RECIPES])
def test_every_recipe_still_validates(recipe):
    assert load_config(recipe).model.modalities


def test_duplicate_yaml_key_names_file_line_and_key(tmp_path):
    dup = tmp_path / "dup.yaml"
    dup.write_text("ppo:\n  lr: 1.0e-4\n  gamma: 0.9\n  lr: 3.0e-4\n")
    with pytest.raises(ConfigError) as info:
        load_config(dup)
    msg = str(info.value)
    assert "dup.yaml:4" in msg and "duplicate key 'lr'" in msg and "line 2" in msg and "\n" not in msg
    top = tmp_path / "top.yaml"
    top.write_text("run:\n  seed: 1\nppo:\n  lr: 1.0e-4\nrun:\n  seed: 2\n")
    with pytest.raises(ConfigError, match=r"top\.yaml:5: duplicate key 'run'"):
        load_config(top)


def test_yaml_merge_keys_are_not_duplicates(tmp_path):
    from freamer_rl.config.checks import check_recipe_file

    merged = tmp_path / "merged.yaml"
    merged.write_text("model:\n  language:\n    <<: {heads: 2, layers: 1}\n    heads: 4\n")
    check_recipe_file(merged)
    assert load_config(merged).model.language.heads == 4


@pytest.mark.parametrize("text", ["", "\n", "# only a comment\n"])
def test_empty_recipe_is_one_line(tmp_path, text):
    empty = tmp_path / "empty.yaml"
    empty.write_text(text)
    with pytest.raises(ConfigError, match=r"empty\.yaml: the recipe file is empty"):
        load_config(empty)


def test_invalid_yaml_still_reports_its_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo:\n  lr: [1, 2\n")
    with pytest.raises(ConfigError, match="bad.yaml:"):
        load_config(bad)


def test_cuda_without_a_visible_gpu_is_one_line(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError) as info:
        resolve_device("cuda")
    assert "run.device" in str(info.value) and "no CUDA device is visible" in str(info.value)
    assert resolve_device("cpu") == torch.device("cpu")


def test_trainer_refuses_cuda_before_touching_the_run_dir(tmp_path, monkeypatch):
    from freamer_rl.trainers.minigrid_ppo import Trainer

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = load_config(_RECIPE_DIR / "tiny.yaml", ["run.device=cuda"])
    with pytest.raises(ConfigError, match="no CUDA device is visible"):
        Trainer(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("device, fragment", [("banana", "expected cpu, cuda or cuda:N"), ("cuda", "run.device")])
def test_cli_bad_device_is_one_error_line(tmp_path, capsys, monkeypatch, device, fragment):
    from freamer_rl.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code = main(["train", str(_RECIPE_DIR / "tiny.yaml"), f"run.device={device}", "--run-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("error: run.device") and fragment in err[0]


HEALTH_BAD = [
    ("world_model.lr=.nan", "world_model.lr"),
    ("world_model.lr=0", "world_model.lr"),
    ("imagination.gamma=5", "imagination.gamma"),
    ("imagination.lmbda=-0.1", "imagination.lmbda"),
    ("encoder.heads=3", "encoder.dim"),
    ("encoder.fm_steps=0", "encoder.fm_steps"),
    ("encoder.memory_slots=0", "encoder.memory_slots"),
    ("collect.iterations=-1", "collect.iterations"),
    ("collect.random_action_prob=1.5", "collect.random_action_prob"),
    ("env.rate_hz=0", "env.rate_hz"),
    ("world_model.kl_balance=2", "world_model.kl_balance"),
    ("eval.seed=-1", "eval.seed"),
    ("encoder.gate_init.imu=.inf", "encoder.gate_init.imu"),
]


@pytest.mark.parametrize("override, field", HEALTH_BAD, ids=[o for o, _ in HEALTH_BAD])
def test_health_values_are_range_checked(override, field):
    recipe = Path(__file__).resolve().parents[2] / "recipes" / "health" / "health_foundation.yaml"
    with pytest.raises(ConfigError, match=re.escape(field)) as err:
        load_config(recipe, [override])
    assert "\n" not in str(err.value)
