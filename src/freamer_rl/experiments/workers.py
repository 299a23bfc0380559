"""The worker processes of a suite: spawned, one torch thread each, dying with the suite process.

:func:`worker_pool` starts them (shared by training and evaluation); :func:`submit_jobs` queues jobs to them (more can
be queued while earlier ones run) and :func:`collect_jobs` waits for them with one overall progress. A worker dies with
the suite, ``kill -9`` included: the kernel sends it SIGTERM when the parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``)
and a parent-pid watchdog covers the rest, so the trainer checkpoints and frees its run lock. When the suite stops
(SIGTERM, Ctrl-C), a shared event makes the jobs that ``ProcessPoolExecutor`` had already queued to a worker return
without running.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Any

import torch

from freamer_rl.errors import FreamerError
from freamer_rl.experiments.progress import OverallProgress
from freamer_rl.run.rundir import Terminated, catch_sigterm, restore_sigterm

logger = logging.getLogger(__name__)

__all__ = ["collect_jobs", "error_line", "submit_jobs", "worker_pool"]

_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_ORPHAN_GRACE_S = 60.0  # an orphaned worker's time to checkpoint after SIGTERM before it exits regardless
# In a worker: set once the suite stops (the suite's shared event) or the worker is orphaned (its own), so that the
# jobs ProcessPoolExecutor had already queued to it return at once instead of training after the SIGTERM
_SUITE_STOP: Any = None
_ORPHANED = threading.Event()


def _watch_parent(parent: int) -> None:
    """Watchdog thread of a worker: once the suite process is gone (the worker was re-parented), SIGTERM itself (the
    trainer checkpoints and stops, releasing its run lock), then exit after a grace period in any case."""
    while os.getppid() == parent:
        time.sleep(1.0)
    _ORPHANED.set()
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(_ORPHAN_GRACE_S)
    os._exit(143)


def _init_worker(parent: int, stop: Any = None) -> None:
    """Worker start: one torch thread; die with the suite process, even when it is killed with ``kill -9`` (a worker
    left training would hold its run lock, so a rerun would be refused): the kernel sends SIGTERM when the parent dies
    (Linux ``prctl(PR_SET_PDEATHSIG)``), and a parent-pid watchdog thread covers other systems and a parent that died
    before the ``prctl``. ``stop``: the suite's stop event (see :func:`_unless_stopped`)."""
    global _SUITE_STOP
    _SUITE_STOP = stop
    torch.set_num_threads(1)
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError) as err:  # no prctl: the watchdog alone
            logger.debug("prctl(PR_SET_PDEATHSIG) unavailable: %s", err)
    threading.Thread(target=_watch_parent, args=(parent,), name="suite-parent-watchdog", daemon=True).start()


def _unless_stopped(worker: Any, payload: dict[str, Any]) -> dict[str, Any]:
    """Worker: ``worker(payload)``, unless the suite has stopped (SIGTERM) or this worker is orphaned; then nothing
    runs (the suite no longer reads the result, and nothing is recorded for a job that never started)."""
    if _ORPHANED.is_set() or (_SUITE_STOP is not None and _SUITE_STOP.is_set()):
        return {"ok": False, "error": "the suite stopped before this job started", "seconds": 0.0}
    return worker(payload)


@contextmanager
def worker_pool(jobs: int) -> Iterator[ProcessPoolExecutor]:
    """The suite's spawned workers, ``jobs`` at most (started on demand, one torch thread each), shared by training
    and evaluation; every exit stops them, and a SIGTERM is passed on to them (Ctrl-C reaches them itself)."""
    token = catch_sigterm()
    context = mp.get_context("spawn")
    stop = context.Event()
    pool = ProcessPoolExecutor(
        max_workers=jobs, mp_context=context, initializer=_init_worker, initargs=(os.getpid(), stop)
    )
    try:
        yield pool
    except KeyboardInterrupt as err:
        if token is not None:  # later SIGTERMs wait for the workers' checkpoints
            token.stopping_now()
        stop.set()  # the jobs already queued to a worker return at once (cancel_futures cannot reach those)
        if isinstance(err, Terminated):
            for process in list(getattr(pool, "_processes", {}).values()):
                process.terminate()
        raise
    finally:  # every exit, an unexpected error included, stops the workers
        restore_sigterm(token)
        pool.shutdown(wait=True, cancel_futures=True)


def submit_jobs(pool: ProcessPoolExecutor, worker: Any, payloads: list[dict], start: int = 0) -> dict[Future, int]:
    """Queue ``worker(payload)`` for every payload (in order, behind what the pool already holds); returns each
    future with its index, counted from ``start``."""
    return {pool.submit(_unless_stopped, worker, payload): start + i for i, payload in enumerate(payloads)}


def collect_jobs(futures: dict[Future, int], desc: str, weights: list[int | None], item: str, on_result: Any) -> None:
    """Wait for every queued job with one overall progress (``weights``: as :class:`OverallProgress`, one per
    index); ``on_result(index, future) -> (ok, note)`` reads each outcome as it finishes."""
    progress = OverallProgress(desc, weights, item=item)
    try:
        for future in as_completed(futures):
            index = futures[future]
            ok, note = on_result(index, future)
            if not ok:
                progress.warn(f"{desc}: {note}")
            progress.advance(index, note)
    finally:
        progress.close()


def error_line(err: BaseException) -> str:
    """One line for a job's failure: the message of a FreamerError, else ``Type: message``."""
    text = " ".join(str(err).split()) or "(no message)"
    return text if isinstance(err, FreamerError) else f"{type(err).__name__}: {text}"
