"""TorchRL PPO baselines (trainer ``ppo_baseline``): networks over batch shapes, config validation, a real learning
run, and the Crafter PPO-CNN through the shared run loop."""

import csv
from pathlib import Path

import pytest
import torch
from torchrl.data import Bounded, Categorical, Composite

from freamer_rl.errors import CheckpointError, ConfigError, EnvSetupError
from freamer_rl.run.checkpoint import load_checkpoint
from freamer_rl.trainers.baselines.config import NetworkConfig, PPOBaselineConfig
from freamer_rl.trainers.baselines.impala import ImpalaTrainer
from freamer_rl.trainers.baselines.networks import ObservationEncoder, build_actor_critic
from freamer_rl.trainers.baselines.ppo_baseline import PPOBaselineTrainer
from freamer_rl.trainers.registry import TRAINERS, load_config, resolve_checkpoint

ROOT = Path(__file__).resolve().parents[2]
MLP_RECIPE = ROOT / "recipes" / "baselines" / "ppo_mlp_n2s4.yaml"
CNN_RECIPE = ROOT / "recipes" / "baselines" / "ppo_cnn_crafter.yaml"
LSTM_CRAFTER_RECIPE = ROOT / "recipes" / "baselines" / "ppo_lstm_crafter.yaml"


def _specs():
    obs = Composite(
        grid=Bounded(0, 10, shape=(7, 7, 3), dtype=torch.int64),
        direction=Categorical(4, shape=(), dtype=torch.int64),
        pixels=Bounded(0, 255, shape=(64, 64, 3), dtype=torch.uint8),
        inventory=Bounded(0.0, 9.0, shape=(16,), dtype=torch.float32),
    )
    return obs, Categorical(7, shape=(), dtype=torch.int64)


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
@pytest.mark.parametrize(
    "kind,keys,shared,image_key",
    [
        ("mlp", ["grid", "direction"], False, None),
        ("mlp", ["grid"], True, None),
        ("cnn", ["pixels", "inventory"], True, None),
        # two image-shaped keys: the named one is convolved, the 7x7x3 grid flattened beside it
        ("cnn", ["grid", "pixels", "direction"], True, "pixels"),
    ],
)
def test_actor_critic_over_batch_shapes(batch, kind, keys, shared, image_key):
    obs_spec, act_spec = _specs()
    net = build_actor_critic(
        obs_spec,
        act_spec,
        NetworkConfig(kind=kind, observation_keys=keys, hidden=32, shared=shared, image_key=image_key),
    )
    td = obs_spec.rand(batch)
    out = net.get_policy_operator()(td.clone())
    assert out["action"].shape == batch and out["action_log_prob"].shape == batch
    assert net.get_value_operator()(td.clone())["state_value"].shape == (*batch, 1)
    encoders = [m for m in net.module[0].module.modules() if isinstance(m, ObservationEncoder)]
    assert len(encoders) == (1 if shared else 2)
    if image_key is not None:  # the conv stack reads the pixels; the grid and direction are flattened beside it
        assert encoders[0].image_index == keys.index(image_key)


def test_encoder_scales_pixels_and_flattens_scalars():
    enc = ObservationEncoder([(36, 36, 3), ()], hidden=4, image_index=0, channels=(2, 2, 2))
    x = torch.full((2, 36, 36, 3), 255, dtype=torch.uint8)
    # the conv stack sees [0, 1] pixels: the same as feeding ones through it by hand
    ones = enc.conv(torch.ones(2, 3, 36, 36))
    expected = enc.fc(torch.cat([ones, torch.tensor([[1.0], [2.0]])], dim=-1))
    torch.testing.assert_close(enc(x, torch.tensor([1, 2])), expected)


