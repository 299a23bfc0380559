"""Architecture switches of issue 20 part 1: ``model.flow.placement: pre | post | off`` and ``model.fusion: fno | concat
| mean`` (plus "Layer-1 only" = placement off and no DNC), built from recipes, trained, counted and checkpointed."""

import csv
from pathlib import Path

import pytest
import torch

from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.layers.encoders import RewardEncoder, VisionEncoder
from freamer_rl.layers.fno import FNOFuser
from freamer_rl.layers.fusion import ConcatFuser, MeanFuser
from freamer_rl.model.losses import FreamerAuxLoss
from freamer_rl.run.checkpoint import load_checkpoint
from freamer_rl.run.envs import make_batched_env
from freamer_rl.trainers.minigrid_ppo import build_modules, params, train
from freamer_rl.trainers.registry import evaluate_any, load_config, resolve_checkpoint

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
FUSERS = {"fno": FNOFuser, "concat": ConcatFuser, "mean": MeanFuser}


def _rollout(cfg, modules, steps=6):
    env = make_batched_env(cfg, modules.primers(), seed=0)
    try:
        with torch.no_grad():
            return env.rollout(steps, modules.policy, break_when_any_done=False)
    finally:
        env.close()


@pytest.mark.parametrize("fusion", sorted(FUSERS))
@pytest.mark.parametrize("placement", ["pre", "post", "off"])
def test_trunk_keys_and_refiners_follow_the_switches(placement, fusion):
    cfg = load_config(TINY, [f"model.flow.placement={placement}", f"model.fusion={fusion}"])
    torch.manual_seed(0)
    modules = build_modules(cfg)
    assert isinstance(modules.fuser, FUSERS[fusion])
    expected = {"pre": set(cfg.model.modalities), "post": {"fused"}, "off": set()}[placement]
    assert set(modules.refiners) == expected
    data = _rollout(cfg, modules)
    assert data["fused"].shape == (cfg.env.num_envs, 6, cfg.model.embed_dim)
    assert (("refined", "state") in data.keys(True)) == (placement == "pre")
    if placement == "post":  # the refiner reads the mixed vector and writes the one the DNC reads
        refined = modules.refiners["fused"](data["embed", "fused"])
        torch.testing.assert_close(refined, data["fused"])


def test_mean_fusion_is_the_mean_of_the_stacked_rows():
    cfg = load_config(TINY, ["model.fusion=mean", "model.flow.placement=off"])
    modules = build_modules(cfg)
    data = _rollout(cfg, modules)
    torch.testing.assert_close(data["fused"], data["modal_stack"].mean(-2))
    stacked = torch.stack([data["embed", m] for m in cfg.model.modalities], dim=-2)
    torch.testing.assert_close(data["modal_stack"], stacked)  # placement off: the raw embeddings are mixed


def test_reward_symlog_reaches_the_reward_encoder():
    def reward_encoder(overrides):
        modules = build_modules(load_config(TINY, overrides))
        return next(m for m in modules.encoders.modules() if isinstance(m, RewardEncoder))

    assert reward_encoder(["model.reward.symlog=true"]).symlog
    assert not reward_encoder([]).symlog  # the default keeps the published runs' maths
    with pytest.raises(ConfigError, match="model.reward.symlog: expected bool"):
        load_config(TINY, ["model.reward.symlog=maybe"])


def test_fm_loss_follows_the_refiners():
    for placement, keys in (("pre", {"fm_state", "fm_language", "fm_reward"}), ("post", {"fm_fused"}), ("off", set())):
        cfg = load_config(TINY, [f"model.flow.placement={placement}"])
        modules = build_modules(cfg)
        data = _rollout(cfg, modules)
        out = FreamerAuxLoss(modules.refiners, smooth_fuser=modules.fuser, modalities=modules.modalities)(data)
        assert {k for k in out.keys() if k.startswith("fm_")} == keys, placement
        assert ("loss_fm" in out.keys()) == bool(keys)


def test_parameter_table_counts_each_arm():
    def total(*overrides):
        return params(load_config(TINY, list(overrides)))[-1]["trainable"]

    base = total()
    off = total("model.flow.placement=off")
    post = total("model.flow.placement=post")
    # pre holds one refiner per modality (3), post one of the same width, off none
    assert post > off and base - off == 3 * (post - off)
    assert total("model.fusion=mean") < base  # the FNO fuser's parameters are gone
    wide, narrow = (
        total("model.fusion=concat", "model.fusion_hidden=64"),
        total("model.fusion=concat", "model.fusion_hidden=8"),
    )
    d, m = 32, 3  # tiny.yaml: embed_dim 32, three modalities; the concat MLP is Linear(M d, h) -> Linear(h, d)
    assert wide - narrow == (m * d + 1) * 56 + 56 * d


@pytest.mark.parametrize(
    "overrides, columns, absent",
    [
        (["model.flow.placement=post"], {"gate_fused", "fm_fused", "loss_fm"}, {"gate_state"}),
        (["model.flow.placement=off", "model.dnc.enabled=false"], set(), {"gate_state", "loss_fm", "gate_fused"}),
        (["model.fusion=concat"], {"gate_state", "loss_fm"}, {"loss_smooth"}),
        (
            ["model.flow.reliability=both", "model.flow.noise_scale=relative"],
            {"gate_input_state", "weight_state", "weight_language", "fm_displacement_reward"},
            {"gate_fused"},
        ),
    ],
)
def test_each_arm_trains_through_the_trainer(overrides, columns, absent, tmp_path):
    cfg = load_config(TINY, [*overrides, "run.total_frames=128"])
    summary = train(cfg, tmp_path / "run")
    assert summary["frames"] == 128
    header = set(next(csv.reader((tmp_path / "run" / "progress.csv").open())))
    assert columns <= header and not absent & header, (columns - header, absent & header)


