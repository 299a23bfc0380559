"""Transfer (run.init_from), recipe chains (freamer-rl chain) and the MultiRoom sizes minigrid does not register."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from freamer_rl import cli
from freamer_rl.errors import CheckpointError, ConfigError, EnvSetupError
from freamer_rl.experiments.chain import is_chain, load_chain, plan_chain, run_chain, split_overrides
from freamer_rl.run.envs import make_single_env
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config
from freamer_rl_envs.minigrid import make_minigrid_env

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
CHAINS = sorted((ROOT / "recipes").glob("*.chain.yaml"))
SHRINK = [
    "env.num_envs=2",
    "ppo.frames_per_batch=32",
    "ppo.sequence_length=8",
    "ppo.minibatch_size=16",
    "ppo.epochs=1",
    "run.total_frames=64",
    "logging.progress_bar=false",
    "model.compile=false",
]


def _train_tiny(run_dir: Path, *overrides: str) -> dict:
    return Trainer(load_config(TINY, list(overrides)), run_dir, resume=True).train()


def _weights(trainer: Trainer) -> dict:
    return {k: v.clone() for k, v in trainer.modules.actor_value.state_dict().items()}


def test_init_from_copies_the_weights_only(tmp_path):
    _train_tiny(tmp_path / "a")
    trained = Trainer(load_config(TINY), tmp_path / "a")  # resumes: holds a's final weights
    source = _weights(trained)
    trained._lock.release()
    b = Trainer(
        load_config(TINY, ["env.id=MiniGrid-DoorKey-5x5-v0", f"run.init_from={tmp_path / 'a'}"]), tmp_path / "b"
    )
    for key, value in _weights(b).items():
        assert torch.equal(value, source[key]), key
    assert b.frames == 0 and b.stats.episodes == 0 and not b.optimizer.state  # a fresh run: weights only
    b._lock.release()


def test_init_from_refuses_another_model_or_no_checkpoint(tmp_path):
    _train_tiny(tmp_path / "a")
    with pytest.raises(CheckpointError, match=r"run.init_from: .* another model \(model.embed_dim: checkpoint 32"):
        Trainer(load_config(TINY, ["model.embed_dim=16", f"run.init_from={tmp_path / 'a'}"]), tmp_path / "b")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="holds no checkpoint"):
        Trainer(load_config(TINY, [f"run.init_from={tmp_path / 'empty'}"]), tmp_path / "c")


def test_a_resumed_run_keeps_its_own_weights(tmp_path):
    _train_tiny(tmp_path / "a")
    _train_tiny(tmp_path / "b", "run.seed=5")
    own = Trainer(load_config(TINY, ["run.seed=5"]), tmp_path / "b")
    expected = _weights(own)
    own._lock.release()
    resumed = Trainer(load_config(TINY, ["run.seed=5", f"run.init_from={tmp_path / 'a'}"]), tmp_path / "b")
    assert all(torch.equal(v, expected[k]) for k, v in _weights(resumed).items())
    resumed._lock.release()


def _write_chain(folder: Path, stages: str) -> Path:
    shutil.copy(TINY, folder / "tiny.yaml")
    path = folder / "c.chain.yaml"
    path.write_text(f"name: demo\nseed: 3\noutput_dir: {folder / 'runs'}\nstages:\n{stages}")
    return path


def test_chain_trains_stages_in_order_and_resumes(tmp_path):
    path = _write_chain(
        tmp_path,
        "  - {name: empty, recipe: tiny.yaml}\n"
        "  - {name: rooms, recipe: tiny.yaml, overrides: [env.id=MiniGrid-MultiRoom-N1-S4-v0]}\n",
    )
    rows = run_chain(path)
    root = tmp_path / "runs" / "demo-s3"
    assert [r["stage"] for r in rows] == ["empty", "rooms"] and [r["chain_frames"] for r in rows] == [256, 512]
    config_text = (root / "rooms" / "config.yaml").read_text()  # the second stage starts from the first's weights
    assert f"init_from: {root / 'empty'}" in config_text and "seed: 3" in config_text
    assert json.loads((root / "chain_summary.json").read_text())["stages"] == rows
    stamp = (root / "rooms" / "summary.json").stat().st_mtime
    again = run_chain(path)  # finished stages are read back, not retrained
    assert again == rows and (root / "rooms" / "summary.json").stat().st_mtime == stamp
    assert "| rooms | MiniGrid-MultiRoom-N1-S4-v0 | 256 | 512 |" in (root / "chain_summary.md").read_text()


@pytest.mark.parametrize(
    "stages, message",
    [
        ("  - {name: a, recipe: ../tiny.yaml}\n", "leaves the chain file's folder"),
        ("  - {name: a, recipe: missing.yaml}\n", "no such recipe file"),
        ("  - {name: a, recipe: tiny.yaml}\n  - {name: a, recipe: tiny.yaml}\n", "'a' is used twice"),
        ("  - {name: ../a, recipe: tiny.yaml}\n", r"stages\[0\].name"),
        ("  []\n", "at least one stage"),
        ("  - {name: a}\n", r"stages\[0\].recipe: missing"),
    ],
)
def test_chain_file_errors_name_the_field(tmp_path, stages, message):
    (tmp_path / "sub").mkdir()
    with pytest.raises(ConfigError, match=message):
        load_chain(_write_chain(tmp_path / "sub", stages))


def _write_shared_recipe_chain(folder: Path) -> Path:
    """Two stages with no recipe of their own: the chain's ``recipe`` (tiny FreamerV1) for both."""
    shutil.copy(TINY, folder / "tiny.yaml")
    (folder / "mlp.yaml").write_text(
        "trainer: ppo_baseline\nenv: {adapter: minigrid, id: MiniGrid-Empty-5x5-v0, num_envs: 2}\n"
        "network: {kind: mlp, observation_keys: [grid, direction], hidden: 16}\n"
        "ppo: {frames_per_batch: 64, minibatch_size: 32, epochs: 1}\nrun: {total_frames: 128}\n"
        "logging: {progress_bar: false}\n"
    )
    path = folder / "c.chain.yaml"
    path.write_text(
        f"name: demo\nseed: 3\noutput_dir: {folder / 'runs'}\nrecipe: tiny.yaml\nstages:\n"
        "  - {name: empty}\n  - {name: rooms, overrides: [env.id=MiniGrid-MultiRoom-N1-S4-v0]}\n"
    )
    return path


