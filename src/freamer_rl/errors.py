"""User-facing error types. The CLI prints these as one line and exits non-zero (no traceback)."""

from __future__ import annotations


class FreamerError(Exception):
    """Base class of errors caused by user input (recipes, env ids, weights, checkpoints)."""


class EnvSetupError(FreamerError, ValueError):
    """The requested environment cannot be built or lacks an observation a modality needs."""


class CheckpointError(FreamerError, RuntimeError):
    """A checkpoint is missing, unreadable, or was saved with a different model configuration."""


class ConfigError(FreamerError, ValueError):
    """A recipe or override is invalid; the message names the dotted field."""