def test_resume_with_another_placement_is_refused(tmp_path):
    train(load_config(TINY, ["run.total_frames=128"]), tmp_path / "run")
    with pytest.raises(CheckpointError, match="model.flow.placement: checkpoint 'pre' vs now 'post'"):
        train(load_config(TINY, ["run.total_frames=256", "model.flow.placement=post"]), tmp_path / "run")


@pytest.mark.parametrize(
    "override, message",
    [
        ("model.flow.placement=sideways", "model.flow.placement: expected one of pre, post, off"),
        ("model.fusion=attention", "model.fusion: expected one of fno, concat, mean"),
        ("model.vision.pooling=max", "model.vision.pooling: expected one of slots, flatten, got 'max'"),
        ("model.fusion_hidden=64", "model.fusion_hidden: got 64, but only model.fusion=concat has an MLP"),
        ("model.flow.gate_init.lidar=-1", "model.flow.gate_init: unknown modality 'lidar'"),
        ("model.flow.reliability=sometimes", "model.flow.reliability: expected one of off, gate, weight, both"),
        ("model.flow.noise_scale=huge", "model.flow.noise_scale: expected one of absolute, relative"),
        ("model.flow.reliability_margin=-1", "model.flow.reliability_margin"),
    ],
)
def test_bad_switches_are_one_line(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(TINY, [override])


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["model.flow.reliability=weight", "model.flow.placement=post"], "needs model.flow.placement=pre"),
        (["model.flow.reliability=gate", "aux.lambda_fm=0"], "give aux.lambda_fm > 0"),
    ],
)
def test_reliability_needs_per_modality_refiners_and_their_fm_loss(overrides, message):
    with pytest.raises(ConfigError, match=f"model.flow.reliability: .*{message}"):
        load_config(TINY, overrides)


def test_reliability_state_is_checkpointed_and_evaluated(tmp_path):
    train(load_config(TINY, ["run.total_frames=256", "model.flow.reliability=weight"]), tmp_path / "run")
    ckpt = load_checkpoint(resolve_checkpoint(tmp_path / "run"))
    stats = {k: v for k, v in ckpt["model"].items() if k.endswith("score_stats")}
    assert len(stats) == 3 and all(v[0] > 0 for v in stats.values())  # count: the FM loss fed the statistics
    result = evaluate_any(tmp_path / "run", episodes=2, num_envs=2)
    weights = [result[f"weight_{m}"] for m in ("state", "language", "reward")]
    assert all(0.0 < w <= 1.0 for w in weights)  # a mean of exp(-relu(.)) over the evaluated steps


def test_ogm_needs_a_refiner_per_modality():
    with pytest.raises(ConfigError, match="ogm.mode: got 'A', but OGM-GE modulates one refiner per modality"):
        load_config(TINY, ["ogm.mode=A", "model.flow.placement=post"])


def test_yaml_off_is_the_string_off(tmp_path):
    recipe = tmp_path / "r.yaml"
    recipe.write_text("model:\n  flow: {placement: off}\n")
    assert load_config(recipe).model.flow.placement == "off"


@pytest.mark.parametrize("critic_input", ["shared", "detached"])
def test_critic_input_sets_whether_the_value_loss_trains_the_trunk(critic_input):
    """``model.critic_input: detached``: the value head reads the trunk's features through a stop-gradient, so the
    value loss moves the head only; the parameters and their state-dict keys are those of ``shared``."""
    cfg = load_config(TINY, [f"model.critic_input={critic_input}"])
    torch.manual_seed(0)
    modules = build_modules(cfg)
    data = _rollout(cfg, modules)
    td = modules.actor_value.get_value_operator()(data.clone())
    td["state_value"].pow(2).mean().backward()
    trunk_grads = [p.grad for p in modules.trunk.parameters() if p.requires_grad]
    reached = any(g is not None and g.abs().sum() > 0 for g in trunk_grads)
    assert reached == (critic_input == "shared")
    assert all(p.grad is not None for p in modules.critic.parameters())
    shared = build_modules(load_config(TINY, []))
    assert modules.critic.state_dict().keys() == shared.critic.state_dict().keys()


def test_critic_input_is_checked():
    with pytest.raises(ConfigError, match="model.critic_input: expected one of shared, detached, got 'frozen'"):
        load_config(TINY, ["model.critic_input=frozen"])


def test_vision_flatten_pooling_builds_from_the_env_and_trains(tmp_path):
    """``model.vision.pooling: flatten`` sizes its Linear from the env's frames (56x56 RGB view -> 7x7 tokens), gives
    the vision modality one slot, and a tiny run trains it through the trainer."""
    overrides = ["model.modalities=[vision, reward]", "model.vision.pooling=flatten", "run.total_frames=256"]
    cfg = load_config(TINY, overrides)
    torch.manual_seed(0)
    modules = build_modules(cfg)
    encoder = next(m for m in modules.encoders.modules() if isinstance(m, VisionEncoder))
    assert (encoder.pooling, encoder.num_slots, encoder.flat.in_features) == ("flatten", 1, 49 * encoder.token_dim)
    data = _rollout(cfg, modules)
    assert data["slots", "vision"].shape == (cfg.env.num_envs, 6, 1, cfg.model.embed_dim)
    train(cfg, tmp_path / "run")
    first, last = (
        load_checkpoint(tmp_path / "run" / "checkpoints" / f"checkpoint_{n:09d}.pt")["model"] for n in (128, 256)
    )
    (key,) = [k for k in last if k.endswith("flat.weight")]
    assert last[key].shape == encoder.flat.weight.shape
    assert not torch.equal(first[key], last[key])  # the second batch's PPO update reached the flattened grid's Linear
