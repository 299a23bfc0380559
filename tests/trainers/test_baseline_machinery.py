"""The shared machinery on the baselines (issue 21): the success buffer in ``ppo_baseline`` (every network kind), the
``shaping`` section in ``impala``, and the refusals of what a baseline cannot do."""

import csv
import math
from pathlib import Path

import pytest
import torch
from torchrl.modules import set_recurrent_mode

from freamer_rl.errors import ConfigError
from freamer_rl.machinery.success_buffer import LOSS_MASK_KEY, LOSS_WEIGHT_KEY, REPLAY_MASK_KEY, weighted_ppo_loss
from freamer_rl.trainers.baselines.impala import ImpalaTrainer
from freamer_rl.trainers.baselines.ppo_baseline import PPOBaselineTrainer
from freamer_rl.trainers.ppo_loss import clip_ppo_loss
from freamer_rl.trainers.registry import TRAINERS, load_config

ROOT = Path(__file__).resolve().parents[2]
RECIPES = ROOT / "recipes" / "baselines"
L, S_MB, MIX = 4, 2, 0.5  # sequence length, on-policy sequences per minibatch, buffer share
N_REPLAY = round(S_MB * MIX / (1 - MIX))  # replayed sequences per minibatch (SuccessReplay.mix): 2
PPO_TINY = [
    "env.id=MiniGrid-Empty-5x5-v0",
    "env.num_envs=2",
    "ppo.frames_per_batch=32",  # [2 envs, 16 steps] = 8 sequences of 4
    f"ppo.sequence_length={L}",
    f"ppo.minibatch_size={S_MB * L}",
    "ppo.epochs=1",
    "network.hidden=16",
    "network.cnn_channels=[4,4,4]",
    "logging.progress_bar=false",
    "run.seed=3",
]
KEYS = {"mlp": ["grid", "direction"], "mlp_lstm": ["grid", "direction"], "cnn": ["pixels"], "cnn_lstm": ["pixels"]}


def _ppo(tmp_path, kind, *extra):
    keys = ",".join(KEYS[kind])
    cfg = load_config(
        RECIPES / "ppo_mlp_n2s4.yaml", [*PPO_TINY, f"network.kind={kind}", f"network.observation_keys=[{keys}]", *extra]
    )
    return PPOBaselineTrainer(cfg, tmp_path / "run")


def _collect(trainer, frames):
    collector = trainer.make_collector(frames)
    try:
        return next(iter(collector))
    finally:
        collector.shutdown()


def _spy_loss(trainer):
    """Record every minibatch the trainer's ClipPPOLoss receives."""
    seen, loss = [], trainer.loss

    def spy(td):
        seen.append(td.detach().clone())
        return loss(td)

    trainer.loss = spy
    return seen


def _one_success(data):
    """No real success left in ``data [2, 16]``; env 0's episode ends in success at t = L - 1 (MiniGrid's rule:
    terminated with a positive reward), so exactly its steps of the first sequence are successful."""
    nxt = data["next"]
    nxt["reward"].zero_()
    for key in ("done", "terminated"):
        nxt[key][0, L - 1] = True
    nxt["reward"][0, L - 1] = 0.9
    start = max([0, *[t + 1 for t in range(L - 1) if bool(nxt["done"][0, t])]])
    expected = torch.zeros(L, dtype=torch.bool)
    expected[start:] = True
    return expected


@pytest.mark.parametrize(
    "kind,shaping", [("mlp", []), ("mlp_lstm", ["shaping.time_penalty=0.01"]), ("cnn", []), ("cnn_lstm", [])]
)
def test_successes_fill_the_buffer_and_replayed_steps_reach_the_loss(tmp_path, kind, shaping):
    trainer = _ppo(tmp_path, kind, "success_buffer.enabled=true", f"success_buffer.mix={MIX}", *shaping)
    data = _collect(trainer, 32)
    expected_mask = _one_success(data)
    if shaping:  # the reward GAE reads is the one replayed
        trainer.shaper(data, 0.0)
    with set_recurrent_mode(trainer.recurrent), torch.no_grad():  # stored after GAE, as the trainer does
        trainer.gae(data)
    assert trainer.replay.store(data) == 1  # only the first sequence of env 0 holds successful steps
    stored = trainer.replay.buffer.ordered()
    assert torch.equal(stored[REPLAY_MASK_KEY][0], expected_mask)
    assert torch.equal(stored[KEYS[kind][0]][0], data[KEYS[kind][0]][0, :L])
    assert (("next", "shaped_reward") in stored.keys(True)) == bool(shaping)

    seen = _spy_loss(trainer)
    logs = trainer.learn(data)
    # feed-forward kinds too: [S + n, L] sequences, S on-policy then n replayed (one stored row: n copies of it)
    assert len(seen) == 8 // S_MB and all(mb.shape == (S_MB + N_REPLAY, L) for mb in seen)
    first = seen[0]
    assert torch.equal(first[LOSS_WEIGHT_KEY][:S_MB], torch.ones(S_MB, L))
    for row in range(S_MB, S_MB + N_REPLAY):
        assert torch.equal(first["action"][row], stored["action"][0])
    # before the first update pi_k = mu: the weight min(rho_clip, pi_k / mu) * mask is the mask itself (the last
    # step is terminated, so no bootstrap point is dropped); TorchRL's validity mask follows it
    replay_w = first[LOSS_WEIGHT_KEY][S_MB:]
    torch.testing.assert_close(replay_w, expected_mask.float().expand(N_REPLAY, L), atol=1e-4, rtol=0)
    assert torch.equal(first[LOSS_MASK_KEY], first[LOSS_WEIGHT_KEY] > 0)
    assert logs["success_buffer_size"] == 2.0  # the same batch stored again after its epochs
    assert math.isfinite(logs["loss_objective"])


