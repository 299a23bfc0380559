"""Run-directory safety: one writer per run directory, run names that stay inside the output folder, SIGTERM.

- :class:`RunDirLock` -- ``fcntl.flock`` on ``<run_dir>/.lock`` (non-blocking). The lock belongs to the open file,
  so the kernel releases it when the process dies, even by ``kill -9``: a crash never leaves a stale lock. The
  holder's pid, host and command are written into the file so that a refused second run can name it. The file
  itself is never deleted (deleting a lock file lets two processes lock two different files).
- :func:`run_name_problem` -- why a ``run.name`` would escape ``run.output_dir`` (None when it is safe).
- :func:`catch_sigterm` / :func:`restore_sigterm` -- SIGTERM raises :class:`Terminated` (a KeyboardInterrupt), so
  the code that checkpoints on Ctrl-C also checkpoints when a scheduler or ``kill`` stops the run.
- :func:`write_rows_csv` -- progress tables replaced atomically; :func:`next_attempt_name` -- ``metrics/attempt_NN``.

Caveat: ``flock`` protects runs on one machine (and on NFS only where the server supports it); where locking is
unavailable a warning is logged and the run proceeds unlocked.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from freamer_rl.config.checks import run_name_problem
from freamer_rl.errors import FreamerError, interrupt_in_chain
from freamer_rl.run.checkpoint import atomic_write_text

try:
    import fcntl
except ImportError:  # Windows: no flock; runs are not locked there
    fcntl = None  # type: ignore[assignment]

logger = logging.getLogger(__name__)

__all__ = [
    "LOCK_NAME",
    "RunDirLock",
    "Terminated",
    "interrupt_in_chain",
    "surfaced_interrupts",
    "catch_sigterm",
    "next_attempt_name",
    "restore_sigterm",
    "SigtermToken",
    "run_name_problem",
    "write_rows_csv",
]

LOCK_NAME = ".lock"


# ----------------------------------------------------------------------------------------------------------------------
# run names
# ----------------------------------------------------------------------------------------------------------------------
# ----------------------------------------------------------------------------------------------------------------------
# lock
# ----------------------------------------------------------------------------------------------------------------------
def _holder_info() -> dict[str, Any]:
    return {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "command": " ".join(sys.argv)[:300],
        "since": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }


def _describe_holder(text: str) -> str:
    try:
        info = json.loads(text)
        cmd = " ".join(str(info.get("command", "?")).split())[:160]  # one line whatever the command held
        return f"pid {info.get('pid')} on {info.get('host')} since {info.get('since')}: {cmd}"
    except (ValueError, AttributeError):
        return "holder unknown (it has not written its details yet)"


class RunDirLock:
    """Exclusive, non-blocking lock of a run directory; ``acquire`` raises FreamerError naming the holder.

    Re-entrant within one object (``acquire`` on a held lock is a no-op); usable as a context manager.
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self._file = None

    @property
    def held(self) -> bool:
        return self._file is not None

    def acquire(self) -> RunDirLock:
        if self._file is not None:
            return self
        self.run_dir.mkdir(parents=True, exist_ok=True)
        f = open(self.path, "a+", encoding="utf-8")  # "a+": opening must not wipe the current holder's details
        if fcntl is not None:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    # e.g. ENOLCK on a file system without locks: run unlocked rather than not at all
                    logger.warning(
                        "cannot lock %s (%s): the run directory is not protected from a second run", self.path, err
                    )
                else:
                    f.seek(0)
                    holder = _describe_holder(f.read(2000))
                    f.close()
                    raise FreamerError(
                        f"run dir {self.run_dir} is in use by another run ({holder}); wait for it to finish "
                        f"or use another run.name / --run-dir"
                    ) from None
        f.seek(0)
        f.truncate()
        f.write(json.dumps(_holder_info()) + "\n")
        f.flush()
        self._file = f
        return self

    def release(self) -> None:
        f, self._file = self._file, None
        if f is None:
            return
        try:
            f.seek(0)
            f.truncate()  # the details describe a holder only while it holds the lock
            if fcntl is not None:
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)
        except OSError as err:
            logger.debug("releasing %s: %s", self.path, err)
        finally:
            f.close()

    def __enter__(self) -> RunDirLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


