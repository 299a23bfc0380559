"""Recurrent PPO baseline (``trainer: ppo_baseline``, ``network.kind: mlp_lstm | cnn_lstm``): the LSTM state is primed
and fed back while collecting, the sequence minibatches tile the batch, the recurrent-mode loss sees the collector's
log-probs, and a run trains, checkpoints, evaluates and resumes."""

import csv
import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode

from freamer_rl.errors import ConfigError
from freamer_rl.run.envs import make_batched_env
from freamer_rl.run.sequences import split_sequences
from freamer_rl.trainers.baselines.common import build_network
from freamer_rl.trainers.baselines.networks import ObservationEncoder, recurrent_primers
from freamer_rl.trainers.baselines.ppo_baseline import sequence_minibatches
from freamer_rl.trainers.registry import TRAINERS, evaluate_any, load_config

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "baselines" / "ppo_lstm_n2s4.yaml"
TINY = [
    "env.id=MiniGrid-Empty-5x5-v0",
    "env.num_envs=2",
    "network.hidden=16",
    "network.lstm_hidden=16",
    "ppo.frames_per_batch=64",
    "ppo.minibatch_size=32",
    "ppo.sequence_length=8",
    "logging.progress_bar=false",
    "logging.checkpoint_every_frames=64",
]


def _rollout(overrides: list[str], steps: int, seed: int = 3):
    """``[num_envs, steps]`` of the untrained policy in the primed env (auto-reset inside the rows)."""
    cfg = load_config(RECIPE, [*TINY, *overrides])
    torch.manual_seed(seed)
    net = build_network(cfg)
    env = make_batched_env(cfg, recurrent_primers(net), seed)
    try:
        with torch.no_grad():
            data = env.rollout(steps, net.get_policy_operator(), break_when_any_done=False)
    finally:
        env.close()
    return net, data


def test_lstm_state_is_fed_back_and_zero_at_episode_starts():
    # Empty-5x5 truncates at 100 steps: 130 steps hold an episode start inside every row
    net, data = _rollout(["env.num_envs=4"], 130)
    init = data["is_init"].squeeze(-1)
    assert init[:, 1:].any(dim=1).all()  # a reset inside each row, not only at t = 0
    h, c = data["lstm_h"], data["lstm_c"]
    assert h[init].abs().max() == 0 and c[init].abs().max() == 0
    # the state the policy wrote at step t is the one it reads at t + 1 (unless an episode starts there)
    carried = ~init[:, 1:]
    torch.testing.assert_close(h[:, 1:][carried], data["next", "lstm_h"][:, :-1][carried])
    assert (h[:, 1:][carried] - h[:, :-1][carried]).abs().amax(dim=(-2, -1)).min() > 0  # it changes every step
    # the action distribution at a step depends on the earlier steps, through the state
    step = data[:, 20].exclude("next")
    with torch.no_grad():
        with_state = net.get_policy_operator()(step.clone())["logits"]
        zeroed = net.get_policy_operator()(step.clone().set("lstm_h", torch.zeros_like(step["lstm_h"])))["logits"]
    assert not torch.allclose(with_state, zeroed)