def test_buffer_off_keeps_the_single_step_minibatches(tmp_path):
    trainer = _ppo(tmp_path, "mlp")
    assert trainer.replay is None and trainer.loss.reduction == "mean"
    seen = _spy_loss(trainer)
    logs = trainer.learn(_collect(trainer, 32))
    assert [mb.shape for mb in seen] == [torch.Size([S_MB * L])] * 4 and "success_buffer_size" not in logs
    assert all(LOSS_WEIGHT_KEY not in mb.keys() for mb in seen)


def test_empty_buffer_gives_plain_ppo_loss(tmp_path):
    """Before any success the mixed minibatch is the collected one with weight 1: weighted == PPO's mean loss."""
    trainer = _ppo(tmp_path, "mlp", "success_buffer.enabled=true")
    data = trainer.gae(_collect(trainer, 32))
    mb = data.exclude("next")[:, :L].clone()
    mixed = trainer.replay.mix(mb)
    assert mixed.shape == mb.shape and torch.equal(mixed[LOSS_WEIGHT_KEY], torch.ones(2, L))
    weighted = weighted_ppo_loss(trainer.loss(trainer.common(mixed.clone())), mixed[LOSS_WEIGHT_KEY])
    plain = clip_ppo_loss(trainer.actor, trainer.critic, trainer.cfg.ppo)(trainer.common(mb.clone()))
    for key in ("loss_objective", "loss_critic", "loss_entropy"):
        torch.testing.assert_close(weighted[key], plain[key])


IMPALA_TINY = [
    "env.id=MiniGrid-Empty-5x5-v0",
    "env.num_envs=2",
    "network.hidden=16",
    "impala.frames_per_batch=64",
    "collector.num_collectors=1",
    "logging.checkpoint_every_frames=128",
    "logging.progress_bar=false",
    "shaping.time_penalty=0.01",
    "shaping.novelty.weight=0.1",
]


def test_impala_trains_on_the_shaped_reward(tmp_path):
    cfg = load_config(RECIPES / "impala_n2s4.yaml", [*IMPALA_TINY, "run.total_frames=128"])
    summary = TRAINERS["impala"].train(cfg, tmp_path / "run")
    rows = list(csv.DictReader((tmp_path / "run" / "progress.csv").open()))
    assert summary["frames"] == 128 and len(rows) == 2
    assert {"bonus_novelty", "time_penalty", "shaping_decay"} <= set(rows[0])
    assert all(math.isfinite(float(r["loss_objective"])) for r in rows)

    trainer = ImpalaTrainer(cfg, tmp_path / "seam")
    data = _collect(trainer, 64)
    logs = trainer.learn(data)
    nxt = data["next"]
    rate = trainer.stats.success_rate
    penalty = 0.01 * (1 + (0.0 if math.isnan(rate) else rate))  # A.5: alpha (1 + success rate)
    assert logs["time_penalty"] == pytest.approx(penalty)
    assert bool((nxt["novelty_bonus"] > 0).any())  # the NoveltyBonus transform ran in the actor's env
    torch.testing.assert_close(nxt["shaped_reward"] - nxt["reward"], 0.1 * nxt["novelty_bonus"] - penalty)
    # V-trace reads the shaped reward and never the env's (on which success is judged)
    _, target, _ = trainer.vtrace(data)
    noisy = data.clone()
    noisy["next", "reward"] = torch.rand_like(noisy["next", "reward"])
    torch.testing.assert_close(trainer.vtrace(noisy)[1], target)
    unshaped = data.clone()
    unshaped["next", "shaped_reward"] = unshaped["next", "reward"].clone()
    assert not torch.allclose(trainer.vtrace(unshaped)[1], target)


@pytest.mark.parametrize(
    "recipe,override,match",
    [
        ("impala_n2s4.yaml", "success_buffer.enabled=true", "success_buffer.enabled: trainer impala has no success"),
        ("impala_n2s4.yaml", "shaping.curiosity=0.2", "shaping.curiosity: .* the impala trainer does not have"),
        ("impala_n2s4.yaml", "shaping.vision_language=0.1", "shaping.vision_language: .* impala trainer"),
        ("ppo_mlp_n2s4.yaml", "shaping.vision_language=0.1", "shaping.vision_language: .* ppo_baseline trainer"),
        ("ppo_mlp_n2s4.yaml", "success_buffer.mix=1.0", "success_buffer.mix: got 1.0"),
        ("impala_n2s4.yaml", "shaping.time_penalty=-1.0", "shaping.time_penalty: got -1.0"),
    ],
)
def test_refusals_name_the_field(recipe, override, match):
    with pytest.raises(ConfigError, match=match):
        load_config(RECIPES / recipe, [override])


def test_buffer_refused_where_the_adapter_cannot_judge_success(tmp_path):
    cfg = load_config(RECIPES / "ppo_mlp_cartpole.yaml", ["success_buffer.enabled=true", "env.num_envs=1"])
    with pytest.raises(ConfigError, match="success_buffer.enabled: the 'gym' adapter does not judge"):
        PPOBaselineTrainer(cfg, tmp_path / "run")
