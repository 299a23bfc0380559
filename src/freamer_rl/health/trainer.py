"""Health-domain training run: real-env collection -> RSSM world model -> imagination PPO, repeated, then real-env
evaluation (paper Section 5, Appendix J). ``freamer-rl train recipes/health/health_mlp.yaml``.

One :class:`HealthTrainer` owns one run directory (the same layout as a MiniGrid run)::

    <run_dir>/config.yaml           resolved config (``trainer: health`` first: a recipe again)
    <run_dir>/run_info.json         git commit, versions, command, resumed_from
    <run_dir>/progress.csv          one row per iteration (row 0: the random prefill)
    <run_dir>/metrics/attempt_NN/   the TorchRL logger's files (``run.logger``) with the hyperparameters
    <run_dir>/checkpoints/          the newest 3 resume checkpoints (after every iteration) + ``latest``
    <run_dir>/learning_curve.png    training and evaluation return vs frames
    <run_dir>/summary.json          final figures
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

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler
from torchrl.objectives import LossModule

from freamer_rl.run.checkpoint import atomic_write_text, latest_checkpoint, read_checkpoint, resume_checkpoint
from freamer_rl.run.checkpoint import save_checkpoint
from freamer_rl.errors import ConfigError
from freamer_rl.errors import CheckpointError
from freamer_rl.health.agent import CHECKPOINT_FORMAT, build_agent, make_health_env, save_agent
from freamer_rl.health.config import HealthConfig, health_config_to_dict
from freamer_rl.health.evaluation import STORE_KEYS, episode_stats, evaluate_agent
from freamer_rl.run.optim import StepStats, optimizer_step
from freamer_rl.run.rundir import RunDirLock, Terminated, catch_sigterm, restore_sigterm
from freamer_rl.run.files import make_metrics_logger, write_run_files
from freamer_rl.config.checks import run_name_problem
from freamer_rl.run.rundir import write_rows_csv
from freamer_rl.world_model.imagination import ImaginationPPO, RSSMWorldModelEnv
from freamer_rl.world_model.metrics import seed_latents
from freamer_rl.world_model.rssm import WorldModel
from freamer_rl.world_model.training import as_sequences

logger = logging.getLogger(__name__)

__all__ = ["HealthTrainer", "run_health", "default_run_dir", "train_world_model_step", "plot_health_curve"]

TRAINER_NAME = "health"
# sections whose change makes a checkpoint's weights not fit (or mean something else)
_STRUCTURAL = ("env", "encoder", "world_model")


def train_world_model_step(
    world_model: WorldModel, batch: TensorDictBase, optimizer: torch.optim.Optimizer, *, lambda_fm: float = 0.1,
    lambda_smooth: float = 1e-3, grad_clip: float | None = 1.0, stats: StepStats | None = None,
    aux_loss: LossModule | None = None,
) -> dict[str, float]:  # fmt: skip
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


def plot_health_curve(rows: list[dict], path: Path, title: str = "") -> None:
    """Training-episode return and real-env evaluation return vs frames, one PNG (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for key, label, style in (("train_return", "training episodes", "-"), ("eval_return_mean", "evaluation", "o-")):
        pts = [(r["frames"], r[key]) for r in rows if isinstance(r.get(key), float) and math.isfinite(r[key])]
        if pts:
            ax.plot(*zip(*pts), style, label=label)
    ax.set_xlabel("frames")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    if ax.get_lines():
        ax.legend(loc="lower right")
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)


def _mean_rows(rows: list[dict[str, float]], prefix: str) -> dict[str, float]:
    if not rows:
        return {}
    keys = rows[0].keys()
    return {f"{prefix}{k}": float(np.mean([r[k] for r in rows if k in r])) for k in keys}


