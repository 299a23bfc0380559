"""Modality corruption transforms (freamer_rl.run.corruption): each kind on a real env, against closed forms where
there is one, configured from recipes for training and evaluation, for FreamerV1 and the PPO baseline."""

import functools
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, InitTracker, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from freamer_rl.config.sections import CorruptionConfig
from freamer_rl.errors import ConfigError
from freamer_rl.run.corruption import ModalityCorruption, SensorCopy, corruption_transforms
from freamer_rl.run.envs import make_batched_env, probe_specs
from freamer_rl.trainers.minigrid_ppo import build_modules
from freamer_rl.trainers.registry import TRAINERS, load_config
from freamer_rl_envs.minigrid import make_minigrid_env

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
PPO_MLP = ROOT / "recipes" / "baselines" / "ppo_mlp_n2s4.yaml"
#: the PPO-MLP recipe at a size that trains in seconds
TINY_PPO_MLP = [
    "env.id=MiniGrid-Empty-5x5-v0",
    "env.num_envs=2",
    "ppo.frames_per_batch=64",
    "ppo.minibatch_size=32",
    "network.hidden=16",
    "run.total_frames=64",
    "logging.progress_bar=false",
]


def _env(*transforms, pixels=False):
    base = make_minigrid_env("MiniGrid-Empty-5x5-v0", pixels=pixels, include_mission=False)
    return TransformedEnv(base, Compose(InitTracker(), *transforms))


@pytest.mark.parametrize(
    "kind, key, level, pixels",
    [
        ("gaussian", "pixels", 1.0, True),
        ("gaussian", "reward_history", 0.5, False),
        ("salt", "grid", 0.3, False),
        ("dropout", "grid", 0.5, False),
        ("dropout_episode", "pixels", 0.5, True),
        ("stale", "grid", 3, False),
        ("noisy_tv", "pixels", 0.25, True),
        ("salt", "mission_tokens", 0.5, False),
    ],
)
def test_every_kind_keeps_the_env_specs(kind, key, level, pixels):
    torch.manual_seed(0)
    env = _env(ModalityCorruption(key, kind, level), pixels=pixels)
    check_env_specs(env)
    env.close()


def test_salt_replaces_the_given_share_within_the_spec_range():
    torch.manual_seed(0)
    clean = _env().rollout(200, break_when_any_done=False)["grid"]
    torch.manual_seed(0)
    env = _env(ModalityCorruption("grid", "salt", 0.3))
    spec = env.observation_spec["grid"]
    noisy = env.rollout(200, break_when_any_done=False)["grid"]
    changed = (noisy != clean).float().mean()  # a replacement may redraw the same value: a bit under 0.3
    assert 0.2 < changed < 0.31, changed
    assert spec.is_in(noisy)


def test_gaussian_scale_is_relative_to_the_running_std():
    torch.manual_seed(0)
    t = ModalityCorruption("x", "gaussian", 2.0)
    x = torch.randn(20_000, 4) * 5.0
    td = t._corrupt(__import__("tensordict").TensorDict({"x": x}, batch_size=[20_000]), None)
    assert abs(t.running_std - 5.0) < 0.1
    # noise std = level * running std = 10
    assert abs(float((td["x"] - x).std()) - 10.0) < 0.3


def test_dropout_zeroes_the_whole_key_and_marks_it():
    torch.manual_seed(0)
    data = _env(ModalityCorruption("grid", "dropout", 0.5)).rollout(300, break_when_any_done=False)
    present = data["grid_present"].reshape(-1).bool()
    assert 0.4 < present.float().mean() < 0.6
    assert (data["grid"][~present] == 0).all() and (data["grid"][present].sum((-1, -2, -3)) > 0).all()


def test_episode_dropout_holds_its_draw_until_that_env_resets():
    torch.manual_seed(0)
    t = ModalityCorruption("x", "dropout_episode", 0.25)
    td = lambda: TensorDict({"x": torch.ones(4000, 3)}, batch_size=[4000])  # noqa: E731
    first = t._corrupt(td(), None)["x_present"].squeeze(-1)  # every env starts an episode
    assert abs(float(first.mean()) - 0.75) < 0.03
    for _ in range(3):  # steps continue the episode: the same draw, the key zeroed exactly where it is dropped
        step = t._call(td())
        assert torch.equal(step["x_present"].squeeze(-1), first)
        assert torch.equal(step["x"], first.unsqueeze(-1).expand(4000, 3))
    restart = torch.arange(4000) < 2000
    reset = t._reset(TensorDict({"_reset": restart.unsqueeze(-1)}, batch_size=[4000]), td())
    after = reset["x_present"].squeeze(-1)
    assert torch.equal(after[~restart], first[~restart])  # envs that did not reset keep theirs
    assert 0.3 < float((after[restart] != first[restart]).float().mean()) < 0.45  # 2 * 0.25 * 0.75 = 0.375 redrawn