def test_network_errors_name_the_field(tmp_path):
    with pytest.raises(ConfigError, match="network.kind"):
        load_config(MLP_RECIPE, ["network.kind=transformer"])
    with pytest.raises(ConfigError, match="network.observation_keys"):
        load_config(MLP_RECIPE, ["network.observation_keys=[]"])
    with pytest.raises(ConfigError, match="network.cnn_channels"):
        load_config(MLP_RECIPE, ["network.cnn_channels=[8,8]"])
    obs_spec, act_spec = _specs()
    with pytest.raises(EnvSetupError, match="network.observation_keys.*'image'"):
        build_actor_critic(obs_spec, act_spec, NetworkConfig(observation_keys=["image"]))
    with pytest.raises(EnvSetupError, match="exactly one image key"):
        build_actor_critic(obs_spec, act_spec, NetworkConfig(kind="cnn", observation_keys=["grid", "pixels"]))
    with pytest.raises(ConfigError, match="network.image_key"):
        load_config(MLP_RECIPE, ["network.kind=cnn", "network.image_key=pixels"])
    with pytest.raises(EnvSetupError, match="at least 36x36"):
        ObservationEncoder([(8, 8, 3)], hidden=4, image_index=0)


def test_recipes_build_their_schema():
    assert isinstance(load_config(MLP_RECIPE), PPOBaselineConfig)
    cfg = load_config(CNN_RECIPE)
    assert cfg.network.kind == "cnn" and cfg.env.adapter == "crafter"


def test_ppo_mlp_learns_empty_5x5(tmp_path):
    """PPO-MLP on Empty-5x5: after 6k frames the agent finishes episodes several times faster than at the start."""
    cfg = load_config(
        MLP_RECIPE,
        [
            "env.id=MiniGrid-Empty-5x5-v0",
            "env.num_envs=4",
            "ppo.frames_per_batch=512",
            "ppo.minibatch_size=128",
            "network.hidden=64",
            "optim.lr=1e-3",
            "run.total_frames=6144",
            "logging.progress_bar=false",
        ],
    )
    summary = TRAINERS["ppo_baseline"].train(cfg, tmp_path / "run")
    import csv

    rows = list(csv.DictReader((tmp_path / "run" / "progress.csv").open()))
    assert len(rows) == 12 and {"loss_objective", "loss_critic", "loss_entropy", "grad_norm"} <= set(rows[0])
    first = int(rows[1]["episodes"])  # episodes finished in the first 1,024 frames
    last = int(rows[-1]["episodes"]) - int(rows[-3]["episodes"])  # ... and in the last 1,024
    assert last >= 2 * first, (first, last)
    assert summary["final_return_mean"] > 0.4 and summary["trainer"] == "ppo_baseline"
    result = TRAINERS["ppo_baseline"].evaluate(resolve_checkpoint(tmp_path / "run"), episodes=8)
    assert result["episodes"] == 8 and result["success_rate"] > 0.5


@pytest.mark.parametrize("recipe", [CNN_RECIPE, LSTM_CRAFTER_RECIPE], ids=["ppo_cnn", "ppo_lstm"])
def test_ppo_on_crafter_logs_the_score_and_resumes(tmp_path, recipe):
    """Both Crafter baselines as their recipes build them (worlds generated ahead in a worker process, the LSTM's
    pixels + inventory + reward history), tiny: train, resume, the score in the log, parameter rows."""
    pytest.importorskip("crafter")
    tiny = [
        "env.num_envs=2",
        "ppo.frames_per_batch=64",
        "ppo.minibatch_size=32",
        "ppo.sequence_length=8",
        "ppo.epochs=1",
        "network.hidden=32",
        "network.cnn_channels=[4,4,4]",
        "logging.progress_bar=false",
        "logging.checkpoint_every_frames=64",
    ]
    assert load_config(recipe, tiny).env.reset_workers == 1  # the recipes' prefetched worlds are what this runs
    TRAINERS["ppo_baseline"].train(load_config(recipe, [*tiny, "run.total_frames=64"]), tmp_path / "run")
    summary = TRAINERS["ppo_baseline"].train(load_config(recipe, [*tiny, "run.total_frames=128"]), tmp_path / "run")
    assert summary["frames"] == 128 and "crafter_score" in summary
    header = (tmp_path / "run" / "progress.csv").read_text().splitlines()[0]
    assert "crafter_score" in header
    assert len((tmp_path / "run" / "progress.csv").read_text().splitlines()) == 3  # the resumed run kept row 1
    assert (tmp_path / "run" / "metrics" / "attempt_02").is_dir()
    rows = TRAINERS["ppo_baseline"].params(load_config(recipe, tiny))
    assert rows[-1]["component"] == "Total" and rows[-1]["trainable"] == sum(r["trainable"] for r in rows[:-1])


