"""Issue 12's training machinery inside the real trainer: reward shaping, the success buffer, OGM-GE, adaptive FM
steps -- each switched on from the recipe, trained for a few batches, checked in the data and the logs."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import pytest
import torch

from freamer_rl.errors import CheckpointError
from freamer_rl.machinery.reward_mixer import RewardMixer
from freamer_rl.machinery.shaping import potential_difference
from freamer_rl.run.checkpoint import latest_checkpoint
from freamer_rl.run.sequences import split_sequences
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
ALL_SHAPING = [
    "shaping.language.weight=0.2",
    "shaping.novelty.weight=0.1",
    "shaping.curiosity=0.2",
    "shaping.vision_language=0.1",
    "shaping.time_penalty=0.02",
    "shaping.adaptive=true",
]


def _rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "progress.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def shaped(tmp_path_factory):
    """One tiny batch with every shaping term on, before and after the trainer's advantage step."""
    torch.manual_seed(0)
    cfg = load_config(TINY, ALL_SHAPING)
    trainer = Trainer(cfg, tmp_path_factory.mktemp("shaped") / "run")
    data = trainer.collect_batch()
    env_reward = data["next", "reward"].clone()
    trainer.stats.recent_success.extend([1.0, 0.0, 0.0, 0.0])  # success rate 0.25: decay 1 - 1.25 * 0.25
    data = trainer.compute_advantage(data)
    yield cfg, trainer, env_reward, data
    trainer.life.lock.release()


def test_shaping_keeps_the_env_reward_and_trains_on_the_shaped_one(shaped):
    _, trainer, env_reward, data = shaped
    assert torch.equal(data["next", "reward"], env_reward)  # success is judged on the env's own reward
    assert trainer.gae.tensor_keys.reward == "shaped_reward"


def test_shaped_reward_is_the_mix_of_every_term(shaped):
    _, _, env_reward, data = shaped
    for key in ("lang_reward", "novelty_bonus", "vl_reward", "curiosity_reward"):
        assert data["next", key].shape == env_reward.shape, key
    decay = 1 - 1.25 * 0.25
    bonus = sum(
        w * data["next", k]
        for k, w in [("lang_reward", 0.2), ("novelty_bonus", 0.1), ("vl_reward", 0.1), ("curiosity_reward", 0.2)]
    )
    expected = env_reward + decay * bonus - 0.02 * (1 + 0.25)
    torch.testing.assert_close(data["next", "shaped_reward"], expected)


def test_vision_language_reward_is_potential_based(shaped):
    """R_VL = gamma * cos(next) - cos(now), with 0 potential after an episode's end."""
    cfg, _, _, data = shaped
    sim = torch.nn.functional.cosine_similarity(data["refined", "state"], data["refined", "language"], dim=-1)
    torch.testing.assert_close(
        data["next", "vl_reward"], potential_difference(sim.unsqueeze(-1), data["next", "done"], cfg.ppo.gamma)
    )


@pytest.fixture(scope="module")
def shaped_run(tmp_path_factory):
    """A trained tiny run with every shaping term on; tests that train further copy its run directory."""
    run_dir = tmp_path_factory.mktemp("shaped_run") / "run"
    Trainer(load_config(TINY, ALL_SHAPING), run_dir).train()
    return run_dir


def test_shaping_logs_every_term(shaped_run):
    row = _rows(shaped_run)[-1]
    for col in (
        "bonus_lang",
        "bonus_novelty",
        "bonus_vl",
        "bonus_curiosity",
        "shaping_decay",
        "time_penalty",
        "loss_curiosity",
        "parser_hit_rate",
        "parser_fallbacks",
    ):
        assert col in row and row[col] != "nan", col


def test_shaping_resumes_the_curiosity_model(shaped_run, tmp_path):
    shutil.copytree(shaped_run, tmp_path / "run")
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
    trainer.life.lock.release()


def test_mixer_matches_the_papers_time_penalty_example():
    assert RewardMixer.accumulated_time_penalty(0.05, 0.295, 145) == pytest.approx(9.39, abs=0.01)


@pytest.fixture(scope="module")
def success_run(tmp_path_factory):
    """A tiny run with the success buffer on (capacity 16), trained for 6 batches."""
    torch.manual_seed(0)
    cfg = load_config(TINY, ["success_buffer.enabled=true", "success_buffer.capacity=16", "run.total_frames=768"])
    run_dir = tmp_path_factory.mktemp("success") / "run"
    trainer = Trainer(cfg, run_dir)
    trainer.train()
    return cfg, trainer, _rows(run_dir)


def test_success_buffer_fills_up_to_its_capacity(success_run):
    _, trainer, rows = success_run
    sizes = [int(float(r["success_buffer_size"])) for r in rows]
    assert sizes[-1] == len(trainer.replay.buffer) > 0  # Empty-5x5: a random policy reaches the goal now and then
    assert max(sizes) <= 16


