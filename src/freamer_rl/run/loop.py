"""Collect-then-learn, the loop every collector-based trainer shares: FreamerV1's PPO and the TorchRL baselines.

A :class:`RunLoop` owns one run directory through a :class:`~freamer_rl.run.lifecycle.RunLifecycle` (the lock,
resume or refusal, run files, progress rows, metrics logger, checkpoints, SIGTERM, learning curve, summary: the piece
the health trainer uses too) and runs the collector loop itself: episode statistics and the Crafter score, periodic
and interrupt checkpoints, the progress display. A subclass provides the learning:

* ``_policy()`` -- the module the collector runs; ``_primers()`` -- its state primers (default none);
* ``_learn(data) -> dict of floats`` -- everything done with one collected batch ``[*B, T]`` (advantages, updates);
* ``_model_state()`` / ``_load_model_state(ckpt, path)`` -- its own checkpoint entries (model, optimiser, ...);
* ``_extra_row()`` / ``_extra_summary()`` -- its own progress.csv columns and summary entries;
* ``_privileged_information()`` -- the settings that read what the agent cannot observe (summary ``privileged``);
* ``_trainable_parameters()`` -- summary ``trainable_params`` (default: ``self.optimizer``'s parameters);
* ``_compiling()`` -- True when the first batches compile (one "compiling ..." log line before the first batch);
* ``frames_per_batch``, ``trainer_name`` (the checkpoint's ``"trainer"`` entry, a key of
  ``freamer_rl.trainers.registry.TRAINERS``; a resume refuses another trainer's checkpoint) and ``trainer_label``
  (what summary.json's ``algorithm`` and the curve's title call it; default the registry key).

It is built in two steps so the subclass can build its model between them: ``super().__init__(cfg, run_dir)``
(common state, no files touched; the run's wall time starts here), then ``self._start(resume)`` (lock and open the
run directory).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import time
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from freamer_rl.config.checks import resolve_device, run_name_problem
from freamer_rl.config.loader import config_to_dict
from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.run import env_registry
from freamer_rl.run.checkpoint import FORMAT as CHECKPOINT_FORMAT
from freamer_rl.run.checkpoint import load_checkpoint, read_transfer_source
from freamer_rl.run.collection import make_collector
from freamer_rl.run.corruption import env_corruption_state, load_corruption_state
from freamer_rl.run.crafter_score import CrafterScore
from freamer_rl.run.envs import make_batched_env
from freamer_rl.run.lifecycle import RunLifecycle
from freamer_rl.run.metrics import EpisodeStats, ProgressReporter, format_duration, format_rate
from freamer_rl.run.rundir import RunDirLock, surfaced_interrupts

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
    #: a name for titles and summary.json's ``algorithm`` (default ``trainer_name``): what trained, not on which env
    trainer_label = ""
    #: config sections (or dotted fields) that shape the weights: a resume needs them equal (the registry entry's)
    structural: tuple[str, ...] = ()

    def __init__(self, cfg: Any, run_dir: str | Path) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        label = self.trainer_label or self.trainer_name
        # first: the run's wall time starts before the model is built (start-up and compiling count)
        self.life = RunLifecycle(
            self.run_dir,
            trainer_name=self.trainer_name,
            config=config_to_dict(cfg),
            read_checkpoint=load_checkpoint,
            structural=self.structural,
            defaults=config_to_dict(type(cfg)()),
            title=f"{cfg.env.id} -- {label}, seed {cfg.run.seed}",
            curve={"window": cfg.logging.success_window},
        )
        self.device = resolve_device(cfg.run.device)  # before any work: 'cuda' without a visible GPU is one line
        torch.set_num_threads(cfg.run.threads)
        torch.manual_seed(cfg.run.seed)
        self.frames = 0
        self.batches = 0
        adapter = env_registry.get_adapter(cfg.env.adapter)
        self.stats = EpisodeStats(
            window=cfg.logging.success_window, success_fn=adapter.success, return_target=cfg.logging.return_target
        )
        # the Crafter score over every training episode, for adapters that report achievements
        self.achievements = CrafterScore(adapter.achievements) if adapter.achievements else None
        self._lock: RunDirLock | None = None
        # the training corruptions' running statistics (issue 20): restored from a checkpoint into the transforms
        # the envs are built from, read back from the in-process training env for the next checkpoint
        self._corruption_saved: list | None = None
        self._train_env: Any = None

    @property
    def rows(self) -> list[dict]:
        """The progress rows of the run so far (those of the resumed checkpoint first)."""
        return self.life.rows

    @property
    def wall_time(self) -> float:
        return self.life.wall_time

    @property
    def resumed_from(self) -> Path | None:
        return self.life.resumed_from

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

    def _trainable_parameters(self) -> int | None:
        """Parameters the trainer's optimiser updates (summary ``trainable_params``, a column of every suite table);
        default: those of ``self.optimizer``'s groups, None without one."""
        optimizer = getattr(self, "optimizer", None)
        if optimizer is None:
            return None
        return sum(p.numel() for group in optimizer.param_groups for p in group["params"])

    def _privileged_information(self) -> list[str]:
        """The settings that give the agent what it cannot observe (e.g. ``shaping.language.distance=oracle``):
        summary.json's ``privileged`` list, which the suite reports mark. Default none."""
        return []

    def _compiling(self) -> bool:
        """Whether the first batches compile parts of the model (a log line says so before the bar moves)."""
        return False

    # -- run directory --------------------------------------------------------------------------------------
    def _start(self, resume: bool) -> None:
        """Lock the run directory (held until train() returns), then resume or refuse to overwrite a checkpoint."""
        ckpt = self.life.open(resume, "delete it (--no-resume never deletes a run)")
        self._lock = self.life.lock
        try:
            if ckpt is not None:
                self._resume(ckpt)
            self._after_open(self.resumed_from)
            self.life.write_run_files()
        except BaseException:
            self._lock.release()
            raise

    #: config sections that shape the weights and must match ``run.init_from``'s checkpoint for a transfer; None: the
    #: trainer cannot transfer, and ``run.init_from`` is refused
    transfer_sections: tuple[str, ...] | None = None

    def _load_weights(self, state: dict[str, Any], path: Path) -> None:
        """Load a transferred model state (``run.init_from``); trainers with ``transfer_sections`` implement it."""
        raise NotImplementedError

    def _after_open(self, ckpt_path: Path | None) -> None:
        """Hook after a resume (``ckpt_path``) or a fresh start (``None``), before the run files are written: a fresh
        start with ``run.init_from`` loads that run's weights (``transfer_sections`` must match); a resume keeps its
        own. Subclasses that override it call it."""
        source = getattr(self.cfg.run, "init_from", None)
        if not source:
            return
        if ckpt_path is not None:
            logger.info("resuming this run's own checkpoint: run.init_from=%s is not applied", source)
            return
        if self.transfer_sections is None:
            raise ConfigError(
                f"run.init_from: the {self.trainer_name} trainer cannot start from another run's weights; leave it unset"
            )
        current, defaults = config_to_dict(self.cfg), config_to_dict(type(self.cfg)())
        state, path = read_transfer_source(source, current, defaults, self.transfer_sections)
        self._load_weights(state, path)
        logger.info("initialised the model from %s (run.init_from)", path)

    def _resume(self, ckpt: dict[str, Any]) -> None:
        path = self.life.checkpoint_path
        with self.life.restoring(ckpt):
            self._load_model_state(ckpt, path)
            self.frames = int(ckpt["frames"])
            self.batches = int(ckpt["batches"])
            self.stats.load_state_dict(ckpt["stats"])
            self._corruption_saved = ckpt.get("corruption")
            if self.achievements is not None and ckpt.get("achievements"):
                self.achievements.load_state_dict(ckpt["achievements"])
        logger.info("resumed from %s at %d frames, %d episodes", path, self.frames, self.stats.episodes)

    def _checkpoint(self) -> Path:
        return self.life.checkpoint(
            {
                **self._model_state(),
                "frames": self.frames,
                "batches": self.batches,
                "stats": self.stats.state_dict(),
                "config": config_to_dict(self.cfg),
                "achievements": self.achievements.state_dict() if self.achievements is not None else None,
                "corruption": env_corruption_state(self._train_env) if self._train_env is not None else None,
                "format": CHECKPOINT_FORMAT,
            }
        )

    # -- data -----------------------------------------------------------------------------------------------
    def _env_fns(self, seed: int) -> list:
        transforms = [*self._env_transforms(), *self._primers()]
        if self.resumed_from is not None:
            try:
                load_corruption_state(transforms, self._corruption_saved, str(self.resumed_from))
            except (KeyError, TypeError, ValueError) as err:
                raise CheckpointError(f"checkpoint {self.resumed_from}: {err}") from err
        return [
            functools.partial(make_batched_env, self.cfg, transforms, seed + 1000 * i)
            for i in range(self.cfg.collector.num_collectors)
        ]

    def _planned_frames(self, remaining: int) -> int:
        """The frames the collector will deliver for ``remaining`` more: whole batches."""
        return math.ceil(remaining / self.frames_per_batch) * self.frames_per_batch

    # -- inspection seams (tests, benchmarks): the pieces train() runs, callable one at a time -----------------
    def make_collector(self, remaining: int):
        """The training collector for ``remaining`` more frames (whole batches), as :meth:`train` builds it; the
        caller iterates it and shuts it down."""
        return self._make_collector(remaining)

    def learn(self, data: TensorDictBase) -> dict[str, float]:
        """One learning step on a collected batch ``[*B, T]``, as :meth:`train` runs it (with
        :meth:`learning_threads`); returns its log values."""
        with self.learning_threads():
            return self._learn(data)

    @contextlib.contextmanager
    def learning_threads(self):
        """torch's thread count while learning: ``run.update_threads`` inside, ``run.threads`` again after (for
        collection, whose policy forward and envs run in this process)."""
        n = self.cfg.run.update_threads
        if n is None or n == self.cfg.run.threads:
            yield
            return
        torch.set_num_threads(n)
        try:
            yield
        finally:
            torch.set_num_threads(self.cfg.run.threads)

    def _make_collector(self, remaining: int):
        seed = self.cfg.run.seed * 10_000 + self.frames  # a resumed run does not replay the same episodes
        # envs step on the CPU; the policy runs on run.device and the batch is stored there for the learner
        devices = {"policy_device": self.device, "env_device": "cpu", "storing_device": self.device}
        return make_collector(
            self.cfg.collector,
            self._env_fns(seed),
            self._policy(),
            frames_per_batch=self.frames_per_batch,
            total_frames=self._planned_frames(remaining),
            devices=devices,
            sync=self._collector_sync(),
        )

    # -- main -----------------------------------------------------------------------------------------------
    def train(self) -> dict[str, Any]:
        """Train up to ``run.total_frames``; returns the summary. Holds the run-dir lock until it returns.

        Ctrl-C (KeyboardInterrupt) and SIGTERM (:class:`~freamer_rl.run.rundir.Terminated`) write a checkpoint and
        re-raise; the previous SIGTERM handler is restored afterwards.
        """
        if self._lock is None:
            raise RuntimeError(f"{type(self).__name__}.__init__ must call self._start(resume)")
        with self.life.guard():  # lock, SIGTERM, no per-batch INFO lines of TorchRL in the user's terminal
            return self._train()

    def _train(self) -> dict[str, Any]:
        cfg = self.cfg
        remaining = cfg.run.total_frames - self.frames
        if remaining <= 0:
            logger.info(
                "run already has %d frames (run.total_frames=%d): nothing to do", self.frames, cfg.run.total_frames
            )
            return self._finish()
        metrics_logger = self.life.metrics_logger(cfg.logging.backend, option="logging.backend")
        collector = self._make_collector(remaining)
        # one in-process env holds the corruption statistics; worker processes keep theirs (not checkpointed)
        local = self.cfg.collector.num_collectors == 1 and getattr(self.cfg.collector, "backend", "local") == "local"
        self._train_env = getattr(collector, "env", None) if local else None
        every = cfg.logging.checkpoint_every_frames
        next_ckpt = (self.frames // every + 1) * every
        # a tqdm bar on a terminal, else a plain log line every ~10 s; its total is what the collector will deliver
        progress = ProgressReporter(
            self.frames + self._planned_frames(remaining), self.frames, bar=cfg.logging.progress_bar
        )
        if self._compiling():
            logger.info("compiling the model (model.compile) during the first batches: they take longer")
        t_batch = time.perf_counter()
        try:
            with surfaced_interrupts():  # an interrupt that a library turned into its own error
                for data in collector:
                    losses = self.learn(data)
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
                    self.life.log_row(
                        row, metrics_logger, self.frames, to_logger=self.batches % cfg.logging.log_every_batches == 0
                    )
                    progress.update(self.frames, data.numel(), self.stats)
                    if self.frames >= next_ckpt:
                        self._checkpoint()
                        next_ckpt += every
                    if self._should_stop():
                        break
                    self.life.check_terminated()
        except KeyboardInterrupt as err:
            # keep everything learnt so far: rerunning the same command resumes from this checkpoint
            self.life.stopping()
            self.life.interrupted(err, f"at {self.frames} frames", self._checkpoint())
            raise
        finally:
            collector.shutdown()
            progress.close()
        self._checkpoint()
        return self._finish()

    def _should_stop(self) -> bool:
        target = self.cfg.run.stop_at_success
        if (
            target is not None
            and len(self.stats.recent_success) >= self.stats.window
            and self.stats.success_rate >= target
        ):
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
        wall = self.wall_time
        summary = {
            "env": self.cfg.env.id,
            "seed": self.cfg.run.seed,
            "trainer": self.trainer_name,  # the registry key (recipes' ``trainer:``, what freamer-rl eval reads)
            "algorithm": self.trainer_label or self.trainer_name,
            "frames": self.frames,
            "episodes": self.stats.episodes,
            "final_success_rate": self.stats.success_rate,
            "final_return_mean": self.stats.mean_return,
            **self.stats.level_summary(),
            "privileged": self._privileged_information(),
            "trainable_params": self._trainable_parameters(),
            "wall_time_s": wall,  # from the trainer's start (model build and compiling included), all attempts
            "fps": self.frames / wall if wall > 0 else None,
            **self._extra_summary(),
        }
        if self.achievements is not None:  # per-achievement table, bar chart and score (official formula)
            summary["crafter_score"] = self.achievements.score()
            self.achievements.write_report(self.run_dir)
        summary = self.life.write_summary(summary)
        fps = f" ({summary['fps']:.0f} frames/s)" if summary["fps"] else ""
        logger.info(
            "finished: %d frames, %d episodes | success %s, return %s (last %d episodes) | wall time %s%s | run dir %s",
            self.frames,
            self.stats.episodes,
            format_rate(self.stats.success_rate),
            format_rate(self.stats.mean_return),
            min(self.stats.episodes, self.stats.window),
            format_duration(wall),
            fps,
            self.run_dir,
        )
        return summary
