"""The one optimiser step: a non-finite gradient is skipped (weights and Adam state unchanged), counted and logged."""

import logging

import pytest
import torch

from freamer_rl.run.optim import StepStats, optimizer_step


def _setup():
    torch.manual_seed(0)
    lin = torch.nn.Linear(3, 1)
    opt = torch.optim.Adam(lin.parameters(), lr=0.1)
    return lin, opt


def test_finite_gradient_steps_and_clips():
    lin, opt = _setup()
    before = [p.detach().clone() for p in lin.parameters()]
    stats = StepStats("test")
    loss = (lin(torch.ones(4, 3)) * 100.0).sum()
    gn = optimizer_step(loss, opt, lin.parameters(), max_grad_norm=1.0, stats=stats)
    assert torch.isfinite(gn) and float(gn) > 1.0  # the norm before clipping is returned
    assert stats.steps == 1 and stats.skipped == 0
    assert any(not torch.equal(b, p) for b, p in zip(before, lin.parameters()))
    assert all(p.grad is None for p in lin.parameters())


def test_nan_gradient_is_skipped_counted_and_logged(caplog):
    lin, opt = _setup()
    stats = StepStats("test")
    optimizer_step(lin(torch.ones(2, 3)).sum(), opt, lin.parameters(), 1.0, stats)  # one good step: Adam has state
    weights = [p.detach().clone() for p in lin.parameters()]
    adam = {k: v.clone() for k, v in opt.state[lin.weight].items()}
    with caplog.at_level(logging.WARNING, logger="freamer_rl.run.optim"):
        gn = optimizer_step(lin(torch.ones(2, 3)).sum() * float("nan"), opt, lin.parameters(), 1.0, stats)
        gn2 = optimizer_step(lin(torch.ones(2, 3)).sum() * float("inf"), opt, lin.parameters(), None, stats)
    assert not torch.isfinite(gn) and not torch.isfinite(gn2)
    assert stats.steps == 3 and stats.skipped == 2
    assert all(torch.equal(w, p) for w, p in zip(weights, lin.parameters()))
    assert all(torch.equal(adam[k], v) for k, v in opt.state[lin.weight].items())
    assert all(p.grad is None for p in lin.parameters())
    warnings = [r for r in caplog.records if "update skipped" in r.getMessage()]
    assert len(warnings) == 1  # rate-limited: the second skip within the window is counted, not logged again
    assert "test" in warnings[0].getMessage()
    # a finite step afterwards trains again
    optimizer_step(lin(torch.ones(2, 3)).sum(), opt, lin.parameters(), 1.0, stats)
    assert any(not torch.equal(w, p) for w, p in zip(weights, lin.parameters()))
    assert stats.state_dict() == {"steps": 4, "skipped": 2}


def test_minigrid_trainer_counts_skipped_steps(tmp_path, monkeypatch):
    """The trainer's optimiser step goes through optimizer_step: a NaN loss is skipped, counted in progress.csv and
    kept in the checkpoint."""
    import csv
    from pathlib import Path

    from freamer_rl.trainers.minigrid_ppo import Trainer
    from freamer_rl.trainers.registry import load_config

    tiny = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"
    trainer = Trainer(load_config(tiny, ["logging.progress_bar=false"]), tmp_path / "run")
    real = trainer.aux_loss.forward

    def nan_fm(td):
        out = real(td)
        out["loss_fm"] = out["loss_fm"] * float("nan")
        return out

    monkeypatch.setattr(trainer.aux_loss, "forward", nan_fm)
    before = [p.detach().clone() for p in trainer.params]
    summary = trainer.train()
    assert summary["skipped_steps"] == trainer.step_stats.steps > 0
    assert all(torch.equal(a, b.detach()) for a, b in zip(before, trainer.params))  # no step was taken
    rows = list(csv.DictReader((tmp_path / "run" / "progress.csv").open()))
    assert int(rows[-1]["skipped_steps"]) == summary["skipped_steps"]


def test_resume_takes_lr_and_eps_from_the_config(tmp_path):
    from pathlib import Path

    from freamer_rl.trainers.minigrid_ppo import Trainer
    from freamer_rl.trainers.registry import load_config

    tiny = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"
    Trainer(load_config(tiny, ["logging.progress_bar=false", "optim.lr=1e-3"]), tmp_path / "run").train()
    resumed = Trainer(
        load_config(tiny, ["logging.progress_bar=false", "optim.lr=2e-4", "optim.eps=1e-6", "run.total_frames=512"]),
        tmp_path / "run",
    )
    assert resumed.frames > 0
    assert all(g["lr"] == 2e-4 and g["eps"] == 1e-6 for g in resumed.optimizer.param_groups)


def test_linear_lr_schedule_follows_the_frames(tmp_path):
    from pathlib import Path

    from freamer_rl.trainers.minigrid_ppo import Trainer
    from freamer_rl.trainers.registry import load_config

    tiny = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"
    cfg = load_config(tiny, ["logging.progress_bar=false", "optim.lr=1e-3", "optim.lr_schedule=linear"])
    trainer = Trainer(cfg, tmp_path / "run")
    trainer.train()  # 2 batches of 128 frames out of 256: the second trains at lr * (1 - 128 / 256)
    assert trainer.optimizer.param_groups[0]["lr"] == pytest.approx(5e-4)
