"""Paired denoising targets (``model.flow.targets=paired``, issue 20 fix): the refiner trained to carry the embedding
of a corrupted observation to that of its clean copy (``env.clean_copies``), in closed form, against synthetic
training, inside the auxiliary loss, on a real env, from the recipe and in a short training run."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import set_recurrent_mode

from freamer_rl.errors import ConfigError
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.machinery.checks import privileged_information
from freamer_rl.model.losses import FreamerAuxLoss, paired_modalities
from freamer_rl.run.corruption import ModalityCorruption, SensorCopy, corruption_transforms
from freamer_rl.run.envs import make_batched_env
from freamer_rl.run.sequences import split_sequences
from freamer_rl.trainers.minigrid_ppo import build_modules
from freamer_rl.trainers.registry import TRAINERS, load_config
from freamer_rl_envs.minigrid import make_minigrid_env

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
PAIRED = [
    "env.corrupt=[{key: grid, kind: salt, level: 0.5, when: train}]",
    "env.clean_copies=[grid]",
    "model.flow.targets=paired",
]


class _StillRefiner(FlowMatchingRefiner):
    """v(x, t) = 0: the flow does not move, so e_hat = e."""

    def velocity(self, x, t):
        return super().velocity(x, t) * 0


def _noisy_pairs(batch, dim):
    """(noisy, clean) ``[*batch, dim]``: clean rows and the same rows plus unit Gaussian noise."""
    clean = torch.randn(*batch, dim)
    return clean + torch.randn(*batch, dim), clean


@pytest.mark.parametrize("batch", [(5,), (2, 3)])
def test_paired_loss_closed_form(batch):
    torch.manual_seed(0)
    ref = _StillRefiner(6, hidden=8)
    noisy, clean = _noisy_pairs(batch, 6)
    loss, left = ref.paired_loss(noisy, clean)
    # flow term: v = 0 against u = clean - noisy; output term: e_hat = noisy
    expected = 2 * (clean - noisy).pow(2).mean()
    torch.testing.assert_close(loss, expected)
    torch.testing.assert_close(left, torch.tensor(1.0))
    assert not left.requires_grad
    _, none_corrupted = ref.paired_loss(clean, clean)
    assert none_corrupted.item() == 0.0
    with pytest.raises(ValueError, match=r"noisy and clean must both be \[\*B, 6\]"):
        ref.paired_loss(noisy[..., :5], clean[..., :5])


@pytest.mark.parametrize("batch", [(12,), (3, 4)])
def test_dropped_rows_leave_the_paired_loss(batch):
    torch.manual_seed(0)
    ref = FlowMatchingRefiner(8, hidden=16)
    noisy, clean = _noisy_pairs(batch, 8)
    mask = (torch.arange(12) % 3 != 0).float().reshape(batch)
    # the dropped rows' embeddings (of an all-zero observation) differ; the kept rows do not
    other = torch.where(mask.bool().unsqueeze(-1), noisy, 100 * torch.randn(*batch, 8))
    results = []
    for x in (noisy, other):
        torch.manual_seed(1)
        results.append(ref.paired_loss(x, clean, mask=mask))
    torch.testing.assert_close(results[0], results[1])
    torch.manual_seed(1)
    t = torch.rand(batch)  # the kept rows' loss equals the unmasked loss on the kept rows alone (same t draws)
    kept = mask.bool()
    with torch.no_grad():
        x_t = (1 - t[kept]).unsqueeze(-1) * noisy[kept] + t[kept].unsqueeze(-1) * clean[kept]
        flow = (ref.velocity(x_t, t[kept]) - (clean[kept] - noisy[kept])).pow(2).mean()
        err = (ref(noisy[kept]) - clean[kept]).pow(2)
        out, left = err.mean(), err.sum() / (noisy[kept] - clean[kept]).pow(2).sum()
    torch.testing.assert_close(results[0][0], flow + out)
    torch.testing.assert_close(results[0][1], left)
    nothing, nothing_left = ref.paired_loss(noisy, clean, mask=torch.zeros(batch))
    assert nothing.item() == 0.0 and nothing_left.item() == 0.0


def _embedding_pairs(w: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Clean rows on a 3-dim subspace of R^16; a quarter of each row's entries hit by large noise."""
    clean = torch.randn(n, 3) @ w / 3**0.5
    hit = (torch.rand(n, w.shape[1]) < 0.25).float()
    return clean + 2 * hit * torch.randn(n, w.shape[1]), clean


