"""Presence-aware fusion (issue 20 part 7): ``env.presence`` writes a ``<key>_present`` flag in every phase (0 where a
dropout corruption dropped the key), ``model.presence_keys`` zeroes the dropped modality's row of the fuser's input,
and the refiner's FM loss and score statistics leave the dropped rows out."""

from pathlib import Path

import pytest
import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import check_env_specs

from freamer_rl.config.sections import CorruptionConfig
from freamer_rl.errors import ConfigError, EnvSetupError
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fusion import PresenceMask
from freamer_rl.run.corruption import ModalityCorruption, PresenceFlag
from freamer_rl.run.envs import make_batched_env
from freamer_rl.trainers.minigrid_ppo import build_modules, evaluate, train
from freamer_rl.trainers.registry import load_config
from freamer_rl_envs.minigrid import make_minigrid_env

TINY = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"
BATCH_SHAPES = [(), (5,), (3, 4)]
PRESENCE = ["env.presence=[grid]", "model.presence_keys={state: grid_present}"]


def _env(*transforms):
    base = make_minigrid_env("MiniGrid-Empty-5x5-v0", include_mission=False)
    return TransformedEnv(base, Compose(InitTracker(), *transforms))


def test_the_flag_reads_one_without_a_dropout():
    env = _env(PresenceFlag("grid"))
    check_env_specs(env)
    td = env.rollout(5, break_when_any_done=False)
    assert td["grid_present"].shape == (5, 1) and (td["grid_present"] == 1).all()
    assert (td["next", "grid_present"] == 1).all()
    env.close()


def test_the_flag_follows_a_dropout_placed_before_it():
    torch.manual_seed(0)
    env = _env(ModalityCorruption("grid", "dropout", 0.5), PresenceFlag("grid"))
    check_env_specs(env)
    td = env.rollout(200, break_when_any_done=False)
    present = td["next", "grid_present"].reshape(-1)
    kept = td["next", "grid"].flatten(1).abs().sum(-1) > 0
    assert 0.35 < present.mean() < 0.65
    assert torch.equal(present.bool(), kept)


def test_a_flag_for_a_missing_key_is_one_line():
    with pytest.raises(ConfigError, match="env.presence: the env has no observation 'lidar'"):
        check_env_specs(_env(PresenceFlag("lidar")))


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_the_mask_zeroes_a_dropped_row(batch):
    e = torch.randn(*batch, 6)
    present = (torch.rand(*batch, 1) < 0.5).float()
    out = PresenceMask()(e, present)
    torch.testing.assert_close(out, torch.where(present.bool(), e, torch.zeros_like(e)))
    with pytest.raises(ValueError, match=r"the flag must be \[\*B, 1\]"):
        PresenceMask()(e, present.expand(*batch, 6))


@pytest.mark.parametrize("placement, source", [("pre", ("refined", "state")), ("off", ("embed", "state"))])
def test_a_dropped_modality_enters_the_fuser_as_zeros(placement, source):
    cfg = load_config(TINY, [*PRESENCE, f"model.flow.placement={placement}"])
    modules = build_modules(cfg)
    env = make_batched_env(cfg, modules.primers(), 0, num_envs=2)
    td = env.reset()
    env.close()
    td = td.expand(3, 2).clone()  # [3, 2]: one flag per row
    td["grid_present"] = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]).unsqueeze(-1)
    with torch.no_grad():
        out = modules.trunk(td)
    row = modules.modalities.index("state")
    stack = out["modal_stack"][..., row, :]
    dropped = td["grid_present"].squeeze(-1) == 0
    assert (stack[dropped] == 0).all()
    torch.testing.assert_close(stack[~dropped], out[source][~dropped])
    assert (out["modal_stack"][..., row + 1, :][dropped] != 0).any()  # the other rows are left alone


def test_dropped_rows_leave_the_fm_loss_and_the_score_statistics():
    torch.manual_seed(0)
    e = torch.randn(16, 8)
    mask = (torch.arange(16) % 3 != 0).float()
    other = torch.where(mask.bool().unsqueeze(-1), e, 100 * torch.randn(16, 8))  # differs only where dropped
    refs = [FlowMatchingRefiner(8, hidden=16, reliability="both") for _ in range(3)]
    for r in refs[1:]:
        r.load_state_dict(refs[0].state_dict())
    losses = []
    for r, x in zip(refs[:2], (e, other)):
        torch.manual_seed(1)
        losses.append(r.cfm_loss(x, mask=mask))
    torch.testing.assert_close(losses[0], losses[1])
    torch.testing.assert_close(refs[0].score_stats, refs[1].score_stats)
    refs[2].cfm_loss(e[mask.bool()])  # the statistics are those of the kept rows alone
    torch.testing.assert_close(refs[0].score_stats, refs[2].score_stats)
    before = refs[0].score_stats.clone()
    assert refs[0].cfm_loss(e, mask=torch.zeros(16)) == 0  # nothing kept: no loss, statistics as they were
    torch.testing.assert_close(refs[0].score_stats, before)


@pytest.mark.parametrize(
    "overrides, error, message",
    [
        (["model.presence_keys={lidar: grid_present}"], ConfigError, "model.presence_keys: 'lidar' is not one of"),
        (["env.presence=[grid, grid]"], ConfigError, "env.presence: a key is named twice"),
        (["model.presence_keys={state: grid_present}"], EnvSetupError, "model.presence_keys.state: .* no observation"),
        (["model.presence_keys={state: grid}"], EnvSetupError, r"'grid' has shape \(7, 7, 3\); a presence flag is"),
    ],
)
def test_bad_presence_settings_are_one_line(overrides, error, message):
    with pytest.raises(error, match=message):
        build_modules(load_config(TINY, overrides))


def test_trains_with_dropped_sensors_and_evaluates_under_salt(tmp_path):
    dropout = "env.corrupt=[{key: grid, kind: dropout, level: 0.5, when: train}]"
    cfg = load_config(TINY, [*PRESENCE, dropout, "model.flow.reliability=both", "run.total_frames=128"])
    summary = train(cfg, tmp_path / "run")
    assert summary["frames"] == 128
    ckpt = sorted((tmp_path / "run" / "checkpoints").glob("checkpoint_*.pt"))[-1]
    state = torch.load(ckpt, weights_only=True)["model"]
    counts = [float(v[0]) for k, v in state.items() if k.endswith("score_stats")]
    assert len(counts) == 3 and min(counts) > 0
    clean = evaluate(ckpt, episodes=2)  # no dropout at evaluation: the flag reads 1
    salted = evaluate(ckpt, episodes=2, corrupt=[CorruptionConfig("grid", "salt", 0.5, "eval")])
    assert clean["episodes"] == salted["episodes"] == 2
    assert 0 < salted["weight_state"] <= 1 and clean["weight_state"] > 0
