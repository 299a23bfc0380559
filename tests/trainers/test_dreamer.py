"""DreamerV3 baseline (TorchRL's DreamerV3 losses and RSSM): world-model learning, imagination shapes, the
collection policy's carried state, a tiny train -> checkpoint -> resume -> evaluate run, config validation."""

import csv
from pathlib import Path

import pytest
import torch

from freamer_rl.errors import ConfigError
from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint
from freamer_rl.run.envs import make_batched_env
from freamer_rl.trainers.baselines.config import DreamerConfig
from freamer_rl.trainers.baselines.dreamer_v3 import DreamerLearner, SequenceReplay, build_nets
from freamer_rl.trainers.baselines.dreamer_v3 import evaluate as evaluate_dreamer
from freamer_rl.trainers.registry import TRAINERS, load_config

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "baselines" / "dreamer_v3_n2s4.yaml"
TINY = [
    "env.id=MiniGrid-Empty-5x5-v0",
    "env.num_envs=2",
    "dreamer.stoch_categoricals=4",
    "dreamer.stoch_classes=4",
    "dreamer.deter=32",
    "dreamer.hidden=32",
    "dreamer.mlp_layers=1",
    "dreamer.frames_per_batch=64",
    "dreamer.batch_size=4",
    "dreamer.sequence_length=8",
    "dreamer.train_every=32",
    "dreamer.prefill_frames=64",
    "dreamer.replay_capacity=1000",
    "dreamer.horizon=5",
    "run.total_frames=128",
    "logging.checkpoint_every_frames=64",
    "logging.progress_bar=false",
]


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    cfg = load_config(RECIPE, TINY)
    nets = build_nets(cfg)
    env = make_batched_env(cfg, [nets.primer()], seed=0)
    with torch.no_grad():
        data = env.rollout(32, nets.policy, break_when_any_done=False)  # [2 envs, 32 steps]
    env.close()
    return cfg, nets, data


def test_recipes_load_as_dreamer_configs():
    for path in sorted((ROOT / "recipes" / "baselines").glob("dreamer_v3_*.yaml")):
        cfg = load_config(path)
        assert isinstance(cfg, DreamerConfig) and cfg.dreamer.horizon == 15, path


def test_collection_policy_carries_its_state(tiny):
    _, _, data = tiny
    is_init = data["is_init"].squeeze(-1)
    assert is_init[:, 0].all()
    belief, next_belief = data["belief"], data["next", "belief"]
    # primer pattern: the root state of step t + 1 is the ("next", state) the policy wrote at step t
    cont = ~is_init[:, 1:]
    assert torch.equal(belief[:, 1:][cont], next_belief[:, :-1][cont])
    assert torch.equal(data["previous_action"][:, 1:][cont], data["next", "previous_action"][:, :-1][cont].float())
    # the belief changes from step to step within an episode ...
    inner = cont[:, 1:]
    assert (belief[:, 2:] - belief[:, 1:-1]).abs().sum(-1)[inner].min() > 0
    # ... and is reset where is_init (zeros carried out of the first step, and zeros primed at the reset)
    assert (next_belief[is_init] == 0).all() and (belief[is_init] == 0).all()
    assert data["action"].dtype == torch.int64 and data["action_onehot"].sum(-1).eq(1).all()


def test_world_model_loss_decreases_and_imagination_shapes(tiny):
    cfg, nets, data = tiny
    torch.manual_seed(1)
    d = cfg.dreamer
    learner = DreamerLearner(nets, d, cfg.optim)
    replay = SequenceReplay(1000, data.shape[-1], d.batch_size, d.sequence_length, list(d.observation_keys))
    replay.extend(data)
    batch = replay.sample()
    assert batch.shape == (d.batch_size, d.sequence_length)

    def model_loss():
        with torch.no_grad():
            torch.manual_seed(2)
            losses, _ = learner.model_loss(batch)
        return float(losses["loss_model_reco"] + losses["loss_model_reward"] + losses["loss_model_continue"])

    before = model_loss()
    for _ in range(8):
        out = learner.update(batch)
    after = model_loss()
    assert after < 0.8 * before, (before, after)
    assert {"loss_model_kl", "loss_model_reco", "loss_model_reward", "loss_actor", "loss_value"} <= set(out)
    assert all(torch.isfinite(v) for v in out.values())
    # imagination from every posterior state: [B * L, H]
    _, post = learner.model_loss(batch)
    start = post.get("next").select("state", "belief").reshape(-1)
    _, imagined = learner.actor_loss(start)
    n = d.batch_size * d.sequence_length
    assert imagined.shape == (n, d.horizon)
    assert imagined["state"].shape == (n, d.horizon, d.stoch_categoricals * d.stoch_classes)
    assert imagined["lambda_target"].shape == (n, d.horizon, 1)


