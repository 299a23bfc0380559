"""TorchRL PPO baselines through the project's run loop: PPO-MLP (MiniGrid's symbolic grid, FlatObs-style) and
PPO-CNN (Crafter pixels), chosen by the recipe's ``network`` section (``trainer: ppo_baseline``).

The learning is what a TorchRL user writes from TorchRL's PPO tutorial: ``GAE`` over the batch, then ``epochs`` passes
of shuffled minibatches of single steps through ``ClipPPOLoss``; the network is feed-forward, so steps need no
sequence layout. The ``ppo`` section's values apply (lr, clip, entropy, GAE, minibatch, epochs, grad-norm clip);
``ppo.sequence_length`` and the FreamerV1-only losses do not. ``model.modalities`` only decides what the env renders
(``vision`` in it: MiniGrid pixels).

    freamer-rl train recipes/baselines/ppo_mlp_n2s4.yaml run.seed=1
    freamer-rl train recipes/baselines/ppo_cnn_crafter.yaml
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.objectives.value import GAE

from freamer_rl.run.loop import resolve_run_dir
from freamer_rl.trainers.baselines.common import (
    STRUCTURAL,
    ActorCriticRunLoop,
    actor_critic_params,
    evaluate_actor_critic,
)
from freamer_rl.trainers.baselines.config import PPOBaselineConfig
from freamer_rl.trainers.ppo_loss import clip_ppo_loss

__all__ = ["PPOBaselineConfig", "PPOBaselineTrainer", "STRUCTURAL", "train", "evaluate", "params"]


class PPOBaselineTrainer(ActorCriticRunLoop):
    """``PPOBaselineTrainer(cfg, run_dir).train()``: collect, GAE, ClipPPOLoss on shuffled single-step minibatches."""

    trainer_name = "ppo_baseline"

    def __init__(self, cfg: PPOBaselineConfig, run_dir: str | Path, *, resume: bool = True) -> None:
        super().__init__(cfg, run_dir)
        p = cfg.ppo
        self.loss = clip_ppo_loss(self.actor, self.critic, p)
        self.gae = GAE(
            gamma=p.gamma, lmbda=p.gae_lambda, value_network=self.net.get_value_operator(), average_gae=False
        )
        self._start(resume)

    @property
    def frames_per_batch(self) -> int:
        return self.cfg.ppo.frames_per_batch

    def _learn(self, data: TensorDictBase) -> dict[str, float]:
        p = self.cfg.ppo
        self._current_lr()
        with torch.no_grad():
            data = self.gae(data)
        flat = data.exclude("next").reshape(-1)
        epochs = (torch.randperm(flat.numel(), device=flat.device).split(p.minibatch_size) for _ in range(p.epochs))
        return self._minibatch_steps(flat[idx] for epoch in epochs for idx in epoch)


def train(cfg: PPOBaselineConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    """Train the PPO baseline of the recipe; returns the summary (also ``summary.json``)."""
    return PPOBaselineTrainer(cfg, resolve_run_dir(cfg, run_dir), resume=resume).train()


def evaluate(path: Path, **options: Any) -> dict[str, Any]:
    return evaluate_actor_critic(path, PPOBaselineConfig, **options)


def params(cfg: PPOBaselineConfig) -> list[dict]:
    return actor_critic_params(cfg)
