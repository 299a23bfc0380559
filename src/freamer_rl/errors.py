"""User-facing error types. The CLI prints these as one line and exits non-zero (no traceback).

Also :func:`interrupt_in_chain`, which every layer that catches broad exceptions uses so that a Ctrl-C / SIGTERM is
never mistaken for an error."""

from __future__ import annotations


class FreamerError(Exception):
    """Base class of errors caused by user input (recipes, env ids, weights, checkpoints)."""


class EnvSetupError(FreamerError, ValueError):
    """The requested environment cannot be built or lacks an observation a modality needs."""


class CheckpointError(FreamerError, RuntimeError):
    """A checkpoint is missing, unreadable, or was saved with a different model configuration."""


class ConfigError(FreamerError, ValueError):
    """A recipe or override is invalid; the message names the dotted field."""


def interrupt_in_chain(err: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C / SIGTERM (:class:`KeyboardInterrupt`) behind ``err``: ``err`` itself or one of its causes /
    contexts (a library that catches every exception inside its own ``try`` turns an interrupt raised there into
    its own error, e.g. a RuntimeError whose ``__context__`` is :class:`Terminated`); None if there is none."""
    seen: set[int] = set()
    e: BaseException | None = err
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None