GYM_BASELINES = sorted((ROOT / "recipes" / "baselines").glob("ppo_*_cartpole.yaml")) + sorted(
    (ROOT / "recipes" / "baselines").glob("ppo_*_pendulum.yaml")
)


@pytest.mark.parametrize("recipe", GYM_BASELINES, ids=[r.stem for r in GYM_BASELINES])
def test_gym_baseline_recipes_train_and_evaluate(tmp_path, recipe):
    """Every gym baseline recipe as shipped, shrunk: two batches train, the episodes in them are CartPole's or
    Pendulum's (Pendulum's 200-step episodes end at 200 frames each), and the checkpoint evaluates."""
    tiny = ["ppo.frames_per_batch=256", "ppo.minibatch_size=64", "ppo.epochs=1", "logging.progress_bar=false"]
    cfg = load_config(recipe, [*tiny, "run.total_frames=512"])
    summary = TRAINERS["ppo_baseline"].train(cfg, tmp_path / "run")
    assert summary["frames"] == 512 and summary["trainer"] == "ppo_baseline"
    if "pendulum" in recipe.stem:  # 8 envs x 64 steps: no 200-step episode has ended yet
        assert summary["episodes"] == 0
    else:  # random CartPole play ends episodes within ~20 steps
        assert summary["episodes"] >= 8 and summary["final_return_mean"] > 0
    result = TRAINERS["ppo_baseline"].evaluate(resolve_checkpoint(tmp_path / "run"), episodes=2)
    assert result["episodes"] == 2


def test_resume_refuses_another_network(tmp_path):
    from freamer_rl.errors import CheckpointError

    tiny = [
        "env.id=MiniGrid-Empty-5x5-v0",
        "env.num_envs=2",
        "ppo.frames_per_batch=64",
        "ppo.minibatch_size=32",
        "ppo.sequence_length=8",
        "network.hidden=16",
        "run.total_frames=64",
        "logging.progress_bar=false",
    ]
    TRAINERS["ppo_baseline"].train(load_config(MLP_RECIPE, tiny), tmp_path / "run")
    # same weight shapes (direction and grid swapped), other meaning: refused by name, not loaded silently
    with pytest.raises(CheckpointError, match="network.observation_keys"):
        TRAINERS["ppo_baseline"].train(
            load_config(MLP_RECIPE, [*tiny, "network.observation_keys=[direction,grid]", "run.total_frames=128"]),
            tmp_path / "run",
        )


def test_resume_refuses_another_trainers_checkpoint_and_legacy_files_go_to_freamer(tmp_path):
    from freamer_rl.errors import CheckpointError
    from freamer_rl.run.checkpoint import latest_checkpoint
    from freamer_rl.trainers.registry import trainer_of_checkpoint

    tiny = [
        "env.id=MiniGrid-Empty-5x5-v0",
        "env.num_envs=2",
        "ppo.frames_per_batch=64",
        "ppo.minibatch_size=32",
        "ppo.sequence_length=8",
        "network.hidden=16",
        "run.total_frames=64",
        "logging.progress_bar=false",
    ]
    TRAINERS["ppo_baseline"].train(load_config(MLP_RECIPE, tiny), tmp_path / "run")
    impala = ROOT / "recipes" / "baselines" / "impala_n2s4.yaml"
    # the same network and env, another trainer: refused by name instead of loading PPO's state into IMPALA
    impala_tiny = [
        "env.id=MiniGrid-Empty-5x5-v0",
        "env.num_envs=2",
        "impala.frames_per_batch=64",
        "network.hidden=16",
        "collector.num_collectors=1",
        "run.total_frames=128",
        "logging.progress_bar=false",
    ]
    with pytest.raises(CheckpointError, match="trainer 'ppo_baseline'.*'impala'"):
        TRAINERS["impala"].train(load_config(impala, impala_tiny), tmp_path / "run")
    # a checkpoint without a "trainer" entry (written before it existed) is FreamerV1's, whatever reuses its format
    ckpt = torch.load(latest_checkpoint(tmp_path / "run"), weights_only=True)
    del ckpt["trainer"]
    torch.save(ckpt, tmp_path / "legacy.pt")
    assert trainer_of_checkpoint(tmp_path / "legacy.pt") == "minigrid_ppo"


