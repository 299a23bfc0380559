"""The bookkeeping of one run directory, the same for every trainer (the collector-based ones through
:class:`freamer_rl.run.loop.RunLoop`, and the health trainer):

    <run_dir>/.lock                 held from construction until training returns (:class:`RunDirLock`)
    <run_dir>/config.yaml           the resolved config; run_info.json: commit, versions, command, resumed_from
    <run_dir>/progress.csv          one row per batch / iteration, rewritten from the checkpoint's rows on (re)start
    <run_dir>/metrics/attempt_NN/   the TorchRL logger of this attempt
    <run_dir>/checkpoints/          the newest resume checkpoints and the ``latest`` marker
    <run_dir>/learning_curve.png    redrawn with every checkpoint and at the end
    <run_dir>/summary.json          final figures (valid JSON: NaN is written as null)

:class:`RunLifecycle` does the parts that do not depend on what is trained: the lock, resume from the latest
checkpoint (or refusal to overwrite one), the checks that the checkpoint belongs to this trainer and was written with
the same weight-shaping config sections (the trainer's registry entry declares them), the one-line CheckpointError
for a damaged payload, the run files, the progress rows, the metrics logger, the checkpoint's common entries
(``rows``, ``wall_time``, ``torch_rng``, ``trainer``), SIGTERM / Ctrl-C handling, the learning curve and the summary.
A trainer supplies its own payload (weights, optimisers, counters) and restores it inside :meth:`restoring`.

Wall time counts from the lifecycle's construction (the start of the trainer, before its model is built, so start-up
and compiling are included), plus that of the earlier attempts of a resumed run.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch

from freamer_rl.errors import CheckpointError
from freamer_rl.run.checkpoint import (
    atomic_write_text,
    check_checkpoint_config,
    resume_checkpoint,
    run_file_errors,
    save_checkpoint,
)
from freamer_rl.run.files import make_metrics_logger, write_run_files
from freamer_rl.run.metrics import RETURN_SERIES, json_safe, plot_learning_curve, quiet_library_logs
from freamer_rl.run.rundir import (
    RunDirLock,
    SigtermToken,
    Terminated,
    catch_sigterm,
    restore_sigterm,
    surfaced_interrupts,
    write_rows_csv,
)

logger = logging.getLogger(__name__)

__all__ = ["RunLifecycle"]


class RunLifecycle:
    """One run directory's lock, resume, run files, progress rows, checkpoints, curve and summary.

    Args:
        run_dir: the run directory (created when the lock is taken).
        trainer_name: the registry key written into checkpoints; a resume refuses another trainer's checkpoint.
        config: the resolved config as a mapping (``config.yaml``, the logger's hyperparameters, the structure check).
        read_checkpoint: ``path -> payload`` (the trainer's checkpoint reader, which checks its format).
        structural: config sections (or dotted fields) that shape the weights: a resume needs them equal.
        defaults: the schema's default mapping (fills fields a later release added to a saved section).
        title: the learning curve's title. ``curve``: extra :func:`plot_learning_curve` options (``window``,
            ``returns``, ``return_label``).
    """

    def __init__(
        self,
        run_dir: str | Path,
        *,
        trainer_name: str,
        config: dict,
        read_checkpoint: Callable[[Path], dict],
        structural: tuple[str, ...],
        defaults: dict | None = None,
        title: str = "",
        curve: dict[str, Any] | None = None,
    ) -> None:
        self.t0 = time.perf_counter()  # first: start-up belongs to the run's wall time
        self.run_dir = Path(run_dir)
        self.trainer_name = trainer_name
        self.config = config
        self._read = read_checkpoint
        self.structural = tuple(structural)
        self.defaults = defaults
        self.title = title
        self.curve = {"returns": RETURN_SERIES, **(curve or {})}
        self.rows: list[dict[str, Any]] = []
        self.resumed_from: Path | None = None
        self.checkpoint_path: Path | None = None  # the checkpoint open() returned
        self._wall_before = 0.0  # wall time of the earlier attempts (from the checkpoint)
        self.lock = RunDirLock(self.run_dir)
        self._sigterm: SigtermToken | None = None  # while guard() runs

    # -- opening ------------------------------------------------------------------------------------------------------
    def open(self, resume: bool, refusal_hint: str) -> dict | None:
        """Lock the directory, then the checkpoint payload to resume from (checked for trainer and structure), or
        None for a fresh start (``resume=False`` refuses a directory holding checkpoints, naming ``refusal_hint``).
        The lock is released again when this raises."""
        self.lock.acquire()
        try:
            path = resume_checkpoint(self.run_dir, resume, refusal_hint)
            if path is None:
                return None
            ckpt = self._read(path)
            saved = ckpt.get("trainer", self.trainer_name)  # checkpoints older than the entry: the format decides
            if saved != self.trainer_name:  # e.g. a PPO run folder resumed with an IMPALA recipe of the same network
                raise CheckpointError(
                    f"checkpoint {path} was written by trainer {saved!r}, this recipe's trainer is "
                    f"{self.trainer_name!r}; use another run directory"
                )
            check_checkpoint_config(ckpt.get("config"), self.config, path, self.structural, self.defaults)
        except BaseException:
            self.lock.release()
            raise
        self.checkpoint_path = path
        return ckpt

    @contextlib.contextmanager
    def restoring(self, ckpt: dict) -> Iterator[None]:
        """The trainer restores its own entries of ``ckpt`` in the block; then the common ones (rows, wall time,
        torch RNG). A missing or mistyped entry anywhere is one CheckpointError line naming the file."""
        path = self.checkpoint_path
        try:
            yield
            rows = [dict(r) for r in ckpt["rows"]]
            wall = float(ckpt.get("wall_time", 0.0))
            torch.set_rng_state(ckpt["torch_rng"])
        except CheckpointError:
            raise
        except (KeyError, TypeError, ValueError, RuntimeError) as err:  # a hand-edited, foreign or final-only payload
            detail = f"missing entry {err}" if isinstance(err, KeyError) else str(err).splitlines()[0][:200]
            raise CheckpointError(f"checkpoint {path} is incomplete or damaged: {detail}") from err
        self.rows, self._wall_before, self.resumed_from = rows, wall, path

    def write_run_files(self) -> None:
        """progress.csv = the checkpoint's rows (rows written after it, by a kill -9, go; a fresh start truncates),
        then config.yaml and run_info.json."""
        self.rewrite_progress()
        write_run_files(self.run_dir, self.config, self.resumed_from)

    # -- during the run -----------------------------------------------------------------------------------------------
    @property
    def wall_time(self) -> float:
        """Seconds of this run so far: the earlier attempts' and this one's since the trainer started."""
        return self._wall_before + time.perf_counter() - self.t0

    def metrics_logger(self, backend: str, option: str) -> Any:
        return make_metrics_logger(self.run_dir, backend, self.config, option=option)

    @contextlib.contextmanager
    def guard(self) -> Iterator[None]:
        """Around training: the lock held (re-taken for a second ``train()``), SIGTERM raising
        :class:`~freamer_rl.run.rundir.Terminated`, TorchRL's INFO lines hidden; all undone afterwards."""
        self.lock.acquire()  # no-op while the constructor's lock is held
        self._sigterm = catch_sigterm()
        try:
            with quiet_library_logs(), surfaced_interrupts():
                yield
        finally:
            restore_sigterm(self._sigterm)
            self._sigterm = None
            self.lock.release()

    def check_terminated(self) -> None:
        """Once per loop step inside :meth:`guard`: raise :class:`~freamer_rl.run.rundir.Terminated` if a SIGTERM
        fired but a library swallowed it (the run would otherwise train on and ignore later SIGTERMs)."""
        if self._sigterm is not None:
            self._sigterm.raise_if_fired()

    def log_row(self, row: dict[str, Any], metrics: Any, step: int, *, to_logger: bool = True) -> None:
        """Keep ``row``, append it to progress.csv and (``to_logger``) send its finite numbers to ``metrics``."""
        self.rows.append(row)
        self.append_progress(row)
        if metrics is not None and to_logger:
            self.log_scalars(row, metrics, step)

    @staticmethod
    def log_scalars(values: dict[str, Any], metrics: Any, step: int) -> None:
        for k, v in values.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                metrics.log_scalar(k, v, step=step)

    def rewrite_progress(self) -> None:
        """Replace progress.csv with the kept rows atomically (every column any row has, in order of appearance:
        an evaluation every N iterations adds columns to some rows only; empty file without rows)."""
        write_rows_csv(self.run_dir / "progress.csv", self.rows)

    def append_progress(self, row: dict[str, Any]) -> None:
        """Append ``row`` (already the last kept row) under the file's header (its missing columns left blank);
        rewrite the file when the row brings a column the header lacks."""
        path = self.run_dir / "progress.csv"
        header: list[str] = []
        if path.exists():
            with path.open(newline="") as f:
                header = next(csv.reader(f), [])
        if not header or not set(row) <= set(header):
            # new file, or new columns (a resumed run with other diagnostics, an evaluation row): rewrite
            self.rewrite_progress()
            return
        with run_file_errors(path), path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=header).writerow(row)

    def checkpoint(self, payload: dict[str, Any]) -> Path:
        """Save ``payload`` (the trainer's entries, with ``format`` and ``frames``) plus the common entries as the
        newest resume checkpoint (atomic, rotated), then redraw the learning curve."""
        path = save_checkpoint(
            self.run_dir,
            {
                **payload,
                "rows": self.rows,
                "wall_time": self.wall_time,
                "torch_rng": torch.get_rng_state(),
                "trainer": self.trainer_name,  # freamer-rl eval dispatches on it (freamer_rl.trainers.registry)
            },
        )
        self.plot()
        return path

    def stopping(self) -> None:
        """The trainer caught Ctrl-C / SIGTERM and writes its checkpoint now: later SIGTERMs wait for it."""
        if self._sigterm is not None:
            self._sigterm.stopping_now()

    def interrupted(self, err: KeyboardInterrupt, where: str, saved: Path | None) -> None:
        """The warning of a Ctrl-C / SIGTERM stop (``where``: "at 1024 frames"); the caller re-raises."""
        how = "terminated by SIGTERM" if isinstance(err, Terminated) else "interrupted"
        logger.warning("%s %s; saved %s (rerun the same command to resume)", how, where, saved)

    # -- the end ------------------------------------------------------------------------------------------------------
    def plot(self) -> None:
        if self.rows:
            plot_learning_curve(self.rows, self.run_dir / "learning_curve.png", title=self.title, **self.curve)

    def write_summary(self, summary: dict[str, Any]) -> dict[str, Any]:
        """``summary.json`` (NaN and inf as null: valid JSON) and the final learning curve; returns ``summary``."""
        summary = json_safe(summary)
        atomic_write_text(self.run_dir / "summary.json", json.dumps(summary, indent=2))
        self.plot()
        return summary
