"""Issue 12's training machinery inside the real trainer: reward shaping, the success buffer, OGM-GE, adaptive FM
steps -- each switched on from the recipe, trained for a few batches, checked in the data and the logs."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from freamer_rl.trainers.registry import load_config
from freamer_rl.errors import CheckpointError
from freamer_rl.machinery.reward_mixer import RewardMixer
from freamer_rl.run.sequences import split_sequences
from freamer_rl.machinery.shaping import potential_difference
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.run.checkpoint import latest_checkpoint

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
ALL_SHAPING = ["shaping.language.weight=0.2", "shaping.novelty.weight=0.1", "shaping.curiosity=0.2",
               "shaping.vision_language=0.1", "shaping.time_penalty=0.02", "shaping.adaptive=true"]  # fmt: skip


def _rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "progress.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_shaped_reward_is_the_mix_of_every_term_and_the_env_reward_is_kept(tmp_path):
    torch.manual_seed(0)
    cfg = load_config(TINY, ALL_SHAPING)
    trainer = Trainer(cfg, tmp_path / "run")
    data = trainer.collect_batch()
    env_reward = data["next", "reward"].clone()
    trainer.stats.recent_success.extend([1.0, 0.0, 0.0, 0.0])  # success rate 0.25: decay 1 - 1.25 * 0.25
    data = trainer.compute_advantage(data)
    assert torch.equal(data["next", "reward"], env_reward)  # success is judged on the env's own reward
    for key in ("lang_reward", "novelty_bonus", "vl_reward", "curiosity_reward"):
        assert data["next", key].shape == env_reward.shape, key
    decay = 1 - 1.25 * 0.25
    bonus = sum(w * data["next", k] for k, w in [("lang_reward", 0.2), ("novelty_bonus", 0.1), ("vl_reward", 0.1),
                                                  ("curiosity_reward", 0.2)])  # fmt: skip
    expected = env_reward + decay * bonus - 0.02 * (1 + 0.25)
    torch.testing.assert_close(data["next", "shaped_reward"], expected)
    assert trainer.gae.tensor_keys.reward == "shaped_reward"
    # R_VL is potential-based: gamma * cos(next) - cos(now), 0 potential after an episode's end
    sim = torch.nn.functional.cosine_similarity(data["refined", "state"], data["refined", "language"], dim=-1)
    torch.testing.assert_close(data["next", "vl_reward"],
                               potential_difference(sim.unsqueeze(-1), data["next", "done"], cfg.ppo.gamma))


def test_shaping_trains_logs_every_term_and_resumes_the_curiosity_model(tmp_path):
    cfg = load_config(TINY, ALL_SHAPING)
    Trainer(cfg, tmp_path / "run").train()
    row = _rows(tmp_path / "run")[-1]
    for col in ("bonus_lang", "bonus_novelty", "bonus_vl", "bonus_curiosity", "shaping_decay", "time_penalty",
                "loss_curiosity", "parser_hit_rate", "parser_fallbacks"):
        assert col in row and row[col] != "nan", col
    again = Trainer(load_config(TINY, [*ALL_SHAPING, "run.total_frames=384"]), tmp_path / "run")
    saved = torch.load(latest_checkpoint(tmp_path / "run"), weights_only=True)["shaping"]
    for k, v in again.shaper.curiosity.state_dict().items():
        assert torch.equal(v, saved["curiosity"][k]), k
    again.train()
    assert len(_rows(tmp_path / "run")) == 3


def test_no_shaping_leaves_ppo_on_the_env_reward(tmp_path):
    trainer = Trainer(load_config(TINY), tmp_path / "run")
    assert not trainer.shaper.active and trainer.gae.tensor_keys.reward == "reward"
    data = trainer.compute_advantage(trainer.collect_batch())
    assert "shaped_reward" not in data["next"].keys()


def test_mixer_matches_the_papers_time_penalty_example():
    assert RewardMixer.accumulated_time_penalty(0.05, 0.295, 145) == pytest.approx(9.39, abs=0.01)


def test_success_buffer_stores_successes_and_replays_them_with_weights(tmp_path):
    torch.manual_seed(0)
    cfg = load_config(TINY, ["success_buffer.enabled=true", "success_buffer.capacity=16", "run.total_frames=768"])
    trainer = Trainer(cfg, tmp_path / "run")
    trainer.train()
    sizes = [float(r["success_buffer_size"]) for r in _rows(tmp_path / "run")]
    assert sizes[-1] > 0 and max(sizes) <= 16  # Empty-5x5: a random policy reaches the goal now and then
    # a minibatch as _update builds it: on-policy sequences plus corrected replayed ones, weighted per step
    data = trainer.compute_advantage(trainer.collect_batch())
    seqs = split_sequences(data.exclude("next", *trainer.modules.trunk.out_keys), cfg.ppo.sequence_length)
    mb = trainer.replay.mix(seqs[:6])
    assert mb.shape[0] == 8  # 6 on-policy + 25% of the mixed minibatch
    w = mb["loss_weight"]
    assert torch.equal(w[:6], torch.ones_like(w[:6]))
    assert bool((w[6:] >= 0).all()) and bool((w[6:] <= cfg.success_buffer.rho_clip).all()) and bool(w[6:].any())
    row = _rows(tmp_path / "run")[-1]
    assert all(torch.isfinite(torch.tensor(float(row[k]))) for k in ("loss_objective", "loss_critic", "loss_total"))


@pytest.mark.parametrize("mode", ["A", "B"])
def test_ogm_groups_coefficients_logs_and_resume(tmp_path, mode):
    cfg = load_config(TINY, [f"ogm.mode={mode}"])
    trainer = Trainer(cfg, tmp_path / "run")
    names = [g.get("name") for g in trainer.optimizer.param_groups]
    assert names[:3] == ["ogm_state", "ogm_language", "ogm_reward"] and names[-1] == "base"
    gate_group = trainer.optimizer.param_groups[0]
    if mode == "A":
        assert gate_group["params"] == [trainer.modules.refiners["state"].alpha]
        assert gate_group["lr"] == pytest.approx(cfg.optim.lr * 10)
    else:
        assert len(gate_group["params"]) == len(list(trainer.modules.refiners["state"].parameters()))
    trainer.train()
    row = _rows(tmp_path / "run")[-1]
    coeffs = {m: float(row[f"ogm_coeff_{m}"]) for m in ("state", "language", "reward")}
    assert all(0 < k <= 1 for k in coeffs.values())
    saved = torch.load(latest_checkpoint(tmp_path / "run"), weights_only=True)["ogm"]
    assert saved == trainer.ogm.state_dict() and saved["steps"] > 0
    with pytest.raises(CheckpointError, match="ogm.mode"):  # its optimiser state has other parameter groups
        Trainer(load_config(TINY, ["ogm.mode=none", "run.total_frames=512"]), tmp_path / "run")
    again = Trainer(load_config(TINY, [f"ogm.mode={mode}", "run.total_frames=384"]), tmp_path / "run")
    assert again.ogm.state_dict() == saved
    again.train()
    assert len(_rows(tmp_path / "run")) == 3


def test_adaptive_steps_are_logged_within_the_choices(tmp_path):
    Trainer(load_config(TINY, ["model.flow.adaptive_steps=[1,2,3,5,7,10]"]), tmp_path / "run").train()
    row = _rows(tmp_path / "run")[-1]
    for m in ("state", "language", "reward"):
        assert 1 <= float(row[f"fm_steps_{m}"]) <= 10


def test_checkpoints_from_before_adaptive_steps_still_resume(tmp_path):
    """A checkpoint whose config predates model.flow.adaptive_steps / adaptive_tau (trained with them off) resumes
    and transfers; one that really differs is still refused."""
    Trainer(load_config(TINY), tmp_path / "run").train()
    path = latest_checkpoint(tmp_path / "run")
    ckpt = torch.load(path, weights_only=True)
    del ckpt["config"]["model"]["flow"]["adaptive_steps"], ckpt["config"]["model"]["flow"]["adaptive_tau"]
    torch.save(ckpt, path)
    Trainer(load_config(TINY, ["run.total_frames=384"]), tmp_path / "run").train()
    assert len(_rows(tmp_path / "run")) == 3
    Trainer(load_config(TINY, [f"run.init_from={path}"]), tmp_path / "child").life.lock.release()
    with pytest.raises(CheckpointError, match="adaptive_steps"):
        Trainer(load_config(TINY, ["model.flow.adaptive_steps=[1,2]", "run.total_frames=512"]), tmp_path / "run")
