"""The run loop every collector-based trainer shares: FreamerV1's PPO and the TorchRL baselines.

A :class:`RunLoop` owns one run directory (the layout of :mod:`freamer_rl.trainers.minigrid_ppo`): the lock, resume from the latest
checkpoint (or refusal to overwrite one), ``config.yaml`` / ``run_info.json``, ``progress.csv`` rewritten from the
checkpoint's rows, the TorchRL metrics logger, episode statistics and the Crafter score, periodic and interrupt
checkpoints, the learning curve and ``summary.json``. A subclass provides the learning:

* ``_policy()`` -- the module the collector runs; ``_primers()`` -- its state primers (default none);
* ``_learn(data) -> dict of floats`` -- everything done with one collected batch ``[*B, T]`` (advantages, updates);
* ``_model_state()`` / ``_load_model_state(ckpt, path)`` -- its own checkpoint entries (model, optimiser, ...);
* ``_extra_row()`` / ``_extra_summary()`` -- its own progress.csv columns and summary entries;
* ``frames_per_batch`` and ``trainer_name`` (the checkpoint's ``"trainer"`` entry, ``freamer_rl.trainers.registry.TRAINERS``;
  a resume refuses another trainer's checkpoint).

It is built in two steps so the subclass can build its model between them: ``super().__init__(cfg, run_dir)``
(common state, no files touched), then ``self._start(resume)`` (lock and open the run directory).
"""

from __future__ import annotations

import csv
import functools
import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from freamer_rl.run import env_registry
from freamer_rl.run.envs import make_batched_env
from freamer_rl.run.checkpoint import FORMAT as CHECKPOINT_FORMAT
from freamer_rl.run.checkpoint import (
    atomic_write_text, check_checkpoint_config, load_checkpoint, resume_checkpoint, save_checkpoint,
)
from freamer_rl.run.collection import make_collector
from freamer_rl.config.checks import resolve_device
from freamer_rl.config.loader import config_to_dict
from freamer_rl.run.crafter_score import CrafterScore
from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.run.metrics import EpisodeStats, ProgressReporter, format_duration, format_rate, plot_learning_curve
from freamer_rl.run.metrics import quiet_library_logs
from freamer_rl.run.files import make_metrics_logger, write_run_files
from freamer_rl.run.rundir import RunDirLock, Terminated, catch_sigterm, restore_sigterm, write_rows_csv
from freamer_rl.config.checks import run_name_problem

logger = logging.getLogger(__name__)

__all__ = ["RunLoop", "resolve_run_dir", "default_run_name"]


def default_run_name(cfg: Any) -> str:
    # env ids may hold a namespace ("ALE/Pong-v5"): keep the name one folder under run.output_dir
    env_short = cfg.env.id.replace("MiniGrid-", "").replace("-v0", "")
    env_short = env_short.replace("/", "_").replace("\\", "_").replace("..", "_")
    return f"{env_short}-s{cfg.run.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


def resolve_run_dir(cfg: Any, run_dir: str | Path | None) -> Path:
    """``run_dir``, else ``run.output_dir/run.name`` (or a name from env id, seed and time)."""
    if run_dir is not None:
        return Path(run_dir)
    name = cfg.run.name or default_run_name(cfg)
    if problem := run_name_problem(name):  # config validation covers run.name; this guards the default too
        raise ConfigError(f"run.name: {problem}")
    return Path(cfg.run.output_dir) / name


