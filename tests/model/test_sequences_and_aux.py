"""Sequences for stateful layers and the auxiliary objective as a TorchRL loss."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tensordict import NonTensorData, TensorDict
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import LossModule

from freamer_rl.model.losses import FreamerAuxLoss
from freamer_rl.run.envs import make_batched_env
from freamer_rl.run.sequences import sequence_replay_buffer, split_sequences
from freamer_rl.trainers.minigrid_ppo import build_modules
from freamer_rl.trainers.registry import load_config

TINY = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"


@pytest.mark.parametrize("lead", [(4,), (2, 3)])
def test_split_sequences_keeps_time_order(lead):
    T, L = 8, 4
    t = torch.arange(T).expand(*lead, T)
    env = torch.arange(int(torch.Size(lead).numel())).reshape(*lead, 1).expand(*lead, T)
    data = TensorDict(
        {"t": t, "env": env, "mission": NonTensorData("go", batch_size=(*lead, T))}, batch_size=(*lead, T)
    )
    seqs = split_sequences(data, L)
    assert seqs.batch_size == (int(torch.Size(lead).numel()) * T // L, L)
    assert "mission" not in seqs.keys()
    # every sequence is L consecutive steps of one env
    assert (seqs["t"].diff(dim=-1) == 1).all()
    assert (seqs["env"] == seqs["env"][:, :1]).all()


def test_split_sequences_refuses_bad_batches():
    with pytest.raises(ValueError, match=r"\[..., envs, T\] with T a multiple of 4"):
        split_sequences(TensorDict({"x": torch.zeros(8)}, batch_size=(8,)), 4)
    with pytest.raises(ValueError, match="multiple of 3"):
        split_sequences(TensorDict({"x": torch.zeros(2, 8)}, batch_size=(2, 8)), 3)


def test_sequence_replay_buffer_samples_whole_sequences_once_per_epoch():
    rb = sequence_replay_buffer(num_sequences=6, sequences_per_minibatch=2)
    seqs = TensorDict({"id": torch.arange(6).unsqueeze(-1).expand(6, 5)}, batch_size=(6, 5))
    for _ in range(2):  # refilled every batch; the buffer is built once
        rb.empty()
        rb.extend(seqs)
        seen = torch.cat([rb.sample()["id"][:, 0] for _ in range(3)])
        assert sorted(seen.tolist()) == list(range(6))


def _collected_minibatch():
    cfg = load_config(TINY)
    torch.manual_seed(0)
    modules = build_modules(cfg)
    env = make_batched_env(cfg, modules.primers(), seed=0)
    with torch.no_grad():
        data = env.rollout(16, modules.policy, break_when_any_done=False)
    env.close()
    return modules, split_sequences(data, 8)


def test_aux_loss_is_a_torchrl_loss_with_settable_keys():
    modules, mb = _collected_minibatch()
    aux = FreamerAuxLoss(modules.refiners, smooth_fuser=modules.fuser)
    assert isinstance(aux, LossModule)
    assert aux.tensor_keys.embed == "embed"
    with set_recurrent_mode(True):
        mb = modules.trunk(mb)
    out = aux(mb)
    assert {"loss_fm", "loss_smooth", *(f"fm_{m}" for m in modules.modalities)} <= set(out.keys())
    assert all(out[f"fm_{m}"].requires_grad is False for m in modules.modalities)
    # renamed keys: the loss reads wherever the user's trunk wrote
    renamed = mb.clone(False)
    renamed.rename_key_("embed", "features")
    renamed.rename_key_("modal_stack", "E")
    aux.set_keys(embed="features", modal_stack="E")
    out2 = aux(renamed)
    assert ("features", "state") in aux.in_keys and "E" in aux.in_keys
    torch.testing.assert_close(out2["loss_smooth"], out["loss_smooth"])
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        aux.set_keys(bogus="x")


def test_aux_loss_runs_the_trunk_when_given_one():
    modules, mb = _collected_minibatch()
    collected_stack = mb["modal_stack"]  # written at collection time, without gradients
    torch.manual_seed(1)
    with set_recurrent_mode(True):
        expected = FreamerAuxLoss(modules.refiners, smooth_fuser=modules.fuser)(modules.trunk(mb.clone()))
    torch.manual_seed(1)
    got = FreamerAuxLoss(modules.refiners, smooth_fuser=modules.fuser, trunk=modules.trunk)(mb)
    assert mb["modal_stack"] is collected_stack  # the user's minibatch is left as it was
    for k in ("loss_fm", "loss_smooth"):
        torch.testing.assert_close(got[k], expected[k])
    got["loss_fm"].backward()
    assert any(p.grad is not None for p in modules.trunk.parameters())
