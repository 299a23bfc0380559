"""Overall progress of a suite (over its runs) or a chain (over its stages), with an ETA."""

from __future__ import annotations

import logging
import sys
import time

from tqdm.auto import tqdm

logger = logging.getLogger(__name__)

__all__ = ["OverallProgress"]


def _on_terminal() -> bool:
    return all(getattr(s, "isatty", lambda: False)() for s in (sys.stdout, sys.stderr))


def _duration(seconds: float) -> str:
    seconds = max(int(seconds), 0)
    hours, rest = divmod(seconds, 3600)
    return f"{hours}h{rest // 60:02d}m" if hours else f"{rest // 60}m{rest % 60:02d}s"


class OverallProgress:
    """A tqdm bar with ETA on a terminal; otherwise one log line per finished item with the share done and an ETA.

    ``weights[i]``: the frames item ``i`` still has to train; when any is unknown (``None``) the items are counted
    instead. The ETA assumes the remaining items train at the rate of the finished ones.
    """

    def __init__(self, desc: str, weights: list[int | None], *, item: str = "runs") -> None:
        self.frames = bool(weights) and all(w is not None and w > 0 for w in weights)
        self.weights = [int(w) for w in weights] if self.frames else [1] * len(weights)  # type: ignore[arg-type]
        self.total = max(sum(self.weights), 1)
        self.desc, self.item = desc, item
        self.done = self.finished = 0
        self.t0 = time.perf_counter()
        self._bar = None
        if _on_terminal():
            self._bar = tqdm(
                total=self.total,
                desc=desc,
                unit="frames" if self.frames else item,
                unit_scale=self.frames,
                dynamic_ncols=True,
            )

    def eta_s(self) -> float | None:
        """Seconds left at the rate so far; None before the first item finished."""
        if not self.done:
            return None
        return (time.perf_counter() - self.t0) * (self.total - self.done) / self.done

    def advance(self, index: int, note: str) -> None:
        """Item ``index`` finished (or failed); ``note`` says which and how."""
        self.finished += 1
        self.done = min(self.done + self.weights[index], self.total)
        if self._bar is not None:
            self._bar.update(self.weights[index])
            self._bar.set_postfix_str(note)
            return
        eta = self.eta_s()
        logger.info(
            "%s: %d/%d %s finished (%.0f%%%s) | ETA %s | %s",
            self.desc,
            self.finished,
            len(self.weights),
            self.item,
            100.0 * self.done / self.total,
            " of the frames" if self.frames else "",
            "n/a" if eta is None else _duration(eta),
            note,
        )

    def warn(self, message: str) -> None:
        """A warning that does not break the bar."""
        if self._bar is not None:
            self._bar.write(message, file=sys.stderr)
        else:
            logger.warning("%s", message)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