class RunLoop:
    """Collect -> learn -> log -> checkpoint, resumable; see the module docstring for what a subclass provides."""

    trainer_name = ""
    #: config sections (or dotted fields) that shape the weights: a resume needs them equal (the registry entry's)
    structural: tuple[str, ...] = ()

    def __init__(self, cfg: Any, run_dir: str | Path) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.device = resolve_device(cfg.run.device)  # before any work: 'cuda' without a visible GPU is one line
        torch.set_num_threads(cfg.run.threads)
        torch.manual_seed(cfg.run.seed)
        self.frames = 0
        self.batches = 0
        adapter = env_registry.get_adapter(cfg.env.adapter)
        self.stats = EpisodeStats(window=cfg.logging.success_window, success_fn=adapter.success)
        # the Crafter score over every training episode, for adapters that report achievements
        self.achievements = CrafterScore(adapter.achievements) if adapter.achievements else None
        self.rows: list[dict] = []
        self.wall_time = 0.0
        self.resumed_from: Path | None = None
        self._lock: RunDirLock | None = None

    # -- what a subclass provides ---------------------------------------------------------------------------
    @property
    def frames_per_batch(self) -> int:
        raise NotImplementedError

    def _policy(self) -> Any:
        raise NotImplementedError

    def _primers(self) -> list:
        return []

    def _env_transforms(self) -> list:
        """Transforms added to the training envs after RewardSum (e.g. a novelty bonus); default none."""
        return []

    def _collector_sync(self) -> bool:
        return True

    def _learn(self, data: TensorDictBase) -> dict[str, float]:
        raise NotImplementedError

    def _model_state(self) -> dict[str, Any]:
        raise NotImplementedError

    def _load_model_state(self, ckpt: dict[str, Any], path: Path) -> None:
        raise NotImplementedError

    def _extra_row(self) -> dict[str, Any]:
        return {}

    def _extra_summary(self) -> dict[str, Any]:
        return {}

    def _curve_title(self) -> str:
        return self.cfg.env.id

    # -- run directory --------------------------------------------------------------------------------------
    def _start(self, resume: bool) -> None:
        """Lock the run directory (held until train() returns), then resume or refuse to overwrite a checkpoint."""
        self._lock = RunDirLock(self.run_dir).acquire()
        try:
            self._open_run_dir(resume)
        except BaseException:
            self._lock.release()
            raise

    def _open_run_dir(self, resume: bool) -> None:
        ckpt_path = resume_checkpoint(self.run_dir, resume, "delete it (--no-resume never deletes a run)")
        if ckpt_path is not None:
            self._resume(ckpt_path)
        self._after_open(ckpt_path)
        # progress.csv = the checkpoint's rows: rows written after it (a kill -9) go, a fresh start truncates
        self._rewrite_progress(self.run_dir / "progress.csv")
        write_run_files(self.run_dir, config_to_dict(self.cfg), self.resumed_from)

    def _after_open(self, ckpt_path: Path | None) -> None:
        """Hook after a resume (``ckpt_path``) or a fresh start (``None``), before the run files are written."""

    def _resume(self, path: Path) -> None:
        ckpt = load_checkpoint(path)
        saved = ckpt.get("trainer", self.trainer_name)  # older FreamerV1 checkpoints have no entry
        if saved != self.trainer_name:  # e.g. a PPO run folder resumed with an IMPALA recipe of the same network
            raise CheckpointError(f"checkpoint {path} was written by trainer {saved!r}, this recipe's trainer is "
                                  f"{self.trainer_name!r}; use another run directory")  # fmt: skip
        check_checkpoint_config(ckpt["config"], config_to_dict(self.cfg), path, self.structural,
                                config_to_dict(type(self.cfg)()))
        try:
            self._load_model_state(ckpt, path)
            self.frames = int(ckpt["frames"])
            self.batches = int(ckpt["batches"])
            self.stats.load_state_dict(ckpt["stats"])
            self.rows = [dict(r) for r in ckpt["rows"]]
            self.wall_time = float(ckpt.get("wall_time", 0.0))
            torch.set_rng_state(ckpt["torch_rng"])
            if self.achievements is not None and ckpt.get("achievements"):
                self.achievements.load_state_dict(ckpt["achievements"])
        except CheckpointError:
            raise
        except (KeyError, TypeError, ValueError, RuntimeError) as err:  # a hand-edited or foreign payload
            detail = f"missing entry {err}" if isinstance(err, KeyError) else str(err).splitlines()[0][:200]
            raise CheckpointError(f"checkpoint {path} is incomplete or damaged: {detail}") from err
        self.resumed_from = path
        logger.info("resumed from %s at %d frames, %d episodes", path, self.frames, self.stats.episodes)

    def _checkpoint(self) -> Path:
        payload = {
            **self._model_state(),
            "frames": self.frames,
            "batches": self.batches,
            "stats": self.stats.state_dict(),
            "rows": self.rows,
            "wall_time": self.wall_time,
            "config": config_to_dict(self.cfg),
            "torch_rng": torch.get_rng_state(),
            "achievements": self.achievements.state_dict() if self.achievements is not None else None,
            "format": CHECKPOINT_FORMAT,
            "trainer": self.trainer_name,  # freamer-rl eval dispatches on it (freamer_rl.trainers.registry.TRAINERS)
        }
        path = save_checkpoint(self.run_dir, payload)  # atomic + rotated; see freamer_rl.run.checkpoint
        if self.rows:
            plot_learning_curve(self.rows, self.run_dir / "learning_curve.png", title=self._curve_title(),
                                window=self.cfg.logging.success_window)
        return path

    def _rewrite_progress(self, path: Path) -> None:
        """Replace progress.csv with ``self.rows`` atomically (columns of the last row; empty file without rows)."""
        write_rows_csv(path, self.rows, fields=list(self.rows[-1]) if self.rows else None)

    def _append_progress(self, path: Path, row: dict) -> None:
        """Append ``row`` (already the last of ``self.rows``); rewrite the file when its columns differ."""
        header: list[str] = []
        if path.exists():
            with path.open(newline="") as f:
                header = next(csv.reader(f), [])
        if header != list(row):
            # new file, or columns changed (e.g. a resumed run with other diagnostics): rewrite from the kept rows
            self._rewrite_progress(path)
            return
        with path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=list(row)).writerow(row)

    # -- data -----------------------------------------------------------------------------------------------
    def _env_fns(self, seed: int) -> list:
        transforms = [*self._env_transforms(), *self._primers()]
        return [functools.partial(make_batched_env, self.cfg, transforms, seed + 1000 * i)
                for i in range(self.cfg.collector.num_collectors)]  # fmt: skip

    def _make_collector(self, remaining: int):
        seed = self.cfg.run.seed * 10_000 + self.frames  # a resumed run does not replay the same episodes
        fpb = self.frames_per_batch
        total = math.ceil(remaining / fpb) * fpb
        # envs step on the CPU; the policy runs on run.device and the batch is stored there for the learner
        devices = {"policy_device": self.device, "env_device": "cpu", "storing_device": self.device}
        return make_collector(self.cfg.collector, self._env_fns(seed), self._policy(), frames_per_batch=fpb,
                              total_frames=total, devices=devices, sync=self._collector_sync())  # fmt: skip

    # -- main -----------------------------------------------------------------------------------------------
    def train(self) -> dict[str, Any]:
        """Train up to ``run.total_frames``; returns the summary. Holds the run-dir lock until it returns.

        Ctrl-C (KeyboardInterrupt) and SIGTERM (:class:`~freamer_rl.run.rundir.Terminated`) write a checkpoint and
        re-raise; the previous SIGTERM handler is restored afterwards.
        """
        if self._lock is None:
            raise RuntimeError(f"{type(self).__name__}.__init__ must call self._start(resume)")
        self._lock.acquire()  # no-op while __init__'s lock is held; re-locks for a second train() call
        sigterm = catch_sigterm()
        try:
            with quiet_library_logs():  # no per-batch INFO lines of TorchRL in the user's terminal
                return self._train()
        finally:
            restore_sigterm(sigterm)
            self._lock.release()

    def _train(self) -> dict[str, Any]:
        cfg = self.cfg
        remaining = cfg.run.total_frames - self.frames
        if remaining <= 0:
            logger.info("run already has %d frames (run.total_frames=%d): nothing to do", self.frames,
                        cfg.run.total_frames)
            return self._finish()
        metrics_logger = make_metrics_logger(self.run_dir, cfg.logging.backend, config_to_dict(cfg),
                                             option="logging.backend")
        collector = self._make_collector(remaining)
        every = cfg.logging.checkpoint_every_frames
        next_ckpt = (self.frames // every + 1) * every
        # a tqdm bar on a terminal, else a plain log line every ~10 s
        progress = ProgressReporter(cfg.run.total_frames, self.frames, bar=cfg.logging.progress_bar)
        t_start = t_batch = time.perf_counter()
        try:
            for data in collector:
                losses = self._learn(data)
                # counted only once trained on, so a checkpoint written on interrupt is consistent
                self.stats.update(data, self.frames)
                if self.achievements is not None:
                    self.achievements.update(data)
                self.frames += data.numel()
                collector.update_policy_weights_()
                self.batches += 1
                now = time.perf_counter()
                row = self._batch_row(data.numel() / max(now - t_batch, 1e-9), losses)
                t_batch = now
                self._log_row(row, metrics_logger)
                progress.update(self.frames, data.numel(), self.stats)
                if self.frames >= next_ckpt:
                    self.wall_time += time.perf_counter() - t_start
                    t_start = time.perf_counter()
                    self._checkpoint()
                    next_ckpt += every
                if self._should_stop():
                    break
        except KeyboardInterrupt as err:
            # keep everything learnt so far: rerunning the same command resumes from this checkpoint
            self.wall_time += time.perf_counter() - t_start
            path = self._checkpoint()
            how = "terminated by SIGTERM" if isinstance(err, Terminated) else "interrupted"
            logger.warning("%s at %d frames; saved %s (rerun the same command to resume)", how, self.frames, path)
            raise
        finally:
            collector.shutdown()
            progress.close()
        self.wall_time += time.perf_counter() - t_start
        self._checkpoint()
        return self._finish()

    def _log_row(self, row: dict, metrics_logger: Any) -> None:
        self.rows.append(row)
        self._append_progress(self.run_dir / "progress.csv", row)
        if metrics_logger is not None and self.batches % self.cfg.logging.log_every_batches == 0:
            for k, v in row.items():
                if isinstance(v, (int, float)) and math.isfinite(v):
                    metrics_logger.log_scalar(k, v, step=self.frames)

    def _should_stop(self) -> bool:
        target = self.cfg.run.stop_at_success
        if target is not None and len(self.stats.recent_success) >= self.stats.window \
                and self.stats.success_rate >= target:  # fmt: skip
            logger.info("success rate %.3f >= run.stop_at_success: stopping", self.stats.success_rate)
            return True
        return self.frames >= self.cfg.run.total_frames

    def _batch_row(self, fps: float, losses: dict[str, float]) -> dict[str, Any]:
        """The progress.csv row of the batch just trained on."""
        return {
            "frames": self.frames,
            "episodes": self.stats.episodes,
            "success_rate": self.stats.success_rate,
            "return_mean": self.stats.mean_return,
            "episode_length": self.stats.mean_length,
            "fps": fps,
            **losses,
            **self._extra_row(),
            **({"crafter_score": self.achievements.score()} if self.achievements is not None else {}),
        }

    def _finish(self) -> dict[str, Any]:
        summary = {
            "env": self.cfg.env.id,
            "seed": self.cfg.run.seed,
            "trainer": self.trainer_name,
            "frames": self.frames,
            "episodes": self.stats.episodes,
            "final_success_rate": self.stats.success_rate,
            "final_return_mean": self.stats.mean_return,
            "frames_to_95": self.stats.first_target_frames,
            "episodes_to_95": self.stats.first_target_episodes,
            "wall_time_s": self.wall_time,
            "fps": self.frames / self.wall_time if self.wall_time > 0 else None,
            **self._extra_summary(),
        }
        if self.achievements is not None:  # per-achievement table, bar chart and score (official formula)
            summary["crafter_score"] = self.achievements.score()
            self.achievements.write_report(self.run_dir)
        atomic_write_text(self.run_dir / "summary.json", json.dumps(summary, indent=2))
        if self.rows:
            plot_learning_curve(self.rows, self.run_dir / "learning_curve.png", title=self._curve_title(),
                                window=self.cfg.logging.success_window)
        fps = f" ({summary['fps']:.0f} frames/s)" if summary["fps"] else ""
        logger.info(
            "finished: %d frames, %d episodes | success %s, return %s (last %d episodes) | wall time %s%s | run dir %s",
            self.frames, self.stats.episodes, format_rate(self.stats.success_rate), format_rate(self.stats.mean_return),
            min(self.stats.episodes, self.stats.window), format_duration(self.wall_time), fps, self.run_dir,
        )  # fmt: skip
        return summary
