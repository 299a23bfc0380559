"""TorchRL PPO baselines through the project's run loop: PPO-MLP (MiniGrid's symbolic grid, FlatObs-style) and
PPO-CNN (Crafter pixels), chosen by the recipe's ``network`` section (``trainer: ppo_baseline``).

The learning is what a TorchRL user writes from TorchRL's PPO tutorial: ``GAE`` over the batch, then ``epochs`` passes
of shuffled minibatches of single steps through ``ClipPPOLoss``; a feed-forward network (``network.kind`` mlp / cnn)
needs no sequence layout. The recurrent kinds (``mlp_lstm`` / ``cnn_lstm``: TorchRL's ``LSTMModule``, the
memory-matched baseline of FreamerV1's DNC) follow TorchRL's recurrent pattern instead: GAE runs the value network in
recurrent mode over the ``[envs, T]`` batch from the LSTM states stored while collecting, then the minibatches are
whole ``ppo.sequence_length`` sequences (:func:`sequence_minibatches`, shuffled as sequences) that the LSTM runs in
recurrent mode from the stored state at ``t = 0``, reset wherever ``is_init``. The ``ppo`` section's values apply
(lr, clip, entropy, GAE, minibatch, epochs, grad-norm clip, and ``sequence_length`` for the recurrent kinds); the
FreamerV1-only losses do not. MiniGrid renders ``pixels`` only when ``network.observation_keys`` reads them. The
``shaping`` section works as FreamerV1's (:class:`~freamer_rl.machinery.shaping.RewardShaper`: language reward,
novelty bonus, time penalty, adaptive decay), so a comparison can give both sides the same shaping.

The ``success_buffer`` section works as FreamerV1's too (paper App. G.3,
:class:`~freamer_rl.machinery.success_buffer.SuccessReplay` on the network's ``common`` / actor / critic parts):
after the epochs on a batch, the ``ppo.sequence_length`` sequences holding steps of episodes that ended in success
(judged on the env reward by the adapter's rule) go into a FIFO; every minibatch then gets ``success_buffer.mix`` of
its sequences from it, corrected for the current policy (V-trace targets, PPO's ratio re-centred on ``pi_k``, each
step weighted by ``min(rho_clip, pi_k / mu)``), and ClipPPOLoss runs with ``reduction="none"`` reduced by those
weights. With the buffer on, the feed-forward kinds train on the recurrent kinds' layout too: shuffled
``[n, ppo.sequence_length]`` sequences instead of single steps, because V-trace needs each replayed step's successor
value ``V(s_{t+1})``, which a sequence holds at ``t + 1`` (storing single steps would mean storing and re-encoding
every next observation). The epochs still see every collected step once each. As FreamerV1's, the buffer is not in
the checkpoint: a resumed run refills it from its next successes. With the buffer off nothing changes (single-step
minibatches for mlp / cnn, the same numbers).

    freamer-rl train recipes/baselines/ppo_mlp_n2s4.yaml run.seed=1
    freamer-rl train recipes/baselines/ppo_lstm_n2s4.yaml run.seed=1
    freamer-rl train recipes/baselines/ppo_cnn_crafter.yaml
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.modules import set_recurrent_mode
from torchrl.objectives.value import GAE

from freamer_rl.machinery.shaping import SHAPED_REWARD, RewardShaper, env_transforms
from freamer_rl.machinery.success_buffer import ReplayModules, SuccessReplay
from freamer_rl.run.loop import resolve_run_dir
from freamer_rl.run.sequences import split_sequences
from freamer_rl.trainers.baselines.common import (
    STRUCTURAL,
    ActorCriticRunLoop,
    actor_critic_params,
    evaluate_actor_critic,
)
from freamer_rl.trainers.baselines.config import PPOBaselineConfig
from freamer_rl.trainers.baselines.networks import is_recurrent
from freamer_rl.trainers.ppo_loss import clip_ppo_loss

__all__ = [
    "PPOBaselineConfig",
    "PPOBaselineTrainer",
    "STRUCTURAL",
    "sequence_minibatches",
    "train",
    "evaluate",
    "params",
]


def sequence_minibatches(
    data: TensorDictBase, sequence_length: int, minibatch_size: int, epochs: int
) -> Iterator[TensorDictBase]:
    """``epochs`` passes over the collected batch ``[*lead, T]`` cut into ``[n, sequence_length]`` whole
    sequences (:func:`~freamer_rl.run.sequences.split_sequences`; ``n = minibatch_size // sequence_length``),
    shuffled as sequences, never as steps: each pass holds every step exactly once, in time order within its row.
    The ``"next"`` entries are left out (GAE is done)."""
    seqs = split_sequences(data.exclude("next"), sequence_length)
    per_minibatch = max(1, minibatch_size // sequence_length)
    for _ in range(epochs):
        for idx in torch.randperm(seqs.shape[0], device=seqs.device).split(per_minibatch):
            yield seqs[idx]


class PPOBaselineTrainer(ActorCriticRunLoop):
    """``PPOBaselineTrainer(cfg, run_dir).train()``: collect, GAE, ClipPPOLoss on shuffled single-step minibatches
    (feed-forward kinds) or on shuffled ``[n, ppo.sequence_length]`` sequences (``*_lstm`` kinds, and every kind
    with ``success_buffer.enabled``, whose replayed sequences are mixed into each minibatch)."""

    trainer_name = "ppo_baseline"

    def __init__(self, cfg: PPOBaselineConfig, run_dir: str | Path, *, resume: bool = True) -> None:
        super().__init__(cfg, run_dir)
        p = cfg.ppo
        # per-step losses with the success buffer, weighted by its truncated importance weights (App. G.3)
        self.loss = clip_ppo_loss(self.actor, self.critic, p, reduction="none" if cfg.success_buffer.enabled else None)
        self.recurrent = is_recurrent(self.net)
        # recurrent: GAE runs the value network in recurrent mode over the [*B, T] batch (root and "next" in turn,
        # not under vmap), each row from its stored LSTM state at t = 0 and split wherever is_init starts an episode
        extra = {"deactivate_vmap": True} if self.recurrent else {}
        self.gae = GAE(
            gamma=p.gamma, lmbda=p.gae_lambda, value_network=self.net.get_value_operator(), average_gae=False, **extra
        )
        # the shaping FreamerV1 gets (language reward, novelty, time penalty, adaptive decay): GAE then reads
        # ("next", "shaped_reward"); the env reward, and success judged on it, stay as they are
        self.shaper = RewardShaper(cfg, [], 0, 0, self.device, gamma=p.gamma)
        if self.shaper.active:
            self.gae.set_keys(reward=SHAPED_REWARD)
        # App. G.3, as FreamerV1's (None when off); it replays the reward GAE reads, shaped or not
        parts = ReplayModules(self.common, self.actor, self.critic)
        self.replay = SuccessReplay.from_config(cfg, parts, self.device, ("next", self.gae.tensor_keys.reward))
        self._start(resume)

    def _env_transforms(self) -> list:
        return [*env_transforms(self.cfg), *super()._env_transforms()]

    def _model_state(self) -> dict[str, Any]:
        return {**super()._model_state(), "shaping": self.shaper.state_dict()}

    def _load_model_state(self, ckpt: dict[str, Any], path: Path) -> None:
        super()._load_model_state(ckpt, path)
        self.shaper.load_state_dict(ckpt.get("shaping", {}))

    @property
    def frames_per_batch(self) -> int:
        return self.cfg.ppo.frames_per_batch

    def _learn(self, data: TensorDictBase) -> dict[str, float]:
        p = self.cfg.ppo
        self._current_lr()
        shaping = self.shaper(data, self.stats.success_rate) if self.shaper.active else {}
        with torch.no_grad(), set_recurrent_mode(self.recurrent):
            data = self.gae(data)
        if self.recurrent or self.replay is not None:  # replayed steps need their successors: sequences
            minibatches = sequence_minibatches(data, p.sequence_length, p.minibatch_size, p.epochs)
        else:
            flat = data.exclude("next").reshape(-1)
            epochs = (torch.randperm(flat.numel(), device=flat.device).split(p.minibatch_size) for _ in range(p.epochs))
            minibatches = (flat[idx] for epoch in epochs for idx in epoch)
        out = {**shaping, **self._minibatch_steps(minibatches)}
        if self.replay is not None:  # after the epochs: a batch's own successes are replayed from the next
            out["success_buffer_size"] = float(self.replay.store(data))
        return out


def train(cfg: PPOBaselineConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    """Train the PPO baseline of the recipe; returns the summary (also ``summary.json``)."""
    return PPOBaselineTrainer(cfg, resolve_run_dir(cfg, run_dir), resume=resume).train()


def evaluate(path: Path, **options: Any) -> dict[str, Any]:
    return evaluate_actor_critic(path, PPOBaselineConfig, **options)


def params(cfg: PPOBaselineConfig) -> list[dict]:
    return actor_critic_params(cfg)