def _param_count(m: torch.nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def default_run_dir(cfg: HealthConfig) -> Path:
    name = cfg.run.name or f"health-{cfg.encoder.kind}-s{cfg.run.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    if problem := run_name_problem(name):
        raise ConfigError(f"run.name: {problem}")
    return Path(cfg.run.output_dir) / name


class HealthTrainer:
    """Collect -> world model -> imagination PPO on the health env; ``HealthTrainer(cfg, run_dir).train()``.

    Holds the run directory's lock from construction until :meth:`train` returns (see the module docstring).
    """

    def __init__(self, cfg: HealthConfig, run_dir: str | Path, *, resume: bool = True) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self._lock = RunDirLock(self.run_dir).acquire()
        try:
            resume_from = self._find_checkpoint(resume)
            self._build(self._frames_of(resume_from))
            if resume_from is not None:
                self._resume(resume_from)
        except BaseException:
            self._lock.release()
            raise

    # -- construction -------------------------------------------------------------------------------------------------
    def _find_checkpoint(self, resume: bool) -> Path | None:
        return resume_checkpoint(
            self.run_dir, resume, "delete it yourself (resume is the default: drop --no-resume to continue it)"
        )

    @staticmethod
    def _frames_of(path: Path | None) -> int:
        return 0 if path is None else int(read_checkpoint(path, fmt=CHECKPOINT_FORMAT).get("frames", 0))

    def _build(self, frames: int) -> None:
        """Everything in the order of the original single-function pipeline (same random streams when fresh)."""
        cfg = self.cfg
        torch.set_num_threads(cfg.run.threads)
        torch.manual_seed(cfg.run.seed)
        np.random.seed(cfg.run.seed)
        self.agent = build_agent(cfg)
        wc, ic, cc = cfg.world_model, cfg.imagination, cfg.collect
        self.policy = self.agent.policy(sample_latent=True, random_actions=True, explore_probs=cc.explore_probs)
        # a resumed run does not replay the episodes of the first attempt
        env_seed = cfg.run.seed if frames == 0 else cfg.run.seed * 10_000 + frames
        env = make_health_env(cfg, seed=env_seed, primer=self.policy.make_tensordict_primer())
        self.collector = Collector(env, self.policy, frames_per_batch=cc.frames_per_iter, total_frames=-1,
                                   auto_register_policy_transforms=False)  # fmt: skip
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
            RSSMWorldModelEnv(wm, done_mode=ic.done_mode), self.agent.actor, self.agent.value, horizon=ic.horizon,
            gamma=ic.gamma, lmbda=ic.lmbda, clip_epsilon=ic.clip_epsilon, epochs=ic.epochs,
            num_minibatches=ic.num_minibatches, entropy_coeff=ic.entropy_coeff, critic_coeff=ic.critic_coeff,
            lr=ic.lr, adam_eps=ic.adam_eps, max_grad_norm=ic.max_grad_norm,
            lambda_return_actor_critic=ic.lambda_return_actor_critic,
        )  # fmt: skip
        self.frames = 0
        self.iteration = 0  # loop iterations finished
        self.prefilled = False
        self.rows: list[dict[str, Any]] = []
        self.wall_time = 0.0
        self.resumed_from: Path | None = None
        self._traj_offset = 0  # added to the collector's trajectory ids after a resume (they restart at 0)

    # -- checkpoints --------------------------------------------------------------------------------------------------
    def _payload(self) -> dict[str, Any]:
        replay = self.rb[:] if len(self.rb) else None
        return {
            **self.agent.state_dict(),  # format, config, world_model, actor, value: load_agent reads these
            "trainer": TRAINER_NAME,
            "wm_optimizer": self.wm_opt.state_dict(),
            "ppo_optimizer": self.algo.optimizer.state_dict(),
            "wm_steps": self.wm_stats.state_dict(),
            "ppo_steps": self.algo.step_stats.state_dict(),
            "replay": None if replay is None else replay.flatten_keys("/").to_dict(),
            "frames": self.frames,
            "iteration": self.iteration,
            "prefilled": self.prefilled,
            "rows": self.rows,
            "wall_time": self.wall_time,
            "torch_rng": torch.get_rng_state(),
        }

    def _checkpoint(self) -> Path:
        path = save_checkpoint(self.run_dir, self._payload())  # atomic + rotated; see freamer_rl.run.checkpoint
        if self.rows:
            plot_health_curve(self.rows, self.run_dir / "learning_curve.png", title=self._title())
        return path

    def _check_structure(self, saved: dict, path: Path) -> None:
        current = health_config_to_dict(self.cfg)
        diff = [s for s in _STRUCTURAL if saved.get(s) != current.get(s)]
        if diff:
            raise CheckpointError(
                f"checkpoint {path} was written with other {', '.join(diff)} settings; resume with the same recipe "
                "or start a new run (another run.name / --run-dir)"
            )

    def _resume(self, path: Path) -> None:
        ckpt = read_checkpoint(path, fmt=CHECKPOINT_FORMAT)
        try:
            self._check_structure(ckpt["config"], path)
            self.agent.world_model.load_state_dict(ckpt["world_model"])
            self.agent.actor.load_state_dict(ckpt["actor"])
            self.agent.value.load_state_dict(ckpt["value"])
            self.wm_opt.load_state_dict(ckpt["wm_optimizer"])
            self.algo.optimizer.load_state_dict(ckpt["ppo_optimizer"])
            self.wm_stats.load_state_dict(ckpt["wm_steps"])
            self.algo.step_stats.load_state_dict(ckpt["ppo_steps"])
            if ckpt["replay"] is not None:
                flat = ckpt["replay"]
                replay = TensorDict(flat, batch_size=[len(next(iter(flat.values())))]).unflatten_keys("/")
                self.rb.extend(replay)
                self._traj_offset = int(replay.get(("collector", "traj_ids")).max()) + 1
            self.frames, self.iteration = int(ckpt["frames"]), int(ckpt["iteration"])
            self.prefilled = bool(ckpt["prefilled"])
            self.rows = [dict(r) for r in ckpt["rows"]]
            self.wall_time = float(ckpt["wall_time"])
            torch.set_rng_state(ckpt["torch_rng"])
        except CheckpointError:
            raise
        except (KeyError, TypeError, ValueError, RuntimeError) as err:  # a hand-edited, foreign or final-only file
            detail = f"missing entry {err}" if isinstance(err, KeyError) else str(err).splitlines()[0][:200]
            raise CheckpointError(f"health checkpoint {path} cannot be resumed from: {detail}") from err
        self.resumed_from = path
        logger.info("resumed from %s after iteration %d (%d frames)", path, self.iteration, self.frames)

    # -- run files ----------------------------------------------------------------------------------------------------
    def _title(self) -> str:
        return f"health, {self.cfg.encoder.kind} encoder, seed {self.cfg.run.seed}"

    def _write_run_files(self) -> None:
        write_run_files(self.run_dir, health_config_to_dict(self.cfg), self.resumed_from)

    def _make_logger(self):
        """The TorchRL logger of this attempt (``metrics/attempt_NN``) with the resolved config as hyperparameters."""
        return make_metrics_logger(self.run_dir, self.cfg.run.logger, health_config_to_dict(self.cfg),
                                   option="run.logger")

    def _log_row(self, metrics, row: dict[str, Any]) -> None:
        write_rows_csv(self.run_dir / "progress.csv", self.rows)
        for k, v in row.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                metrics.log_scalar(k, v, step=self.frames)

    # -- the loop -----------------------------------------------------------------------------------------------------
    def _collect(self) -> dict[str, float]:
        self.agent.world_model.eval()
        data = next(self._batches)
        self.frames += data.numel()
        stored = data.select(*STORE_KEYS).reshape(-1)
        if self._traj_offset:
            stored.set(("collector", "traj_ids"), stored.get(("collector", "traj_ids")) + self._traj_offset)
        self.rb.extend(stored)
        return episode_stats(data)

    def _sample(self) -> TensorDictBase:
        return as_sequences(self.rb.sample(), self.cfg.world_model.seq_len)

    def _train_world_model(self, steps: int) -> dict[str, float]:
        wc = self.cfg.world_model
        wm = self.agent.world_model
        aux = wm.encoder.make_aux_loss(lambda_fm=wc.lambda_fm, lambda_smooth=wc.lambda_smooth)
        hist = [train_world_model_step(wm, self._sample(), self.wm_opt, grad_clip=wc.grad_clip, stats=self.wm_stats,
                                       aux_loss=aux) for _ in range(steps)]  # fmt: skip
        return _mean_rows(hist, "wm_")

    def _train_policy(self) -> dict[str, float]:
        wm = self.agent.world_model
        wm.eval()
        ic = self.cfg.imagination
        hist = [self.algo.update(seed_latents(wm, self._sample(), ic.num_seeds)) for _ in range(ic.updates)]
        return _mean_rows(hist, "ppo_")

    def _prefill(self, t_start: float) -> None:
        cc, wc = self.cfg.collect, self.cfg.world_model
        n_prefill = math.ceil(cc.prefill_frames / cc.frames_per_iter)
        stats = [self._collect() for _ in range(n_prefill)]
        if n_prefill:
            ep = [s for s in stats if s["episodes"]]
            row: dict[str, Any] = {"iteration": 0, "frames": self.frames,
                                   "train_episodes": sum(s["episodes"] for s in ep),
                                   "train_return": float(np.mean([s["return"] for s in ep])) if ep else float("nan")}
            row.update(self._train_world_model(wc.prefill_train_steps))
            row["wall_s"] = self.wall_time + time.perf_counter() - t_start
            self.rows.append(row)
            logger.info("prefill: %d random frames, %d world-model steps", self.frames, wc.prefill_train_steps)
        self.prefilled = True

    def _iterate(self, it: int, t_start: float) -> dict[str, Any]:
        stats = self._collect()
        row: dict[str, Any] = {"iteration": it, "frames": self.frames, "train_episodes": stats["episodes"],
                               "train_return": stats["return"], "train_violations": stats["violations"]}
        row.update(self._train_world_model(self.cfg.world_model.train_steps))
        row.update(self._train_policy())
        row.update({f"gate_{m}": g for m, g in self.agent.world_model.encoder.gates.items()})
        row["wm_skipped_steps"] = self.wm_stats.skipped
        row["ppo_skipped_steps"] = self.algo.step_stats.skipped
        if self.cfg.eval.every and it % self.cfg.eval.every == 0 and it != self.cfg.collect.iterations:
            row.update({f"eval_{k}": v for k, v in evaluate_agent(self.agent).items()})
        row["wall_s"] = self.wall_time + time.perf_counter() - t_start
        return row

    def train(self) -> dict[str, Any]:
        """Run the remaining iterations, evaluate, write the summary; returns it. Ctrl-C / SIGTERM checkpoint the
        last finished iteration (already written after each one) and re-raise."""
        self._lock.acquire()  # no-op while __init__'s lock is held
        sigterm = catch_sigterm()
        try:
            return self._train()
        finally:
            restore_sigterm(sigterm)
            self.collector.shutdown()
            self._lock.release()

    def _train(self) -> dict[str, Any]:
        from tqdm.auto import tqdm

        cfg, cc = self.cfg, self.cfg.collect
        self._write_run_files()
        metrics = self._make_logger()
        t_start = time.perf_counter()
        try:
            if not self.prefilled:
                self._prefill(t_start)
                if self.rows:
                    self._log_row(metrics, self.rows[-1])
                self._checkpoint_now(t_start)
                t_start = time.perf_counter()
            self.policy.random_actions = False
            self.policy.random_action_prob = cc.random_action_prob
            its = range(self.iteration + 1, cc.iterations + 1)
            pbar = tqdm(its, desc=f"health[{cfg.encoder.kind}]", disable=not cfg.run.progress_bar)
            for it in pbar:
                row = self._iterate(it, t_start)
                self.rows.append(row)
                self.iteration = it
                self._log_row(metrics, row)
                self._checkpoint_now(t_start)  # each iteration: a crash or a kill resumes from here
                t_start = time.perf_counter()
                pbar.set_postfix(frames=self.frames, ret=f"{row['train_return']:.1f}",
                                 rec=f"{row.get('wm_loss_rec', float('nan')):.2f}")  # fmt: skip
        except KeyboardInterrupt as err:
            how = "terminated by SIGTERM" if isinstance(err, Terminated) else "interrupted"
            logger.warning("%s after iteration %d; rerun the same command to resume from %s", how, self.iteration,
                           latest_checkpoint(self.run_dir))  # fmt: skip
            raise
        return self._finish(metrics, t_start)

    def _checkpoint_now(self, t_start: float) -> None:
        self.wall_time += time.perf_counter() - t_start
        self._checkpoint()

    def _finish(self, metrics, t_start: float) -> dict[str, Any]:
        final = evaluate_agent(self.agent)
        if self.rows:
            self.rows[-1].update({f"eval_{k}": v for k, v in final.items()})
            self._log_row(metrics, {f"eval_{k}": v for k, v in final.items()})
        self.wall_time += time.perf_counter() - t_start
        self._checkpoint()
        save_agent(self.agent, self.run_dir, iteration=self.iteration, frames=self.frames)
        summary = self._summary(final)
        atomic_write_text(self.run_dir / "summary.json", json.dumps(summary, indent=2))
        logger.info("health run finished: %s", {k: summary[k] for k in ("eval_return_mean", "recon_mse")
                                                 if k in summary})  # fmt: skip
        return summary

    def _summary(self, final: dict[str, float]) -> dict[str, Any]:
        cfg, wm = self.cfg, self.agent.world_model
        return {
            "encoder": cfg.encoder.kind,
            "seed": cfg.run.seed,
            "iterations": cfg.collect.iterations,
            "frames": self.frames,
            "wall_time_s": self.wall_time,
            **{f"eval_{k}": v for k, v in final.items() if not k.startswith(("recon", "imagination"))},
            **{k: v for k, v in final.items() if k.startswith(("recon", "imagination"))},
            "imagination_horizon_definition": {
                "context": cfg.eval.horizon_context, "max": cfg.eval.horizon_max,
                "reward_tol": cfg.eval.horizon_reward_tol, "windows": cfg.eval.horizon_windows,
            },  # fmt: skip
            "params_world_model": _param_count(wm),
            "params_encoder": _param_count(wm.encoder),
            "params_policy": _param_count(self.agent.actor) + _param_count(self.agent.value),
            "gates": wm.encoder.gates or None,
            "wm_skipped_steps": self.wm_stats.skipped,
            "ppo_skipped_steps": self.algo.step_stats.skipped,
            "resumed_from": str(self.resumed_from) if self.resumed_from else None,
            "run_dir": str(self.run_dir),
        }


def run_health(cfg: HealthConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    """Train a health agent and evaluate it in the real env; returns the summary (also ``summary.json``).

    ``run_dir`` default: ``<run.output_dir>/<run.name or health-<kind>-s<seed>-<time>>``. Summary keys:
    ``eval_return_mean``/``_std``, ``eval_violations_mean``, ``eval_length_mean``, ``recon_mse`` (+ per key),
    ``imagination_horizon`` (+ ``_std``), ``frames``, ``wall_time_s``, parameter counts, FM gates (foundation).
    """
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir(cfg)
    return HealthTrainer(cfg, run_dir, resume=resume).train()