def test_success_replay_minibatch_is_weighted_per_step(success_run):
    """A minibatch as the PPO epochs build it: on-policy sequences (weight 1) plus corrected replayed ones."""
    cfg, trainer, _ = success_run
    data = trainer.compute_advantage(trainer.collect_batch())
    seqs = split_sequences(data.exclude("next", *trainer.modules.trunk.out_keys), cfg.ppo.sequence_length)
    mb = trainer.replay.mix(seqs[:6])
    assert mb.shape[0] == 8  # 6 on-policy + 25% of the mixed minibatch
    w = mb["loss_weight"]
    assert torch.equal(w[:6], torch.ones_like(w[:6]))
    assert bool((w[6:] <= cfg.success_buffer.rho_clip).all()) and bool(w[6:].any())


def test_success_replay_losses_are_logged(success_run):
    _, _, rows = success_run
    for k in ("loss_objective", "loss_critic", "loss_total"):
        assert all(torch.isfinite(torch.tensor(float(r[k]))) for r in rows), k


@pytest.mark.parametrize("mode", ["A", "B"])
def test_ogm_parameter_groups(tmp_path, mode):
    """A group per modality's gate (Mode A, lr * lr_scale) or whole refiner (Mode B), then the rest."""
    cfg = load_config(TINY, [f"ogm.mode={mode}"])
    trainer = Trainer(cfg, tmp_path / "run")
    trainer.life.lock.release()
    names = [g.get("name") for g in trainer.optimizer.param_groups]
    assert names[:3] == ["ogm_state", "ogm_language", "ogm_reward"] and names[-1] == "base"
    gate_group = trainer.optimizer.param_groups[0]
    if mode == "A":
        assert gate_group["params"] == [trainer.modules.refiners["state"].alpha]
        assert gate_group["lr"] == pytest.approx(cfg.optim.lr * 10)
    else:
        assert len(gate_group["params"]) == len(list(trainer.modules.refiners["state"].parameters()))


@pytest.fixture(scope="module", params=["A", "B"])
def ogm_run(request, tmp_path_factory):
    """A trained tiny run with OGM-GE in ``mode``; tests that train further copy its run directory."""
    mode = request.param
    run_dir = tmp_path_factory.mktemp(f"ogm_{mode}") / "run"
    trainer = Trainer(load_config(TINY, [f"ogm.mode={mode}"]), run_dir)
    trainer.train()
    return mode, trainer, run_dir


def test_ogm_coefficients_are_logged_and_checkpointed(ogm_run):
    _, trainer, run_dir = ogm_run
    row = _rows(run_dir)[-1]
    for m, k in trainer.ogm.coefficients().items():
        assert float(row[f"ogm_coeff_{m}"]) == pytest.approx(k, rel=1e-5), m
    saved = torch.load(latest_checkpoint(run_dir), weights_only=True)["ogm"]
    assert saved == trainer.ogm.state_dict()
    cfg = trainer.cfg
    assert saved["steps"] == 2 * cfg.ppo.epochs * (cfg.ppo.frames_per_batch // cfg.ppo.minibatch_size)  # one a step


def test_ogm_resume_refuses_another_mode(ogm_run):
    _, _, run_dir = ogm_run
    with pytest.raises(CheckpointError, match="ogm.mode"):  # its optimiser state has other parameter groups
        Trainer(load_config(TINY, ["ogm.mode=none", "run.total_frames=512"]), run_dir)


def test_ogm_resumes_its_state(ogm_run, tmp_path):
    mode, _, run_dir = ogm_run
    shutil.copytree(run_dir, tmp_path / "run")
    saved = torch.load(latest_checkpoint(run_dir), weights_only=True)["ogm"]
    again = Trainer(load_config(TINY, [f"ogm.mode={mode}", "run.total_frames=384"]), tmp_path / "run")
    assert again.ogm.state_dict() == saved
    again.train()
    assert len(_rows(tmp_path / "run")) == 3


def test_adaptive_steps_logged_are_the_refiners_own(tmp_path):
    """The fm_steps_<m> column is the refiner's mean chosen step count of its last forward."""
    trainer = Trainer(load_config(TINY, ["model.flow.adaptive_steps=[1,2,3,5,7,10]"]), tmp_path / "run")
    trainer.train()
    row = _rows(tmp_path / "run")[-1]
    for m in ("state", "language", "reward"):
        assert float(row[f"fm_steps_{m}"]) == pytest.approx(float(trainer.modules.refiners[m].last_steps)), m
        assert float(row[f"fm_steps_{m}"]) == 2.0  # eval-mode trunk, barely trained: the choice nearest flow.steps


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