def _trained_left(targets: str) -> tuple[float, float]:
    torch.manual_seed(1)
    w = torch.randn(3, 16)
    ref = FlowMatchingRefiner(16, hidden=32, steps=4)
    rest = [p for name, p in ref.named_parameters() if name != "alpha"]
    opt = torch.optim.Adam([{"params": [ref.alpha], "lr": 3e-2}, {"params": rest, "lr": 3e-3}])
    for _ in range(120):
        noisy, clean = _embedding_pairs(w, 128)
        loss = ref.paired_loss(noisy, clean)[0] if targets == "paired" else ref.cfm_loss(clean)
        opt.zero_grad()
        loss.backward()
        opt.step()
    noisy, clean = _embedding_pairs(w, 1024)
    with torch.no_grad():
        return ref.paired_loss(noisy, clean)[1].item(), ref.gate.item()


def test_pairs_teach_the_refiner_to_remove_a_corruption_synthetic_training_leaves():
    paired_left, paired_gate = _trained_left("paired")
    synthetic_left, synthetic_gate = _trained_left("synthetic")
    # synthetic CFM never trains the gate (it sits outside the velocity field): ~95% of the corruption stays
    assert synthetic_gate == pytest.approx(torch.sigmoid(torch.tensor(-3.0)).item())
    assert synthetic_left > 0.9
    # on pairs the gate opens and the flow removes most of the sparse corruption
    assert paired_gate > 0.5
    assert paired_left < 0.5


def test_clean_copy_keeps_the_source_spec_and_escapes_the_corruption():
    torch.manual_seed(0)
    base = make_minigrid_env("MiniGrid-Empty-5x5-v0", include_mission=False)
    copy = SensorCopy("grid_clean", "grid", same_spec=True)
    env = TransformedEnv(base, Compose(InitTracker(), copy, ModalityCorruption("grid", "salt", 0.5)))
    check_env_specs(env)
    assert env.observation_spec["grid_clean"] == env.observation_spec["grid"]
    td = env.rollout(5, break_when_any_done=False)
    assert td["grid_clean"].dtype == td["grid"].dtype
    assert (td["grid_clean"] != td["grid"]).any()  # the policy's grid is salted, the copy is not
    assert env.observation_spec["grid_clean"].is_in(td["grid_clean"][0])
    env.close()


def _paired_minibatch(overrides=()):
    cfg = load_config(TINY, [*PAIRED, *overrides])
    torch.manual_seed(0)
    modules = build_modules(cfg)
    transforms = [*corruption_transforms(cfg.env.corrupt, "train"), *modules.primers()]
    env = make_batched_env(cfg, transforms, seed=0)
    with torch.no_grad():
        data = env.rollout(16, modules.policy, break_when_any_done=False)
    env.close()
    return cfg, modules, split_sequences(data, 8)


