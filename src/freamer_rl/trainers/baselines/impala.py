"""IMPALA through the project's run loop (``trainer: impala``): asynchronous actor processes, V-trace, A2C loss.

With ``collector.num_collectors >= 2`` the actors are TorchRL's ``MultiAsyncCollector`` workers
(:func:`freamer_rl.run.collection.make_collector` with ``sync=False``): each batch is one worker's ``[env.num_envs, T]``
(``T = impala.frames_per_batch / env.num_envs``), collected while the learner trains on the others' batches, so its
behaviour policy ``mu`` lags the learner's ``pi``. V-trace (Espeholt et al. 2018) corrects that lag: TorchRL's
:func:`torchrl.objectives.value.functional.vtrace_advantage_estimate` gives the targets ``v_s`` and the advantages
``rho_s (r_s + gamma v_{s+1} - V(x_s))`` from the stored behaviour log-probs (``action_log_prob``) and the current
policy's log-probs *of the stored actions*; TorchRL's ``A2CLoss`` then takes one gradient step (policy gradient on
that advantage, L2 value loss to ``v_s``, entropy bonus), as TorchRL's own IMPALA example does.

Why the functional and not the ``VTrace`` module: in torchrl 0.14.1 ``VTrace`` computes the current policy's
log-prob at a *fresh* action (``_call_actor_net`` samples under RANDOM exploration) or at the mode (the default),
never at the stored action; at the mode ``log pi >= log mu`` for every step, so the clipped ratios are always 1 and
the off-policy correction vanishes silently.

Progress columns: ``loss_objective``, ``loss_critic``, ``loss_entropy``, ``entropy``, ``grad_norm``, ``rho_mean``
(mean unclipped ratio pi/mu), ``rho_clipped`` (fraction of steps with rho > ``impala.rho_clip``) and ``policy_lag``
(mean number of batches the learner trained on between the weights that collected each frame and its current ones;
0 = on-policy; fractional because the actors take new weights mid-rollout).
The lag is measured by a version counter the actors' policy writes into every step (``policy_version``).

The ``shaping`` section works as the PPO baseline's (:class:`~freamer_rl.machinery.shaping.RewardShaper`: language
reward, novelty bonus, time penalty, adaptive decay; R_VL and curiosity are refused at load, there are no FreamerV1
embeddings): the learner writes ``("next", "shaped_reward")`` into each batch and V-trace reads it; returns and
success stay the env reward's. The novelty counts live in each actor process's env (one count table per worker).
``success_buffer.enabled`` is refused at load (:func:`~freamer_rl.trainers.baselines.config.validate_impala`):
the buffer's correction re-centres PPO's clipped ratio on sequences, which IMPALA's A2C step does not have.

    freamer-rl train recipes/baselines/impala_n2s4.yaml run.seed=1
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.objectives import A2CLoss
from torchrl.objectives.value.functional import vtrace_advantage_estimate

from freamer_rl.errors import CheckpointError
from freamer_rl.machinery.shaping import SHAPED_REWARD, RewardShaper, env_transforms
from freamer_rl.run.loop import resolve_run_dir
from freamer_rl.trainers.baselines.common import (
    STRUCTURAL,
    ActorCriticRunLoop,
    actor_critic_params,
    evaluate_actor_critic,
)
from freamer_rl.trainers.baselines.config import ImpalaConfig

__all__ = ["ImpalaConfig", "ImpalaTrainer", "PolicyVersion", "STRUCTURAL", "train", "evaluate", "params"]

VERSION_KEY = "policy_version"


class PolicyVersion(nn.Module):
    """``(action [*B, ...]) -> policy_version [*B]``: the number of batches learnt from by the weights acting now.

    Its ``version`` buffer travels with the policy's weights to the actor processes (``update_policy_weights_``),
    so every collected frame records which weights chose its action.
    """

    def __init__(self, event_dims: int) -> None:
        super().__init__()
        self.event_dims = event_dims
        self.register_buffer("version", torch.zeros((), dtype=torch.long))

    def forward(self, action: torch.Tensor) -> torch.Tensor:
        # a copy: a view of the buffer would be stored by reference and read the weights' version at the batch's end
        return self.version.expand(action.shape[: action.ndim - self.event_dims]).clone()


class ImpalaTrainer(ActorCriticRunLoop):
    """``ImpalaTrainer(cfg, run_dir).train()``: asynchronous collection, V-trace, ``A2CLoss``."""

    trainer_name = "impala"

    def __init__(self, cfg: ImpalaConfig, run_dir: str | Path, *, resume: bool = True) -> None:
        super().__init__(cfg, run_dir)
        p, s = cfg.optim, cfg.impala
        if s.optimizer == "rmsprop":
            self.optimizer = torch.optim.RMSprop(self.params, lr=p.lr, eps=p.eps, alpha=s.rmsprop_alpha)
        self.loss = A2CLoss(
            self.actor,
            self.critic,
            entropy_coeff=s.entropy_coeff,
            critic_coeff=s.critic_coeff,
            loss_critic_type="l2",
            functional=False,
        )
        self.value_op = self.net.get_value_operator()
        event_dims = len(self.actor.spec["action"].shape) if self.actor.spec is not None else 0
        self.stamp = TensorDictModule(PolicyVersion(event_dims), in_keys=["action"], out_keys=[VERSION_KEY])
        self.acting_policy = TensorDictSequential(self.net.get_policy_operator(), self.stamp)
        # the PPO baseline's shaping: V-trace then reads ("next", "shaped_reward"), success stays the env reward's
        self.shaper = RewardShaper(cfg, [], 0, 0, self.device, gamma=cfg.impala.gamma)
        self.reward_key = ("next", SHAPED_REWARD if self.shaper.active else "reward")
        self._start(resume)

    def _env_transforms(self) -> list:
        return [*env_transforms(self.cfg), *super()._env_transforms()]

    def _model_state(self) -> dict[str, Any]:
        return {**super()._model_state(), "shaping": self.shaper.state_dict()}

    @property
    def frames_per_batch(self) -> int:
        return self.cfg.impala.frames_per_batch

    def _policy(self) -> Any:
        return self.acting_policy

    def _collector_sync(self) -> bool:
        return False  # with several workers: MultiAsyncCollector, the actor-learner lag V-trace corrects

    def _load_model_state(self, ckpt: dict[str, Any], path: Path) -> None:
        saved = (ckpt["config"].get("impala") or {}).get("optimizer", "adam")
        if saved != self.cfg.impala.optimizer:  # Adam's moments are no RMSprop state: refused before loading
            raise CheckpointError(
                f"checkpoint {path} was trained with impala.optimizer={saved}, this config has "
                f"impala.optimizer={self.cfg.impala.optimizer}; resume with the same optimizer"
            )
        super()._load_model_state(ckpt, path)
        self.shaper.load_state_dict(ckpt.get("shaping", {}))

    def _after_open(self, ckpt_path: Path | None) -> None:
        super()._after_open(ckpt_path)
        self.stamp.module.version.fill_(self.batches)

    def vtrace(self, data: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """V-trace of one batch ``[*B, T]`` (time last) under the current weights, without gradients.

        Returns ``(advantage [*B, T, 1], value_target [*B, T, 1], rho [*B, T, 1])``, ``rho = pi(a|x) / mu(a|x)``
        unclipped (``mu``: the stored ``action_log_prob`` ``[*B, T]``). The reward is ``self.reward_key``: the
        shaped one when the ``shaping`` section turns a term on (written by :meth:`_learn` first), else the env's.
        """
        s = self.cfg.impala
        keys = list(self.cfg.network.observation_keys)
        with torch.no_grad():
            td = self.common(data.select(*keys).clone(False))
            log_pi = self.actor.get_dist(td).log_prob(data["action"]).unsqueeze(-1)
            value = self.critic(td)["state_value"]
            next_value = self.value_op(data["next"].select(*keys).clone(False))["state_value"]
            log_mu = data["action_log_prob"].unsqueeze(-1)
            nxt = data["next"]
            adv, target = vtrace_advantage_estimate(
                self.cfg.impala.gamma,
                log_pi,
                log_mu,
                value,
                next_value,
                data.get(self.reward_key),
                nxt["done"],
                nxt["terminated"],
                rho_thresh=s.rho_clip,
                c_thresh=s.c_clip,
                time_dim=-2,
            )
        return adv, target, (log_pi - log_mu).exp()

    def _learn(self, data: TensorDictBase) -> dict[str, float]:
        self._current_lr()
        shaping = self.shaper(data, self.stats.success_rate) if self.shaper.active else {}
        adv, target, rho = self.vtrace(data)
        # rho_clipped: ratios clipped by more than float noise (on-policy ratios are 1 +- 1e-6)
        clipped = rho > self.cfg.impala.rho_clip * (1 + 1e-4)
        diag = {"rho_mean": rho.mean(), "rho_clipped": clipped.float().mean()}
        if VERSION_KEY in data.keys():  # noqa: SIM118 (a TensorDict)
            diag["policy_lag"] = self.batches - data[VERSION_KEY].float().mean()
        flat = data.exclude("next").set("advantage", adv).set("value_target", target).reshape(-1)
        splits = torch.randperm(flat.numel(), device=flat.device).chunk(self.cfg.impala.minibatches)
        out = self._minibatch_steps(flat[idx] for idx in splits)
        self.stamp.module.version.fill_(self.batches + 1)  # the weights update_policy_weights_() sends next
        return {**shaping, **out, **{k: float(v) for k, v in diag.items()}}


def train(cfg: ImpalaConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    """Train the IMPALA baseline of the recipe; returns the summary (also ``summary.json``)."""
    return ImpalaTrainer(cfg, resolve_run_dir(cfg, run_dir), resume=resume).train()


def evaluate(path: Path, **options: Any) -> dict[str, Any]:
    return evaluate_actor_critic(path, ImpalaConfig, **options)


def params(cfg: ImpalaConfig) -> list[dict]:
    return actor_critic_params(cfg)