def test_recurrent_mode_on_sequences_reproduces_the_collected_log_probs():
    """What the loss sees: the policy in recurrent mode on [n, L] sequences (from the stored state at t = 0, reset at
    is_init) gives the log-probs the collector stored step by step, so the first PPO ratio is 1."""
    net, data = _rollout([], 128)
    assert data["is_init"][:, 1:].any()
    seqs = split_sequences(data.exclude("next"), 16)
    stored = seqs["action_log_prob"].clone()
    with torch.no_grad(), set_recurrent_mode(True):
        out = net.get_policy_operator()(seqs.exclude("action_log_prob", "logits", "hidden_pi", "hidden_v"))
        dist = net.get_policy_operator().get_dist(out)
    torch.testing.assert_close(dist.log_prob(seqs["action"]), stored, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("seq_len,minibatch", [(4, 8), (8, 16)])
def test_sequence_minibatches_cover_every_step_once_per_epoch(seq_len, minibatch):
    envs, T = 3, 16
    index = torch.arange(envs * T).reshape(envs, T)
    data = TensorDict({"index": index, "next": {"index": index + 1}}, batch_size=[envs, T])
    batches = list(sequence_minibatches(data, seq_len, minibatch, epochs=2))
    per_epoch = envs * T // minibatch
    assert len(batches) == 2 * per_epoch
    for epoch in (batches[:per_epoch], batches[per_epoch:]):
        assert all(mb.batch_size == (minibatch // seq_len, seq_len) and "next" not in mb.keys() for mb in epoch)
        steps = torch.cat([mb["index"].reshape(-1) for mb in epoch])
        assert torch.equal(steps.sort().values, index.reshape(-1))
        for mb in epoch:  # each row: consecutive steps of one env
            rows = mb["index"]
            assert (rows.diff(dim=-1) == 1).all() and (rows[:, 0] // T == rows[:, -1] // T).all()


def test_mlp_lstm_trains_checkpoints_evaluates_and_resumes(tmp_path):
    run = tmp_path / "run"
    spec = TRAINERS["ppo_baseline"]
    spec.train(load_config(RECIPE, [*TINY, "run.total_frames=128"]), run)
    rows = list(csv.DictReader((run / "progress.csv").open()))
    assert len(rows) == 2
    for row in rows:
        for key in ("loss_objective", "loss_critic", "loss_entropy", "grad_norm"):
            assert math.isfinite(float(row[key])), (key, row[key])
    result = evaluate_any(run, episodes=2, num_envs=2)
    assert result["episodes"] == 2 and result["frames_trained"] == 128
    summary = spec.train(load_config(RECIPE, [*TINY, "run.total_frames=192"]), run)
    assert summary["frames"] == 192 and len((run / "progress.csv").read_text().splitlines()) == 4
    table = spec.params(load_config(RECIPE, TINY))
    names = [r["component"] for r in table]
    assert names[:2] == ["encoder", "lstm"] and names[-1] == "Total"
    assert table[1]["trainable"] == 4 * (16 * 16 + 16 * 16 + 2 * 16)  # LSTM(16, 16): 4 gates, 2 biases
    assert table[-1]["trainable"] == sum(r["trainable"] for r in table[:-1])


def test_cnn_lstm_runs_on_minigrid_pixels_with_an_lstm_per_head():
    over = ["network.kind=cnn_lstm", "network.observation_keys=[pixels,direction]", "network.cnn_channels=[4,4,4]"]
    net, data = _rollout([*over, "network.shared=false", "network.lstm_hidden=8"], 4)
    assert data["pixels"].shape[-3:] == (56, 56, 3) and data["action"].shape == (2, 4)
    assert data["lstm_pi_h"].shape == data["lstm_v_h"].shape == (2, 4, 1, 8)
    assert sum(isinstance(m, ObservationEncoder) and m.conv is not None for m in net.modules()) == 2
    with torch.no_grad(), set_recurrent_mode(True):
        values = net.get_value_operator()(data.exclude("next"))["state_value"]
    assert values.shape == (2, 4, 1) and torch.isfinite(values).all()


def test_network_kind_and_lstm_fields_are_checked():
    with pytest.raises(ConfigError, match="network.kind: expected one of mlp, cnn, mlp_lstm, cnn_lstm, got 'gru'"):
        load_config(RECIPE, ["network.kind=gru"])
    with pytest.raises(ConfigError, match="network.lstm_hidden"):
        load_config(RECIPE, ["network.lstm_hidden=0"])
    with pytest.raises(ConfigError, match="ppo.sequence_length"):
        load_config(RECIPE, [*TINY, "ppo.sequence_length=5"])
    impala = ROOT / "recipes" / "baselines" / "impala_n2s4.yaml"  # IMPALA trains feed-forward networks only
    with pytest.raises(ConfigError, match="network.kind: .*mlp_lstm.*ppo_baseline only"):
        load_config(impala, ["network.kind=mlp_lstm"])


@pytest.mark.parametrize("name", ["ppo_lstm_n2s4", "ppo_lstm_gotodoor8x8"])
def test_lstm_recipes_load(name):
    cfg = load_config(ROOT / "recipes" / "baselines" / f"{name}.yaml")
    assert cfg.network.kind == "mlp_lstm" and cfg.network.shared
    assert ("mission_tokens" in cfg.network.observation_keys) == ("gotodoor" in name)