def test_a_chains_recipe_trains_every_stage_and_one_override_swaps_the_agent(tmp_path):
    """``recipe:`` names every stage's recipe; ``recipe=`` (a chain-file field) puts another agent through the same
    stages, each keeping its env id and transferring its weights; rerunning it into the folder the first agent's
    stages finished in is refused, not read back as if the new agent had trained them."""
    path = _write_shared_recipe_chain(tmp_path)
    rows = run_chain(path)
    root = tmp_path / "runs" / "demo-s3"
    assert [r["env"] for r in rows] == ["MiniGrid-Empty-5x5-v0", "MiniGrid-MultiRoom-N1-S4-v0"]
    assert "model:" in (root / "rooms" / "config.yaml").read_text()
    with pytest.raises(ConfigError, match=r"stages\[0\] \(empty\): .*finished with another config .*network: "):
        run_chain(path, ["recipe=mlp.yaml"])
    rows = run_chain(path, ["recipe=mlp.yaml", f"output_dir={tmp_path / 'mlp_runs'}"])
    stage = tmp_path / "mlp_runs" / "demo-s3" / "rooms"
    assert [r["frames"] for r in rows] == [128, 128] and rows[1]["env"] == "MiniGrid-MultiRoom-N1-S4-v0"
    config_text = (stage / "config.yaml").read_text()
    assert "network:" in config_text and f"init_from: {stage.parent / 'empty'}" in config_text
    assert json.loads((stage / "summary.json").read_text())["trainer"] == "ppo_baseline"


def test_a_chain_names_one_recipe_for_every_stage_or_one_per_stage(tmp_path):
    path = _write_shared_recipe_chain(tmp_path)
    path.write_text(path.read_text().replace("{name: empty}", "{name: empty, recipe: tiny.yaml}"))
    with pytest.raises(ConfigError, match=r"stages\[0\].recipe: 'tiny.yaml' beside the chain's recipe"):
        load_chain(path)
    with pytest.raises(ConfigError, match=r"^recipe: no such recipe file"):
        load_chain(_write_shared_recipe_chain(tmp_path), ["recipe=missing.yaml"])
    with pytest.raises(ConfigError, match=r"^recipe: '../tiny.yaml' leaves the chain file's folder"):
        load_chain(path, ["recipe=../tiny.yaml", "stages=[{name: a}]"])