def test_episode_dropout_is_constant_within_each_episode_of_a_batched_env():
    torch.manual_seed(0)
    base = SerialEnv(4, functools.partial(make_minigrid_env, "MiniGrid-Empty-5x5-v0", include_mission=False))
    env = TransformedEnv(base, Compose(InitTracker(), ModalityCorruption("grid", "dropout_episode", 0.5)))
    env.set_seed(0)
    data = env.rollout(240, break_when_any_done=False)  # Empty-5x5 ends at 100 steps: 2-3 episodes per env
    present, first = data["grid_present"].squeeze(-1).bool(), data["is_init"].squeeze(-1)
    kept = []
    for e in range(4):
        starts = first[e].nonzero().squeeze(-1).tolist() + [first.shape[1]]
        for a, b in zip(starts, starts[1:]):
            assert present[e, a:b].all() or not present[e, a:b].any(), (e, a, b)
            assert (data["grid"][e, a:b][~present[e, a:b]] == 0).all()
            kept.append(bool(present[e, a]))
    assert len(kept) >= 8 and any(kept) and not all(kept), kept  # both draws occur across the episodes
    env.close()


def test_stale_sensor_holds_the_value_for_k_steps():
    torch.manual_seed(0)
    clean = _env().rollout(12, break_when_any_done=False)
    torch.manual_seed(0)
    stale = _env(ModalityCorruption("direction", "stale", 3)).rollout(12, break_when_any_done=False)
    for t in range(12):  # refreshed at t = 0, 3, 6, 9 (the reset is step 0), held in between
        assert int(stale["direction"][t]) == int(clean["direction"][3 * (t // 3)]), t


def test_noisy_tv_covers_the_share_of_the_image():
    torch.manual_seed(0)
    clean = _env(pixels=True).rollout(5, break_when_any_done=False)["pixels"]
    torch.manual_seed(0)
    tv = _env(ModalityCorruption("pixels", "noisy_tv", 0.25), pixels=True).rollout(5, break_when_any_done=False)
    diff = (tv["pixels"] != clean).any(-1)  # [T, 56, 56]
    assert diff[:, 28:, :].sum() == 0 and diff[:, :, 28:].sum() == 0  # only the top-left 28x28 square
    assert diff[:, :28, :28].float().mean() > 0.9


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"key": "lidar", "kind": "gaussian"}, r"env.corrupt\[0\].key: the env has no observation 'lidar'"),
        ({"key": "grid", "kind": "gaussian"}, r"env.corrupt\[0\].kind: gaussian adds noise to float or uint8"),
        ({"key": "reward_history", "kind": "salt", "level": 0.1}, r"env.corrupt\[0\].kind: salt replaces integer"),
    ],
)
def test_a_corruption_the_env_cannot_take_is_one_line(entry, message):
    t = corruption_transforms([CorruptionConfig(**entry)], "train")
    with pytest.raises(ConfigError, match=message):
        _ = _env(*t).observation_spec


