"""What the actor-critic baselines (PPO-MLP / PPO-CNN, IMPALA) share: their network, optimiser, checkpoint entries,
evaluator and parameter table, on top of :class:`freamer_rl.run.loop.RunLoop`."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from torchrl.modules import ActorValueOperator, LSTMModule, set_recurrent_mode

from freamer_rl.errors import CheckpointError
from freamer_rl.machinery.checks import privileged_information
from freamer_rl.machinery.success_buffer import LOSS_WEIGHT_KEY, SuccessReplay, weighted_ppo_loss
from freamer_rl.run.corruption import corruption_transforms
from freamer_rl.run.envs import probe_specs
from freamer_rl.run.evaluation import read_checkpoint_config, run_episodes
from freamer_rl.run.loop import RunLoop
from freamer_rl.run.metrics import LogMeans
from freamer_rl.run.optim import StepStats, optimizer_step, restore_optimizer, scheduled_lr, set_lr
from freamer_rl.run.params import parameter_rows
from freamer_rl.trainers.baselines.networks import ObservationEncoder, build_actor_critic, recurrent_primers

#: what shapes a baseline's weights: the env and the ``network`` section (the registry entries')
STRUCTURAL = ("env", "network")

logger = logging.getLogger(__name__)

__all__ = ["ActorCriticRunLoop", "build_network", "evaluate_actor_critic", "actor_critic_params"]


def build_network(cfg: Any) -> ActorValueOperator:
    """The recipe's ``network`` for the env's specs (probed from one env)."""
    obs_spec, act_spec = probe_specs(cfg)
    return build_actor_critic(obs_spec, act_spec, cfg.network)


class ActorCriticRunLoop(RunLoop):
    """A RunLoop around one ``ActorValueOperator`` trained by the ``optim`` section's Adam; subclasses add
    ``_learn``."""

    structural = STRUCTURAL
    transfer_sections = ("network",)  # run.init_from: the weights of a run with the same network section

    def __init__(self, cfg: Any, run_dir: str | Path) -> None:
        super().__init__(cfg, run_dir)
        self.net = build_network(cfg).to(self.device)
        self.common = self.net.module[0]
        self.actor = self.net.get_policy_head()
        self.critic = self.net.get_value_head()
        self.params = [p for p in self.net.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.optim.lr, eps=cfg.optim.eps)
        self.step_stats = StepStats(type(self).__name__)
        #: the success buffer (App. G.3) a PPO subclass sets; None: every minibatch is the collected one
        self.replay: SuccessReplay | None = None

    def _policy(self) -> Any:
        return self.net.get_policy_operator()

    def _primers(self) -> list:
        return recurrent_primers(self.net)  # the *_lstm kinds' state; none for the feed-forward kinds

    def _env_transforms(self) -> list:
        return corruption_transforms(self.cfg.env.corrupt, "train")

    def _current_lr(self) -> float:
        """``optim.lr`` after its schedule, set on the optimiser."""
        lr = scheduled_lr(self.cfg.optim, self.frames, self.cfg.run.total_frames)
        set_lr(self.optimizer, lr)
        return lr

    def _minibatch_steps(self, minibatches) -> dict[str, float]:
        """One shared optimiser step per minibatch (the trunk, then ``self.loss`` on the heads); mean detached logs.

        ``minibatches``: TensorDicts ``[N]`` (or ``[N, L]`` whole sequences for a recurrent trunk, which then runs
        in recurrent mode as the loss's own forward does) holding the observations, ``action``,
        ``action_log_prob``, ``advantage`` and ``value_target`` (and ``is_init`` plus the stored LSTM state).
        With ``self.replay`` (``[N, L]`` sequences and a loss built with ``reduction="none"``), each minibatch gets
        its share of corrected replayed sequences (:meth:`SuccessReplay.mix`) and the per-step losses are reduced
        with their ``"loss_weight"`` (:func:`weighted_ppo_loss`).
        """
        means = LogMeans()
        for mb in minibatches:
            if self.replay is not None:
                mb = self.replay.mix(mb)
            with set_recurrent_mode(True):  # a feed-forward trunk ignores it
                mb = self.common(mb)
            loss_td = self.loss(mb)
            if self.replay is not None:  # per-step losses weighted by the truncated importance weights
                loss_td = weighted_ppo_loss(loss_td, mb[LOSS_WEIGHT_KEY])
            total = loss_td["loss_objective"] + loss_td["loss_critic"] + loss_td["loss_entropy"]
            grad_norm = optimizer_step(
                total, self.optimizer, self.params, self.cfg.optim.max_grad_norm, self.step_stats, foreach=True
            )  # non-finite: skipped, counted
            means.add(
                {"loss_total": total, "grad_norm": grad_norm, **{k: v for k, v in loss_td.items() if v.numel() == 1}}
            )
        return means.means()

    def _model_state(self) -> dict[str, Any]:
        return {
            "model": self.net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "steps": self.step_stats.state_dict(),
        }

    def _load_weights(self, state: dict[str, Any], path: Path) -> None:
        try:
            self.net.load_state_dict(state)
        except RuntimeError as err:
            raise CheckpointError(
                f"checkpoint {path}: weights do not fit this network: {str(err).splitlines()[0][:200]}"
            ) from err

    def _load_model_state(self, ckpt: dict[str, Any], path: Path) -> None:
        self._load_weights(ckpt["model"], path)
        restore_optimizer(
            self.optimizer, ckpt["optimizer"], self.cfg.optim, int(ckpt["frames"]), self.cfg.run.total_frames
        )
        self.step_stats.load_state_dict(ckpt["steps"])

    def _extra_row(self) -> dict[str, Any]:
        return {"skipped_steps": self.step_stats.skipped}

    def _extra_summary(self) -> dict[str, Any]:
        return {"skipped_steps": self.step_stats.skipped}

    def _privileged_information(self) -> list[str]:
        return privileged_information(self.cfg)


def evaluate_actor_critic(path: Path, schema: type, **options: Any) -> dict[str, Any]:
    """Episodes with a baseline checkpoint's policy (``options`` as :func:`freamer_rl.run.evaluation.run_episodes`)."""
    ckpt, cfg = read_checkpoint_config(path, schema)
    torch.set_num_threads(cfg.run.threads)
    net = build_network(cfg)
    try:
        net.load_state_dict(ckpt["model"])
    except RuntimeError as err:
        raise CheckpointError(f"checkpoint {path}: weights do not fit the network of its own config") from err
    net.eval()
    result = run_episodes(cfg, net.get_policy_operator(), recurrent_primers(net), **options)
    return {"checkpoint": str(path), **result, "frames_trained": ckpt.get("frames")}


def actor_critic_params(cfg: Any) -> list[dict]:
    """Parameter rows: encoder(s), LSTM(s) (``*_lstm`` kinds), actor head, critic head, Total."""
    net = build_network(cfg)
    heads = {"actor head": net.get_policy_head(), "critic head": net.get_value_head()}
    lstms = [m for m in net.modules() if isinstance(m, LSTMModule)]
    if not lstms:
        return parameter_rows({"encoder": net.module[0], **heads})
    encoders = [m for m in net.modules() if isinstance(m, ObservationEncoder)]
    return parameter_rows({"encoder": encoders, "lstm": lstms, **heads}, rest=net)