def test_train_checkpoint_resume_evaluate(tmp_path):
    run = tmp_path / "run"
    spec = TRAINERS["dreamer_v3"]
    summary = spec.train(load_config(RECIPE, TINY), run)
    assert summary["frames"] == 128 and summary["updates"] > 0
    rows = list(csv.DictReader((run / "progress.csv").open()))
    for col in ("loss_model_kl", "loss_model_reco", "loss_model_reward", "loss_actor", "loss_value", "updates"):
        assert col in rows[-1], col
    assert float(rows[-1]["loss_model_reco"]) > 0
    ckpt = latest_checkpoint(run)
    assert read_checkpoint(ckpt)["trainer"] == "dreamer_v3"
    resumed = spec.train(load_config(RECIPE, [*TINY, "run.total_frames=192"]), run)
    assert resumed["frames"] == 192
    assert read_checkpoint(latest_checkpoint(run))["frames"] == 192
    result = evaluate_dreamer(latest_checkpoint(run), episodes=2, num_envs=2)
    assert result["episodes"] == 2 and 0 <= result["success_rate"] <= 1
    rows = spec.params(load_config(RECIPE, TINY))
    assert rows[-1]["component"] == "Total" and rows[-1]["trainable"] > 0


@pytest.mark.parametrize(
    "override, field",
    [
        ("dreamer.horizon=0", r"dreamer.horizon: got 0, expected an integer in \[1, "),
        ("dreamer.gamma=1.5", "dreamer.gamma"),
        ("dreamer.sequence_length=64", "dreamer.sequence_length"),
        ("dreamer.observation_keys=[]", "dreamer.observation_keys"),
        ("optim.lr=0", "optim.lr"),
        ("dreamer.frames_per_batch=65", "dreamer.frames_per_batch"),
        # 1,000 frames of capacity hold 31 whole 32-step sequences = 992 < 1,000 prefill: would never start training
        ("dreamer.prefill_frames=1000", "dreamer.replay_capacity: .*whole sequences"),
    ],
)
def test_validation_names_the_field(override, field):
    with pytest.raises(ConfigError, match=field.replace("(", r"\(")):
        load_config(RECIPE, [*TINY, override])


def test_unknown_observation_key_is_named():
    with pytest.raises(ConfigError, match="dreamer.observation_keys: env .* has no observation 'lidar'"):
        build_nets(load_config(RECIPE, [*TINY, "dreamer.observation_keys=[lidar]"]))


def test_image_the_encoder_cannot_halve_is_named():
    """MiniGrid renders 56x56 pixels when a trainer reads them; 4 conv stages need a multiple of 16."""
    with pytest.raises(ConfigError, match="image 'pixels' is 56x56.*divisible by 16"):
        build_nets(load_config(RECIPE, [*TINY, "dreamer.observation_keys=[pixels]"]))


def test_crafter_pixels_through_the_cnn_encoder_and_decoder():
    pytest.importorskip("crafter")
    cfg = load_config(
        ROOT / "recipes" / "baselines" / "dreamer_v3_crafter.yaml",
        [
            "env.num_envs=2",
            "dreamer.deter=32",
            "dreamer.hidden=32",
            "dreamer.cnn_depth=4",
            "dreamer.frames_per_batch=32",
            "dreamer.batch_size=2",
            "dreamer.sequence_length=8",
            "dreamer.prefill_frames=32",
            "dreamer.replay_capacity=1000",
        ],
    )
    torch.manual_seed(0)
    nets = build_nets(cfg)
    assert nets.image_key == "pixels" and not nets.vector_keys
    env = make_batched_env(cfg, [nets.primer()], seed=0)
    with torch.no_grad():
        data = env.rollout(16, nets.policy, break_when_any_done=False)
    env.close()
    learner = DreamerLearner(nets, cfg.dreamer, cfg.optim)
    replay = SequenceReplay(1000, 16, 2, 8, ["pixels"])
    replay.extend(data)
    out = learner.update(replay.sample())
    assert all(torch.isfinite(v) for v in out.values()) and out["loss_model_reco"] > 0