@pytest.mark.parametrize(
    "override, message",
    [
        ("env.corrupt=[{key: grid, kind: blur}]", r"env.corrupt\[0\].kind: expected one of gaussian"),
        ("env.corrupt=[{key: grid, kind: salt, level: 1.5}]", r"env.corrupt\[0\].level: salt needs a replacement"),
        ("env.corrupt=[{key: grid, kind: stale, level: 2.5}]", r"env.corrupt\[0\].level: stale needs a whole number"),
        ("env.corrupt=[{key: grid, kind: salt, when: always}]", r"env.corrupt\[0\].when: expected train, eval or both"),
        ("env.corrupt=[{kind: salt}]", r"env.corrupt\[0\].key: name the observation key"),
    ],
)
def test_bad_recipe_entries_are_one_line(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(TINY, [override])


def test_phases_pick_their_entries():
    entries = [
        CorruptionConfig("grid", "salt", 0.1, "train"),
        CorruptionConfig("grid", "salt", 0.2, "eval"),
        CorruptionConfig("direction", "stale", 2, "both"),
    ]
    assert [t.level for t in corruption_transforms(entries, "train")] == [0.1, 2.0]
    assert [t.level for t in corruption_transforms(entries, "eval")] == [0.2, 2.0]


@pytest.mark.parametrize(
    "trainer, recipe, tiny",
    [
        ("minigrid_ppo", TINY, ["run.total_frames=128"]),
        ("ppo_baseline", PPO_MLP, TINY_PPO_MLP),
    ],
)
def test_trains_corrupted_and_evaluates_corrupted(trainer, recipe, tiny, tmp_path):
    cfg = load_config(recipe, [*tiny, "env.corrupt=[{key: grid, kind: dropout, level: 1.0, when: both}]"])
    spec = TRAINERS[trainer]
    spec.train(cfg, tmp_path / "run")
    ckpt = sorted((tmp_path / "run" / "checkpoints").glob("checkpoint_*.pt"))[-1]
    clean = spec.evaluate(ckpt, episodes=2, corrupt=[])
    dropped = spec.evaluate(ckpt, episodes=2)  # the recipe's entry applies at evaluation too
    assert clean["corrupt"] == [] and dropped["corrupt"][0]["kind"] == "dropout"
    noisy = spec.evaluate(ckpt, episodes=2, corrupt=[CorruptionConfig("grid", "salt", 0.5, "eval")])
    assert noisy["corrupt"][0]["level"] == 0.5


def test_a_baseline_reads_presence_flags_as_observations(tmp_path):
    """``env.presence`` flags among a baseline's inputs (robustness_presence.yaml's PPO-MLP arm)."""
    overrides = [
        *TINY_PPO_MLP,
        "env.presence=[grid]",
        "env.corrupt=[{key: grid, kind: dropout, level: 0.5, when: train}]",
        "network.observation_keys=[grid, direction, grid_present]",
    ]
    spec = TRAINERS["ppo_baseline"]
    spec.train(load_config(PPO_MLP, overrides), tmp_path / "run")
    ckpt = sorted((tmp_path / "run" / "checkpoints").glob("checkpoint_*.pt"))[-1]
    assert spec.evaluate(ckpt, episodes=2, corrupt=[])["episodes"] == 2  # no dropout: the flag reads 1


def test_freamer_eval_reports_gates_and_refiner_displacement(tmp_path):
    """Gate telemetry: sigma(alpha) and ||e_hat - e|| / ||e|| per modality, in progress.csv and the eval result."""
    import csv

    cfg = load_config(TINY, ["run.total_frames=128"])
    TRAINERS["minigrid_ppo"].train(cfg, tmp_path / "run")
    rows = list(csv.DictReader((tmp_path / "run" / "progress.csv").open()))
    assert {f"fm_displacement_{m}" for m in cfg.model.modalities} <= set(rows[-1])
    ckpt = sorted((tmp_path / "run" / "checkpoints").glob("checkpoint_*.pt"))[-1]
    result = TRAINERS["minigrid_ppo"].evaluate(ckpt, episodes=2)
    for m in cfg.model.modalities:
        # the refiner moves a clean input, if only slightly (trained gates sit near sigma(-3) = 0.047)
        assert 0 < result[f"fm_displacement_{m}"] < 0.5
        # the evaluated gates are the trained ones (the last progress row is written after the last update)
        assert abs(result[f"gate_{m}"] - float(rows[-1][f"gate_{m}"])) < 1e-6


def test_embedding_noise_is_levels_times_the_row_std():
    from freamer_rl.model.factory import EmbeddingNoise

    torch.manual_seed(0)
    e = torch.randn(4000, 64) * torch.linspace(0.5, 3.0, 4000)[:, None]  # rows of different scale
    noise = EmbeddingNoise(2.0)(e) - e
    ratio = noise.std(dim=-1) / e.std(dim=-1)
    assert abs(float(ratio.mean()) - 2.0) < 0.05


def test_table13_protocol_perturbs_one_embedding_before_its_refiner(tmp_path):
    from freamer_rl.run.envs import make_batched_env
    from freamer_rl.trainers.minigrid_ppo import build_modules

    cfg = load_config(TINY, [])
    torch.manual_seed(0)
    modules = build_modules(cfg)
    env = make_batched_env(cfg, modules.primers(), seed=0)
    td = env.reset()
    env.close()
    with torch.no_grad():
        clean = modules.policy(td.clone())
        same = modules.policy_with_embedding_noise({"state": 0.0})(td.clone())
        noisy = modules.policy_with_embedding_noise({"state": 4.0})(td.clone())
    torch.testing.assert_close(same["refined", "state"], clean["refined", "state"])
    assert not torch.allclose(noisy["embed", "state"], clean["embed", "state"])
    torch.testing.assert_close(noisy["embed", "reward"], clean["embed", "reward"])  # only the chosen modality
    # the refiner read the noisy embedding: its output follows it
    torch.testing.assert_close(noisy["refined", "state"], modules.refiners["state"](noisy["embed", "state"]))
    TRAINERS["minigrid_ppo"].train(load_config(TINY, ["run.total_frames=128"]), tmp_path / "run")
    ckpt = sorted((tmp_path / "run" / "checkpoints").glob("checkpoint_*.pt"))[-1]
    out = TRAINERS["minigrid_ppo"].evaluate(
        ckpt, episodes=2, corrupt=[CorruptionConfig("embed.state", "gaussian", 8.0, "eval")]
    )
    assert out["embedding_noise"] == {"state": 8.0}
    with pytest.raises(ConfigError, match=r"env.corrupt\[0\]: an embedding key"):
        load_config(TINY, ["env.corrupt=[{key: embed.state, kind: gaussian, when: train}]"])


def test_cli_eval_takes_corruptions(tmp_path, capsys):
    import json

    from freamer_rl import cli

    TRAINERS["minigrid_ppo"].train(load_config(TINY, ["run.total_frames=128"]), tmp_path / "run")
    assert (
        cli.main(
            [
                "eval",
                str(tmp_path / "run"),
                "--episodes",
                "2",
                "--corrupt",
                "grid:salt:0.5",
                "--corrupt",
                "embed.state:gaussian:2",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["corrupt"] == [{"key": "grid", "kind": "salt", "level": 0.5, "when": "eval", "channels": None}]
    assert out["embedding_noise"] == {"state": 2.0}
    assert cli.main(["eval", str(tmp_path / "run"), "--episodes", "2", "--corrupt", "grid:salt"]) == 2
    assert "error: --corrupt 'grid:salt': expected KEY:KIND:LEVEL" in capsys.readouterr().err
    assert cli.main(["eval", str(tmp_path / "run"), "--episodes", "2", "--corrupt", "grid:blur:1"]) == 2
    assert "env.corrupt[0].kind: expected one of" in capsys.readouterr().err


def test_sensor_copy_is_a_float_second_view_corrupted_on_its_own():
    torch.manual_seed(0)
    env = _env(SensorCopy("grid2", "grid"), ModalityCorruption("grid2", "gaussian", 1.0))
    check_env_specs(env)
    td = env.rollout(6, break_when_any_done=False)
    assert td["grid2"].dtype == torch.float32 and td["grid2"].shape == td["grid"].shape
    noise = td["grid2"] - td["grid"].float()
    assert noise.std() > 0.5  # the copy is corrupted (sigma = the copy's running std of the grid values)
    assert td["grid"].dtype == torch.int64 and td["grid"].max() <= 10  # the source sensor is untouched
    env.close()
    clean = _env(SensorCopy("grid2", "grid")).rollout(4, break_when_any_done=False)
    torch.testing.assert_close(clean["grid2"], clean["grid"].float())
    torch.testing.assert_close(clean["next", "grid2"], clean["next", "grid"].float())


@pytest.mark.parametrize(
    "copies, message",
    [
        ({"grid2": "lidar"}, "env.copies.grid2: the env has no observation 'lidar'"),
        ({"direction": "grid"}, "env.copies.direction: the env already has an observation 'direction'"),
    ],
)
def test_a_copy_the_env_cannot_make_is_one_line(copies, message, tmp_path):
    cfg = load_config(TINY, [f"env.copies={{{', '.join(f'{k}: {v}' for k, v in copies.items())}}}"])
    with pytest.raises(ConfigError, match=message):
        probe_specs(cfg)


def test_a_key_copied_onto_itself_is_refused():
    with pytest.raises(ConfigError, match="env.copies.grid: a key cannot be a copy of itself"):
        load_config(TINY, ["env.copies={grid: grid}"])


def test_the_redundant_sensor_recipe_reads_both_views(tmp_path):
    cfg = load_config(ROOT / "recipes" / "minigrid_redundant_sensors.yaml", ["model.compile=false"])
    modules = build_modules(cfg)
    env = make_batched_env(cfg, modules.primers(), 0, num_envs=2)
    with torch.no_grad():
        td = env.rollout(3, modules.policy, break_when_any_done=False)
    env.close()
    assert set(modules.refiners) == {"state", "vector", "reward"}
    assert ("embed", "vector") in td.keys(True) and torch.isfinite(td["embed", "vector"]).all()