_TINY = {
    "ppo_baseline": (
        "ppo_mlp_n2s4.yaml",
        ["ppo.frames_per_batch=128", "ppo.minibatch_size=64", "ppo.epochs=1", "run.total_frames=256"],
    ),
    "impala": (
        "impala_n2s4.yaml",
        ["env.num_envs=2", "impala.frames_per_batch=64", "collector.num_collectors=1", "run.total_frames=128"],
    ),
}


@pytest.mark.parametrize("trainer", sorted(_TINY))
def test_init_from_transfers_a_baselines_weights_and_refuses_another_network(trainer, tmp_path):
    name, tiny = _TINY[trainer]
    recipe = ROOT / "recipes" / "baselines" / name
    tiny = ["env.id=MiniGrid-Empty-5x5-v0", "network.hidden=16", "logging.progress_bar=false", *tiny]
    TRAINERS[trainer].train(load_config(recipe, tiny), tmp_path / "a")
    source = load_checkpoint(resolve_checkpoint(tmp_path / "a"))["model"]
    cls = {"ppo_baseline": PPOBaselineTrainer, "impala": ImpalaTrainer}[trainer]
    given = [*tiny, "env.id=MiniGrid-DoorKey-5x5-v0", f"run.init_from={tmp_path / 'a'}"]
    stage = cls(load_config(recipe, given), tmp_path / "b")
    for key, value in stage.net.state_dict().items():  # another env, the same network: every weight transferred
        torch.testing.assert_close(value, source[key])
    other = [*tiny, "network.hidden=32", f"run.init_from={tmp_path / 'a'}"]
    with pytest.raises(CheckpointError, match=r"run.init_from: .* another network \(network.hidden: checkpoint 16"):
        cls(load_config(recipe, other), tmp_path / "c")


def test_dreamer_refuses_init_from_at_load(tmp_path):
    recipe = ROOT / "recipes" / "baselines" / "dreamer_v3_n2s4.yaml"
    with pytest.raises(ConfigError, match="run.init_from: the dreamer_v3 trainer cannot start from another run"):
        load_config(recipe, [f"run.init_from={tmp_path}"])


def test_ppo_baseline_takes_freamers_shaping(tmp_path):
    recipe = ROOT / "recipes" / "baselines" / "ppo_mlp_n2s4.yaml"
    tiny = [
        "env.id=MiniGrid-DoorKey-5x5-v0",
        "network.hidden=16",
        "logging.progress_bar=false",
        *_TINY["ppo_baseline"][1],
    ]
    shaped = [*tiny, "shaping.novelty.weight=0.1", "shaping.language.weight=0.2", "shaping.time_penalty=0.02"]
    TRAINERS["ppo_baseline"].train(load_config(recipe, shaped), tmp_path / "run")
    rows = list(csv.DictReader((tmp_path / "run" / "progress.csv").open()))
    assert {"bonus_novelty", "bonus_lang", "time_penalty"} <= set(rows[0])
    assert float(rows[0]["bonus_novelty"]) > 0  # first visits pay the bonus
    with pytest.raises(ConfigError, match="shaping.curiosity: R_intrinsic reads the fused embedding"):
        load_config(recipe, [*tiny, "shaping.curiosity=0.2"])