# ----------------------------------------------------------------------------------------------------------------------
# SIGTERM
# ----------------------------------------------------------------------------------------------------------------------
class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C (checkpoint, then stop); the CLI exits with status 143."""


class SigtermToken:
    """What :func:`catch_sigterm` installed: the handler it replaced and where the stop stands.

    ``fired``: a SIGTERM has raised :class:`Terminated`. ``stopping``: the trainer caught it and is writing its
    checkpoint (:meth:`stopping_now`); until then a later SIGTERM raises again, since a library that catches every
    exception inside its own ``try`` may have swallowed the first (seen in a suite worker: the run kept training and
    ignored every later SIGTERM). :meth:`raise_if_fired` lets a loop stop at its next step in that case too."""

    def __init__(self, previous: Any) -> None:
        self.previous = previous
        self.fired = False
        self.stopping = False
        self.swallowed = 0  # SIGTERMs that raised but did not reach the trainer

    def stopping_now(self) -> None:
        """The trainer caught the interrupt: later SIGTERMs are logged and ignored so that its checkpoint completes."""
        self.stopping = True

    def raise_if_fired(self) -> None:
        """At a loop step: raise :class:`Terminated` again if a SIGTERM fired but never reached the trainer."""
        if self.fired and not self.stopping:
            self.swallowed += 1
            logger.warning("SIGTERM was caught inside a library and did not stop the run; stopping at this step")
            raise Terminated("SIGTERM")


def catch_sigterm() -> SigtermToken | None:
    """Make SIGTERM raise :class:`Terminated` in the main thread; returns the token for :func:`restore_sigterm`.

    Once the trainer is writing its interrupt checkpoint (:meth:`SigtermToken.stopping_now`), later SIGTERMs are
    logged and ignored so that the checkpoint completes; before that each one raises. Outside the main thread
    signals cannot be handled: no-op (None).
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    token = SigtermToken(None)

    def handler(signum: int, frame: object) -> None:
        if token.stopping:
            logger.warning("SIGTERM again: already stopping, finishing the checkpoint first")
            return
        if token.fired:
            token.swallowed += 1
            logger.warning("SIGTERM again: the first did not stop the run (caught inside a library); raising again")
        token.fired = True
        raise Terminated("SIGTERM")

    token.previous = signal.signal(signal.SIGTERM, handler)
    return token


@contextlib.contextmanager
def surfaced_interrupts() -> Iterator[None]:
    """Re-raise an error caused by a Ctrl-C / SIGTERM (:func:`interrupt_in_chain`) as that interrupt, so that the
    trainer's ``except KeyboardInterrupt`` checkpoints and stops as for any interrupt instead of the run failing."""
    try:
        yield
    except Exception as err:
        interrupt = interrupt_in_chain(err)
        if interrupt is None:
            raise
        raise interrupt from err


def restore_sigterm(token: Any) -> None:
    """Put back the SIGTERM handler that :func:`catch_sigterm` replaced."""
    if token is None:
        return
    signal.signal(signal.SIGTERM, token.previous if token.previous is not None else signal.SIG_DFL)


# ----------------------------------------------------------------------------------------------------------------------
# tables
# ----------------------------------------------------------------------------------------------------------------------
def write_rows_csv(path: str | Path, rows: list[dict], fields: list[str] | None = None) -> None:
    """Replace ``path`` atomically with ``rows`` as CSV (``fields``: the columns, default the union in order).

    No rows: an empty file (a fresh start truncates the previous attempt's table instead of appending to it).
    """

    if fields is None:
        fields = []
        for r in rows:
            fields += [k for k in r if k not in fields]
    if not rows:
        atomic_write_text(path, "")
        return
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: r.get(k) for k in fields})
    atomic_write_text(path, buf.getvalue())


def next_attempt_name(root: str | Path) -> str:
    """``attempt_NN`` for a new attempt's logger folder under ``root``: one more than the highest there.

    Each start or resume logs into its own folder instead of appending to (or rewriting) the previous attempt's
    files, which no TorchRL logger backend can do in general (tensorboard event files, wandb runs).
    """
    root = Path(root)
    numbers = [int(p.name[8:]) for p in root.glob("attempt_*") if p.name[8:].isdigit()] if root.is_dir() else []
    return f"attempt_{max(numbers, default=0) + 1:02d}"
