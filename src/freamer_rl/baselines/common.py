"""What the actor-critic baselines (PPO-MLP / PPO-CNN, IMPALA) share: their network, optimiser, checkpoint entries,
evaluator and parameter table, on top of :class:`freamer_rl.runloop.RunLoop`."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from torchrl.modules import ActorValueOperator

from freamer_rl.baselines.networks import build_actor_critic
from freamer_rl.errors import CheckpointError
from freamer_rl.optim import StepStats, optimizer_step
from freamer_rl.runloop import RunLoop

logger = logging.getLogger(__name__)

__all__ = ["ActorCriticRunLoop", "build_network", "evaluate_actor_critic", "actor_critic_params"]


def build_network(cfg: Any) -> ActorValueOperator:
    """The recipe's ``network`` for the env's specs (probed from one env)."""
    from freamer_rl.train import probe_specs  # noqa: PLC0415 (train builds FreamerV1; keep this import light)

    obs_spec, act_spec = probe_specs(cfg)
    return build_actor_critic(obs_spec, act_spec, cfg.network)


class ActorCriticRunLoop(RunLoop):
    """A RunLoop around one ``ActorValueOperator`` trained by Adam (``ppo.lr``, ``ppo.adam_eps``); subclasses add
    ``_learn``."""

    def __init__(self, cfg: Any, run_dir: str | Path) -> None:
        super().__init__(cfg, run_dir)
        self.net = build_network(cfg).to(self.device)
        self.common = self.net.module[0]
        self.actor = self.net.get_policy_head()
        self.critic = self.net.get_value_head()
        self.params = [p for p in self.net.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.ppo.lr, eps=cfg.ppo.adam_eps)
        self.step_stats = StepStats(type(self).__name__)

    def _policy(self) -> Any:
        return self.net.get_policy_operator()

    def _current_lr(self) -> float:
        """``ppo.lr``, decayed linearly to 0 at ``run.total_frames`` with ``ppo.lr_schedule: linear``."""
        p = self.cfg.ppo
        if p.lr_schedule != "linear":
            return p.lr
        lr = p.lr * max(1.0 - self.frames / self.cfg.run.total_frames, 0.0)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        return lr

    def _minibatch_steps(self, minibatches) -> dict[str, float]:
        """One shared optimiser step per minibatch (the trunk, then ``self.loss`` on the heads); mean detached logs.

        ``minibatches``: TensorDicts ``[N]`` holding the observations, ``action``, ``action_log_prob``,
        ``advantage`` and ``value_target``.
        """
        sums: dict[str, float] = {}
        count = 0
        for mb in minibatches:
            loss_td = self.loss(self.common(mb))
            total = loss_td["loss_objective"] + loss_td["loss_critic"] + loss_td["loss_entropy"]
            grad_norm = optimizer_step(total, self.optimizer, self.params, self.cfg.ppo.max_grad_norm,
                                       self.step_stats, foreach=True)  # non-finite: skipped, counted
            logs = {"loss_total": total.detach(), "grad_norm": grad_norm,
                    **{k: v.detach() for k, v in loss_td.items() if v.numel() == 1}}  # fmt: skip
            for k, v in logs.items():
                sums[k] = sums.get(k, 0.0) + float(v)
            count += 1
        return {k: v / max(count, 1) for k, v in sums.items()}

    def _model_state(self) -> dict[str, Any]:
        return {"model": self.net.state_dict(), "optimizer": self.optimizer.state_dict(),
                "steps": self.step_stats.state_dict()}  # fmt: skip

    def _load_model_state(self, ckpt: dict[str, Any], path: Path) -> None:
        try:
            self.net.load_state_dict(ckpt["model"])
        except RuntimeError as err:
            raise CheckpointError(f"checkpoint {path}: weights do not fit this network: "
                                  f"{str(err).splitlines()[0][:200]}") from err  # fmt: skip
        self.optimizer.load_state_dict(ckpt["optimizer"])
        for group in self.optimizer.param_groups:  # the moments are kept; the config sets lr / eps
            group["lr"], group["eps"] = self.cfg.ppo.lr, self.cfg.ppo.adam_eps
        self.step_stats.load_state_dict(ckpt["steps"])

    def _extra_row(self) -> dict[str, Any]:
        return {"skipped_steps": self.step_stats.skipped}

    def _extra_summary(self) -> dict[str, Any]:
        return {"skipped_steps": self.step_stats.skipped}


def evaluate_actor_critic(path: Path, schema: type, **options: Any) -> dict[str, Any]:
    """Episodes with a baseline checkpoint's policy (``options`` as :func:`freamer_rl.evaluate.run_episodes`)."""
    from freamer_rl.evaluate import read_checkpoint_config, run_episodes  # noqa: PLC0415

    ckpt, cfg = read_checkpoint_config(path, schema)
    torch.set_num_threads(cfg.run.threads)
    net = build_network(cfg)
    try:
        net.load_state_dict(ckpt["model"])
    except RuntimeError as err:
        raise CheckpointError(f"checkpoint {path}: weights do not fit the network of its own config") from err
    net.eval()
    result = run_episodes(cfg, net.get_policy_operator(), [], **options)
    return {"checkpoint": str(path), **result, "frames_trained": ckpt.get("frames")}


def actor_critic_params(cfg: Any) -> list[dict]:
    """Parameter rows: encoder(s), actor head, critic head, Total."""
    net = build_network(cfg)
    parts = {"encoder": net.module[0], "actor head": net.get_policy_head(), "critic head": net.get_value_head()}
    rows = [{"component": name, "trainable": sum(p.numel() for p in m.parameters() if p.requires_grad),
             "frozen": sum(p.numel() for p in m.parameters() if not p.requires_grad)} for name, m in parts.items()]
    rows.append({"component": "Total", "trainable": sum(r["trainable"] for r in rows),
                 "frozen": sum(r["frozen"] for r in rows)})  # fmt: skip
    return rows