@pytest.mark.parametrize("chain", CHAINS, ids=[c.name for c in CHAINS])
def test_every_chain_recipe_runs_shrunk(chain, tmp_path):
    """Every stage of the shipped chains, shrunk to two tiny batches (the env ids and transfers are real)."""
    rows = run_chain(chain, [f"output_dir={tmp_path}"], stage_overrides=SHRINK)
    assert len(rows) == len(load_chain(chain).stages) and all(r["frames"] == 64 for r in rows)


def test_chain_cli(tmp_path, capsys):
    path = _write_chain(tmp_path, "  - {name: only, recipe: tiny.yaml}\n")
    assert cli.main(["chain", str(path)]) == 0
    assert (tmp_path / "runs" / "demo-s3" / "chain_summary.json").is_file()
    assert cli.main(["chain", str(path), "seed=x"]) == 2  # a bad override: one error line


def test_chain_level_overrides_apply_after_each_stages_own(tmp_path):
    """``freamer-rl chain FILE run.total_frames=...`` shrinks every stage, even one with its own frame cap."""
    path = _write_chain(
        tmp_path,
        "  - {name: a, recipe: tiny.yaml, overrides: [run.total_frames=512]}\n  - {name: b, recipe: tiny.yaml}\n",
    )
    assert cli.main(["--log-level", "WARNING", "chain", str(path), "run.total_frames=128", "seed=4"]) == 0
    summary = json.loads((tmp_path / "runs" / "demo-s4" / "chain_summary.json").read_text())  # seed=4: the file's
    assert summary["seed"] == 4 and [s["frames"] for s in summary["stages"]] == [128, 128]
    assert "seed: 4" in (tmp_path / "runs" / "demo-s4" / "b" / "config.yaml").read_text()


def test_plan_chain_gives_stages_last_env_and_budget_and_names_a_bad_stage(tmp_path):
    """What a suite plans a chain entry with, before anything trains; chain-level overrides reach every stage."""
    path = _write_chain(
        tmp_path,
        "  - {name: a, recipe: tiny.yaml, overrides: [run.total_frames=512]}\n"
        "  - {name: b, recipe: tiny.yaml, overrides: [env.id=MiniGrid-MultiRoom-N1-S4-v0]}\n",
    )
    plan = plan_chain(path, ["seed=1"])
    assert (plan.stages, plan.env, plan.total_frames) == (["a", "b"], "MiniGrid-MultiRoom-N1-S4-v0", 512 + 256)
    assert plan_chain(path, ["run.total_frames=64"]).total_frames == 128
    with pytest.raises(ConfigError, match=r"stages\[0\] \(a\): .*optim.lr"):
        plan_chain(path, ["optim.lr=fast"])
    assert is_chain(path) and not is_chain(TINY)
    assert not (tmp_path / "runs").exists()  # planning trains nothing


def test_split_overrides_follows_the_chain_keys():
    chain, stages = split_overrides(
        ["seed=1", "output_dir=x", "run.total_frames=2048", "overrides=[a=1]", "ppo.epochs=1"]
    )
    assert chain == ["seed=1", "output_dir=x", "overrides=[a=1]"] and stages == [
        "run.total_frames=2048",
        "ppo.epochs=1",
    ]


def test_an_output_dir_that_cannot_be_created_is_one_line_before_training(tmp_path, capsys):
    (tmp_path / "afile").write_text("in the way")
    path = _write_chain(tmp_path, "  - {name: a, recipe: tiny.yaml}\n")
    assert cli.main(["chain", str(path), f"output_dir={tmp_path / 'afile' / 'runs'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: output_dir: cannot create") and "afile" in err[0]
    assert not (tmp_path / "runs").exists()  # nothing trained anywhere


@pytest.mark.parametrize(
    "env_id, rooms, size", [("MiniGrid-MultiRoom-N3-S4-v0", 3, 4), ("MiniGrid-MultiRoom-N5-S5-v0", 5, 5)]
)
def test_unregistered_multiroom_sizes_are_built(env_id, rooms, size):
    env = make_minigrid_env(env_id)
    check_env_specs(env, seed=0)
    assert (env._unwrapped.minNumRooms, env._unwrapped.maxNumRooms, env._unwrapped.maxRoomSize) == (rooms, rooms, size)
    env.close()


def test_impossible_multiroom_size_is_one_error():
    with pytest.raises(EnvSetupError, match="MultiRoom sizes need"):
        make_single_env(load_config(TINY, ["env.id=MiniGrid-MultiRoom-N9-S4-v0"]))