def test_aux_loss_pairs_only_the_modalities_a_clean_copy_feeds():
    cfg, modules, mb = _paired_minibatch()
    paired = paired_modalities(modules.modalities, cfg.env.clean_copies, cfg.model.observation_keys)
    assert paired == ["state"]  # the grid feeds the state encoder alone
    aux = FreamerAuxLoss(
        modules.refiners, clean_keys={"grid": "grid_clean"}, encoders=modules.encoders, paired_modalities=paired
    )
    assert "grid_clean" in aux.in_keys
    with set_recurrent_mode(True):
        mb = modules.trunk(mb)
    out = aux(mb)
    assert set(k for k in out.keys() if k.startswith("fm_left_")) == {"fm_left_state"}
    # salt on half the grid entries: the state embedding moves, and the refiner at init removes ~nothing of it
    assert 0.9 < out["fm_left_state"].item() <= 1.0 + 1e-4
    out["loss_fm"].backward()
    assert modules.refiners["state"].alpha.grad.abs().item() > 0  # the gate is trained by the paired term
    with pytest.raises(KeyError, match=r"the clean copies \['grid_clean'\] are missing"):
        aux(mb.exclude("grid_clean"))
    with pytest.raises(ValueError, match="clean_keys needs encoders="):
        FreamerAuxLoss(modules.refiners, clean_keys={"grid": "grid_clean"})


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["model.flow.targets=denoised"], "model.flow.targets: expected one of synthetic, paired, got 'denoised'"),
        (["model.flow.targets=paired"], "model.flow.targets: paired needs env.clean_copies"),
        (["env.clean_copies=[grid]"], r"env.clean_copies: \['grid'\] are targets of model.flow.targets=paired"),
        (
            [*PAIRED, "model.flow.placement=post"],
            "model.flow.targets: paired .* needs model.flow.placement=pre",
        ),
        ([*PAIRED, "aux.lambda_fm=0"], "model.flow.targets: paired trains through the flow-matching loss"),
        (
            [*PAIRED[1:], "env.corrupt=[{key: grid, kind: salt, level: 0.5, when: eval}]"],
            "env.clean_copies: 'grid' is not corrupted during training",
        ),
        (
            [*PAIRED, "env.clean_copies=[grid, grid]"],
            r"env.clean_copies: a key is named twice in \['grid', 'grid'\]",
        ),
        (
            [*PAIRED, "env.clean_copies=[pixels]"],
            "env.clean_copies: the model reads no observation 'pixels'",
        ),
    ],
)
def test_paired_settings_the_run_cannot_honour_are_one_line(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_config(TINY, overrides)


def test_aux_loss_leaves_dropped_rows_out_of_the_pairs():
    cfg, modules, mb = _paired_minibatch()
    aux = FreamerAuxLoss(
        modules.refiners,
        clean_keys={"grid": "grid_clean"},
        encoders=modules.encoders,
        paired_modalities=["state"],
        presence_keys={"state": "grid_present"},
    )
    with set_recurrent_mode(True):
        mb = modules.trunk(mb)
    flags = torch.ones(*mb.batch_size, 1)
    assert aux(mb.set("grid_present", flags))["fm_left_state"].item() > 0.9
    # every grid dropped: neither the synthetic nor the paired term has a row to train on
    out = aux(mb.set("grid_present", torch.zeros_like(flags)))
    assert out["fm_left_state"].item() == 0.0 and out["fm_state"].item() == 0.0


def test_a_policy_reading_the_clean_copy_is_refused():
    recipe = ROOT / "recipes" / "baselines" / "ppo_mlp_n2s4.yaml"
    with pytest.raises(ConfigError, match="env.clean_copies: the model reads 'grid_clean'"):
        load_config(recipe, ["env.clean_copies=[grid]", "network.observation_keys=[grid_clean, direction]"])


def test_paired_runs_are_flagged_privileged():
    assert privileged_information(load_config(TINY, PAIRED)) == ["model.flow.targets=paired"]
    assert privileged_information(load_config(TINY)) == []


def test_a_paired_run_opens_the_state_gate_and_removes_corruption(tmp_path):
    # OGM-GE Mode A as a gate learning rate (x100, without its gradient noise): Adam moves a logit by ~lr a step
    gate_lr = ["ogm.mode=A", "ogm.lr_scale=100", "ogm.noise=false", "optim.lr=3e-3"]
    overrides = [*PAIRED, *gate_lr, "run.total_frames=1280"]
    cfg = load_config(TINY, overrides)
    summary = TRAINERS["minigrid_ppo"].train(cfg, tmp_path / "run")
    assert summary["privileged"] == ["model.flow.targets=paired"]
    with open(tmp_path / "run" / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    first, last = rows[0], rows[-1]
    init_gate = torch.sigmoid(torch.tensor(-3.0)).item()
    # the paired term drives the state gate (the language gate, trained by PPO alone, stays near its start)
    assert float(last["gate_state"]) > 0.5
    assert float(last["gate_state"]) - init_gate > 10 * abs(float(last["gate_language"]) - init_gate)
    assert float(first["fm_left_state"]) > 0.95
    assert float(last["fm_left_state"]) < 0.6
