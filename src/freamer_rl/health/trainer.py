"""Health-domain training run: real-env collection -> RSSM world model -> imagination PPO, repeated, then real-env
evaluation (paper Section 5, Appendix J). ``freamer-rl train recipes/health/health_mlp.yaml``.

One :class:`HealthTrainer` owns one run directory through the lifecycle every trainer shares
(:class:`~freamer_rl.run.lifecycle.RunLifecycle`: the same layout as a MiniGrid run) and collects with
``freamer_rl.run.collection.make_collector``::

    <run_dir>/config.yaml           resolved config (``trainer: health`` first: a recipe again)
    <run_dir>/run_info.json         git commit, versions, command, resumed_from
    <run_dir>/progress.csv          one row per iteration (row 0: the random prefill)
    <run_dir>/metrics/attempt_NN/   the TorchRL logger's files (``logging.backend``) with the hyperparameters
    <run_dir>/checkpoints/          the newest 3 resume checkpoints (after every iteration) + ``latest``
    <run_dir>/learning_curve.png    training and evaluation return vs frames (``plot_learning_curve``)
    <run_dir>/summary.json          final figures, with "action_ranking": imagined vs real return per held action
                                    from evaluation states (freamer_rl.health.oracle.action_ranking), and the
                                    reference policies' returns on the same episodes (eval.references: the oracle
                                    planner, the heart-rate rule, always-Continue) with the run's fraction of them
    <run_dir>/checkpoint.pt         the final agent (world model + actor + value + config; ``load_agent``)

Loop (``collect.iterations`` times, after ``collect.prefill_frames`` frames of random actions drawn from
``collect.explore_probs``, uniform when null)::

    1. collect collect.frames_per_iter real-env frames with a TorchRL Collector and the current policy
       (HealthPolicy; with probability collect.random_action_prob a random action) -> replay buffer
       (LazyTensorStorage + SliceSampler over ("collector", "traj_ids"))
    2. world_model.train_steps steps of Eq. A27 on [batch_size, seq_len] slices,
       + lambda_FM * L_FM + lambda_s * L_smooth for the foundation encoder (Table A20: lambda_FM(WM) = 0.1;
       FreamerAuxLoss on the tensordict its trunk wrote)
    3. imagination.updates ImaginationPPO updates (ClipPPOLoss + GAE on horizon-15 imagined rollouts seeded with
       posterior latents of replayed slices)

Resume: a rerun on the same directory continues after the last finished iteration from the latest checkpoint
(weights, both optimisers, the replay buffer, the progress rows and the torch RNG); the env restarts with fresh
episodes (seeded from the frame count), as a MiniGrid run's does. ``resume=False`` refuses a directory that
already holds checkpoints (nothing is deleted).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler
from torchrl.objectives import LossModule

from freamer_rl.config.checks import run_name_problem
from freamer_rl.config.sections import CollectorConfig, OptimConfig
from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.health.agent import CHECKPOINT_FORMAT, build_agent, make_health_env, parameter_table, save_agent
from freamer_rl.health.config import HealthConfig, health_config_to_dict
from freamer_rl.health.evaluation import (
    STORE_KEYS,
    corruption_for,
    episode_stats,
    eval_subjects,
    evaluate_agent,
    make_eval_env,
)
from freamer_rl.health.oracle import action_ranking
from freamer_rl.health.reference import ACTION_NAMES, reference_summary
from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint
from freamer_rl.run.collection import make_collector
from freamer_rl.run.corruption import load_corruption_state
from freamer_rl.run.lifecycle import RunLifecycle
from freamer_rl.run.metrics import LogMeans, ProgressReporter, format_duration, format_rate
from freamer_rl.run.optim import StepStats, optimizer_step, restore_optimizer
from freamer_rl.run.rundir import surfaced_interrupts
from freamer_rl.world_model.imagination import ImaginationPPO, RSSMWorldModelEnv
from freamer_rl.world_model.metrics import seed_latents
from freamer_rl.world_model.rssm import WorldModel
from freamer_rl.world_model.training import as_sequences

logger = logging.getLogger(__name__)

__all__ = ["HealthTrainer", "run_health", "default_run_dir", "train_world_model_step", "HEALTH_RETURNS"]

TRAINER_NAME = "health"
TRAINER_LABEL = "RSSM world model + imagination PPO"
#: the learning curve's return series: training episodes finished in each iteration, and real-env evaluation
HEALTH_RETURNS = (("train_return", "training episodes (per iteration)"), ("eval_return_mean", "evaluation"))
#: one local collector: the health env is one batched env in this process (make_collector's default section)
_COLLECTOR = CollectorConfig()


def train_world_model_step(
    world_model: WorldModel,
    batch: TensorDictBase,
    optimizer: torch.optim.Optimizer,
    *,
    lambda_fm: float = 0.1,
    lambda_smooth: float = 1e-3,
    grad_clip: float | None = 1.0,
    stats: StepStats | None = None,
    aux_loss: LossModule | None = None,
) -> dict[str, float]:
    """One gradient step of Eq. A27 on a ``[N, T]`` slice plus the encoder's auxiliary losses through
    :func:`~freamer_rl.run.optim.optimizer_step`.

    The auxiliary loss is ``aux_loss``, else the encoder's ``make_aux_loss(lambda_fm=, lambda_smooth=)`` (foundation:
    :class:`~freamer_rl.model.losses.FreamerAuxLoss`, ``loss_fm`` and ``loss_smooth`` already weighted; ``None`` for the
    others); :meth:`WorldModel.loss` runs it on the tensordict the encoder wrote for this slice. Returns float metrics
    (``total`` includes the auxiliary terms; ``grad_norm``; ``skipped`` = 1.0 for a non-finite gradient, whose update
    is skipped and counted in ``stats``)."""
    world_model.train()
    if aux_loss is None:
        aux_loss = world_model.encoder.make_aux_loss(lambda_fm=lambda_fm, lambda_smooth=lambda_smooth)
    losses = world_model.loss(batch, aux_loss=aux_loss)
    total = losses["total"]
    params = [p for g in optimizer.param_groups for p in g["params"]]
    gn = optimizer_step(total, optimizer, params, grad_clip, stats)
    out = {k: float(v.detach()) for k, v in losses.items()}
    out["grad_norm"] = float(gn)
    out["skipped"] = float(not torch.isfinite(gn))
    return out


def default_run_dir(cfg: HealthConfig) -> Path:
    name = cfg.run.name or f"health-{cfg.encoder.kind}-s{cfg.run.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    if problem := run_name_problem(name):
        raise ConfigError(f"run.name: {problem}")
    return Path(cfg.run.output_dir) / name


class HealthTrainer:
    """Collect -> world model -> imagination PPO on the health env; ``HealthTrainer(cfg, run_dir, structural=...)``
    then ``.train()``. ``structural``: the config sections that shape the weights (the registry entry's,
    :data:`freamer_rl.trainers.health.STRUCTURAL`). Holds the run directory's lock from construction until
    :meth:`train` returns (see the module docstring)."""

    def __init__(
        self, cfg: HealthConfig, run_dir: str | Path, *, resume: bool = True, structural: Sequence[str]
    ) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.life = RunLifecycle(
            self.run_dir,
            trainer_name=TRAINER_NAME,
            config=health_config_to_dict(cfg),
            read_checkpoint=functools.partial(read_checkpoint, fmt=CHECKPOINT_FORMAT),
            structural=tuple(structural),
            defaults=health_config_to_dict(HealthConfig()),
            title=f"health ({cfg.encoder.kind} encoder) -- {TRAINER_LABEL}, seed {cfg.run.seed}",
            curve={"returns": HEALTH_RETURNS, "return_label": "episode return"},
        )
        ckpt = self.life.open(resume, "delete it yourself (resume is the default: drop --no-resume to continue it)")
        try:
            self._build(0 if ckpt is None else int(ckpt.get("frames", 0)), ckpt)
            if ckpt is not None:
                self._resume(ckpt)
            self.life.write_run_files()
        except BaseException:
            self.life.lock.release()
            raise

    @property
    def rows(self) -> list[dict[str, Any]]:
        return self.life.rows

    @property
    def resumed_from(self) -> Path | None:
        return self.life.resumed_from

    # -- construction -------------------------------------------------------------------------------------------------
    def _build(self, frames: int, ckpt: dict[str, Any] | None = None) -> None:
        """Everything in the order of the original single-function pipeline (same random streams when fresh); a
        resume checkpoint ``ckpt`` restores the training corruptions' running statistics before the env is built."""
        cfg = self.cfg
        torch.set_num_threads(cfg.run.threads)
        torch.manual_seed(cfg.run.seed)
        np.random.seed(cfg.run.seed)
        self.agent = build_agent(cfg)
        wc, ic, cc = cfg.world_model, cfg.imagination, cfg.collect
        self.policy = self.agent.policy(sample_latent=True, random_actions=True, explore_probs=cc.explore_probs)
        # a resumed run does not replay the episodes of the first attempt
        env_seed = cfg.run.seed if frames == 0 else cfg.run.seed * 10_000 + frames
        # env.corrupt entries of the training phase, checked against the keys the world model reads
        self.train_corruption = corruption_for(self.agent, cfg.env.corrupt, phase="train")
        if ckpt is not None:
            try:
                load_corruption_state(self.train_corruption, ckpt.get("corruption"), str(self.run_dir / "checkpoints"))
            except (KeyError, TypeError, ValueError) as err:
                raise CheckpointError(f"checkpoint in {self.run_dir}: {err}") from err
        env_fn = functools.partial(
            make_health_env,
            cfg,
            seed=env_seed,
            primer=self.policy.make_tensordict_primer(),
            corrupt=self.train_corruption,
        )
        self.collector = make_collector(
            _COLLECTOR, [env_fn], self.policy, frames_per_batch=cc.frames_per_iter, total_frames=-1, devices={}
        )
        self._batches = iter(self.collector)
        self.rb = ReplayBuffer(
            storage=LazyTensorStorage(cc.buffer_capacity),
            sampler=SliceSampler(slice_len=wc.seq_len, traj_key=("collector", "traj_ids"), strict_length=True),
            batch_size=wc.batch_size * wc.seq_len,
        )
        wm = self.agent.world_model
        self.wm_opt = torch.optim.Adam(wm.parameters(), lr=wc.lr, eps=wc.adam_eps)
        self.wm_stats = StepStats("health world model")
        self.algo = ImaginationPPO(
            RSSMWorldModelEnv(wm, done_mode=ic.done_mode, uncertainty_penalty=ic.uncertainty_penalty),
            self.agent.actor,
            self.agent.value,
            horizon=ic.horizon,
            gamma=ic.gamma,
            lmbda=ic.lmbda,
            clip_epsilon=ic.clip_epsilon,
            epochs=ic.epochs,
            num_minibatches=ic.num_minibatches,
            entropy_coeff=ic.entropy_coeff,
            critic_coeff=ic.critic_coeff,
            lr=ic.lr,
            adam_eps=ic.adam_eps,
            max_grad_norm=ic.max_grad_norm,
            lambda_return_actor_critic=ic.lambda_return_actor_critic,
            return_norm=ic.return_norm,
        )
        self.action_counts = torch.zeros(wm.action_dim)  # actions in the replay buffer (collect.balance_actions)
        self.frames = 0
        self.iteration = 0  # loop iterations finished
        self.prefilled = False
        self._traj_offset = 0  # added to the collector's trajectory ids after a resume (they restart at 0)

    # -- checkpoints --------------------------------------------------------------------------------------------------
    def _payload(self) -> dict[str, Any]:
        """The health entries of a resume checkpoint (the lifecycle adds rows, wall time, RNG and trainer)."""
        replay = self.rb[:] if len(self.rb) else None
        return {
            **self.agent.state_dict(),  # format, config, world_model, actor, value: load_agent reads these
            "wm_optimizer": self.wm_opt.state_dict(),
            "ppo_optimizer": self.algo.optimizer.state_dict(),
            "wm_steps": self.wm_stats.state_dict(),
            "ppo_steps": self.algo.step_stats.state_dict(),
            "replay": None if replay is None else replay.flatten_keys("/").to_dict(),
            "frames": self.frames,
            "iteration": self.iteration,
            "prefilled": self.prefilled,
            "return_scale": None if self.algo.return_scale is None else self.algo.return_scale.state_dict(),
            # the training corruptions' running std (the collector's env holds these very transforms)
            "corruption": [t.stats_state() for t in self.train_corruption],
        }

    def _resume(self, ckpt: dict[str, Any]) -> None:
        wc, ic = self.cfg.world_model, self.cfg.imagination
        with self.life.restoring(ckpt):
            self.agent.world_model.load_state_dict(ckpt["world_model"])
            self.agent.actor.load_state_dict(ckpt["actor"])
            self.agent.value.load_state_dict(ckpt["value"])
            # Adam's moments are kept, the current recipe sets lr and eps (as every trainer's resume)
            restore_optimizer(self.wm_opt, ckpt["wm_optimizer"], OptimConfig(lr=wc.lr, eps=wc.adam_eps), 0, 1)
            restore_optimizer(self.algo.optimizer, ckpt["ppo_optimizer"], OptimConfig(lr=ic.lr, eps=ic.adam_eps), 0, 1)
            self.wm_stats.load_state_dict(ckpt["wm_steps"])
            self.algo.step_stats.load_state_dict(ckpt["ppo_steps"])
            if ckpt["replay"] is not None:
                flat = ckpt["replay"]
                replay = TensorDict(flat, batch_size=[len(next(iter(flat.values())))]).unflatten_keys("/")
                self.rb.extend(replay)
                self._traj_offset = int(replay.get(("collector", "traj_ids")).max()) + 1
                self._count_actions(replay.get("action"))
            if self.algo.return_scale is not None and ckpt.get("return_scale") is not None:
                self.algo.return_scale.load_state_dict(ckpt["return_scale"])
            self.frames, self.iteration = int(ckpt["frames"]), int(ckpt["iteration"])
            self.prefilled = bool(ckpt["prefilled"])
        logger.info("resumed from %s after iteration %d (%d frames)", self.resumed_from, self.iteration, self.frames)

    # -- the loop -----------------------------------------------------------------------------------------------------
    def _collect(self) -> dict[str, float]:
        self.agent.world_model.eval()
        data = next(self._batches)
        self.frames += data.numel()
        stored = data.select(*STORE_KEYS).reshape(-1)
        if self._traj_offset:
            stored.set(("collector", "traj_ids"), stored.get(("collector", "traj_ids")) + self._traj_offset)
        self.rb.extend(stored)
        self._count_actions(stored.get("action"))
        return episode_stats(data)

    def _count_actions(self, action: torch.Tensor) -> None:
        """Add the stored actions to the counts; with ``collect.balance_actions`` the random actions are drawn with
        ``p(a) = (1 / (1 + n_a)) / sum_b 1 / (1 + n_b)`` from then on (a host-side count, outside any forward)."""
        n = self.action_counts.shape[0]
        self.action_counts += torch.bincount(action.reshape(-1).long(), minlength=n)[:n].float()
        if self.cfg.collect.balance_actions:
            inv = 1.0 / (1.0 + self.action_counts)
            self.policy.explore_probs = inv / inv.sum()

    def _sample(self) -> TensorDictBase:
        return as_sequences(self.rb.sample(), self.cfg.world_model.seq_len)

    def _train_world_model(self, steps: int) -> dict[str, float]:
        wc = self.cfg.world_model
        wm = self.agent.world_model
        aux = wm.encoder.make_aux_loss(lambda_fm=wc.lambda_fm, lambda_smooth=wc.lambda_smooth)
        means = LogMeans()
        for _ in range(steps):
            means.add(
                train_world_model_step(
                    wm, self._sample(), self.wm_opt, grad_clip=wc.grad_clip, stats=self.wm_stats, aux_loss=aux
                )
            )
        return means.means("wm_")

    def _train_policy(self) -> dict[str, float]:
        wm = self.agent.world_model
        wm.eval()
        ic = self.cfg.imagination
        means = LogMeans()
        for _ in range(ic.updates):
            means.add(self.algo.update(seed_latents(wm, self._sample(), ic.num_seeds)))
        return means.means("ppo_")

    def _prefill_batches(self) -> int:
        return math.ceil(self.cfg.collect.prefill_frames / self.cfg.collect.frames_per_iter)

    def _prefill(self) -> dict[str, Any] | None:
        """Random-action batches and the world model's prefill steps; their row (None without a prefill)."""
        wc = self.cfg.world_model
        stats = [self._collect() for _ in range(self._prefill_batches())]
        self.prefilled = True
        if not stats:
            return None
        ep = [s for s in stats if s["episodes"]]
        row: dict[str, Any] = {
            "iteration": 0,
            "frames": self.frames,
            "train_episodes": sum(s["episodes"] for s in ep),
            "train_return": float(np.mean([s["return"] for s in ep])) if ep else float("nan"),
        }
        row.update(self._train_world_model(wc.prefill_train_steps))
        row["wall_s"] = self.life.wall_time
        logger.info("prefill: %d random frames, %d world-model steps", self.frames, wc.prefill_train_steps)
        return row

    def _iterate(self, it: int) -> dict[str, Any]:
        stats = self._collect()
        row: dict[str, Any] = {
            "iteration": it,
            "frames": self.frames,
            "train_episodes": stats["episodes"],
            "train_return": stats["return"],
            "train_violations": stats["violations"],
        }
        row.update(self._train_world_model(self.cfg.world_model.train_steps))
        row.update(self._train_policy())
        row.update({f"gate_{m}": g for m, g in self.agent.world_model.encoder.gates.items()})
        row["wm_skipped_steps"] = self.wm_stats.skipped
        row["ppo_skipped_steps"] = self.algo.step_stats.skipped
        if self.cfg.eval.every and it % self.cfg.eval.every == 0 and it != self.cfg.collect.iterations:
            row.update({f"eval_{k}": v for k, v in evaluate_agent(self.agent).items()})
        row["wall_s"] = self.life.wall_time
        return row

    def train(self) -> dict[str, Any]:
        """Run the remaining iterations, evaluate, write the summary; returns it. Ctrl-C / SIGTERM stop after a
        warning naming the checkpoint of the last finished iteration (written after each one) and re-raise."""
        try:
            with self.life.guard():
                return self._train()
        finally:
            self.collector.shutdown()

    def _train(self) -> dict[str, Any]:
        cfg, cc = self.cfg, self.cfg.collect
        metrics = self.life.metrics_logger(cfg.logging.backend, option="logging.backend")
        total = (self._prefill_batches() + cc.iterations) * cc.frames_per_iter
        progress = ProgressReporter(
            total, self.frames, bar=cfg.logging.progress_bar, desc=f"health[{cfg.encoder.kind}]"
        )
        try:
            with surfaced_interrupts():  # an interrupt that a library turned into its own error
                if not self.prefilled:
                    row = self._prefill()
                    if row is not None:
                        self.life.log_row(row, metrics, self.frames)
                    self.life.checkpoint(self._payload())
                self.policy.random_actions = False
                self.policy.random_action_prob = cc.random_action_prob
                for it in range(self.iteration + 1, cc.iterations + 1):
                    before = self.frames
                    row = self._iterate(it)
                    self.iteration = it
                    self.life.log_row(row, metrics, self.frames)
                    self.life.checkpoint(self._payload())  # each iteration: a crash or a kill resumes from here
                    progress.update(
                        self.frames,
                        self.frames - before,
                        extra={
                            "iteration": f"{it}/{cc.iterations}",
                            "return": format_rate(row["train_return"], 1),
                            "rec": format_rate(row.get("wm_loss_rec", math.nan)),
                        },
                    )
                    self.life.check_terminated()
        except KeyboardInterrupt as err:
            self.life.stopping()
            self.life.interrupted(err, f"after iteration {self.iteration}", latest_checkpoint(self.run_dir))
            raise
        finally:
            progress.close()
        return self._finish(metrics)

    def _finish(self, metrics: Any) -> dict[str, Any]:
        final = {f"eval_{k}": v for k, v in evaluate_agent(self.agent).items()}
        # imagined vs real return per held action on the evaluation env (issue 22 part 2): summary "action_ranking"
        self._ranking = action_ranking(
            self.agent, functools.partial(make_eval_env, self.cfg), action_names=ACTION_NAMES
        )
        final["eval_action_rank_spearman"] = self._ranking["spearman_mean"]
        final["eval_action_rank_top1"] = self._ranking["top1_agreement"]
        # the oracle planner and the rules on the same episodes: the learned policy as a fraction of each (eval.references)
        final.update(reference_summary(self.cfg, self.cfg.eval.references, final["eval_return_mean"]))
        if self.rows:
            self.rows[-1].update(final)
            self.life.rewrite_progress()  # the last row gained the evaluation columns
            self.life.log_scalars(final, metrics, self.frames)
        self.life.checkpoint(self._payload())
        save_agent(self.agent, self.run_dir, iteration=self.iteration, frames=self.frames)
        summary = self.life.write_summary(self._summary(final))
        logger.info(
            "health run finished: %d frames | evaluation return %s | recon_mse %s | wall time %s | run dir %s",
            self.frames,
            format_rate(summary.get("eval_return_mean")),
            format_rate(summary.get("recon_mse"), 4),
            format_duration(summary["wall_time_s"]),
            self.run_dir,
        )
        return summary

    def _summary(self, final: dict[str, float]) -> dict[str, Any]:
        cfg = self.cfg
        table = {r["component"]: r["trainable"] + r["frozen"] for r in parameter_table(self.agent)}
        encoder, rssm, actor, value = (v for k, v in table.items() if k != "Total")
        wall = self.life.wall_time
        return {
            "env": cfg.env.id,
            "trainer": TRAINER_NAME,
            "algorithm": TRAINER_LABEL,
            "encoder": cfg.encoder.kind,
            "seed": cfg.run.seed,
            # the subjects trained on and evaluated on (leave-one-subject-out folds; None: the env's default set)
            "train_subjects": cfg.env.subjects,
            "eval_subjects": eval_subjects(cfg),
            "iterations": cfg.collect.iterations,
            "frames": self.frames,
            "wall_time_s": wall,  # from the trainer's start (model build included), all attempts
            "fps": self.frames / wall if wall > 0 else None,
            **{k: v for k, v in final.items() if not k.startswith(("eval_recon", "eval_imagination"))},
            **{k[5:]: v for k, v in final.items() if k.startswith(("eval_recon", "eval_imagination"))},
            "imagination_horizon_definition": {
                "context": cfg.eval.horizon_context,
                "max": cfg.eval.horizon_max,
                "reward_tol": cfg.eval.horizon_reward_tol,
                "windows": cfg.eval.horizon_windows,
            },
            "params_world_model": encoder + rssm,
            "params_encoder": encoder,
            "params_policy": actor + value,
            "gates": self.agent.world_model.encoder.gates or None,
            "action_ranking": self._ranking,
            "action_counts": [int(c) for c in self.action_counts],
            "wm_skipped_steps": self.wm_stats.skipped,
            "ppo_skipped_steps": self.algo.step_stats.skipped,
            "resumed_from": str(self.resumed_from) if self.resumed_from else None,
            "run_dir": str(self.run_dir),
        }


def run_health(
    cfg: HealthConfig, run_dir: str | Path | None = None, *, resume: bool = True, structural: Sequence[str]
) -> dict[str, Any]:
    """Train a health agent and evaluate it in the real env; returns the summary (also ``summary.json``).

    ``run_dir`` default: ``<run.output_dir>/<run.name or health-<kind>-s<seed>-<time>>``; ``structural``: the
    registry entry's weight-shaping sections (``freamer_rl.trainers.health.train`` passes them). Summary keys:
    ``eval_return_mean``/``_std``, ``eval_violations_mean``, ``eval_length_mean``, ``recon_mse`` (+ per key),
    ``imagination_horizon`` (+ ``_std``), ``frames``, ``wall_time_s``, ``fps``, parameter counts, FM gates.
    """
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir(cfg)
    return HealthTrainer(cfg, run_dir, resume=resume, structural=structural).train()
