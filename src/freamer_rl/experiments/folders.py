"""Output folders of suites and chains, checked before anything trains."""

from __future__ import annotations

import tempfile
from pathlib import Path

from freamer_rl.errors import ConfigError

__all__ = ["prepare_output_folder"]


def prepare_output_folder(folder: str | Path, field: str) -> Path:
    """Create ``folder`` (parents included) and prove it writable with a throw-away file.

    Raises:
        ConfigError: one line naming ``field`` and the folder when it cannot be created (a file in the way) or
            written (permissions, a read-only or full file system).
    """
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        reason = err.strerror or type(err).__name__
        where = f" ({err.filename})" if err.filename and str(err.filename) != str(folder) else ""
        raise ConfigError(
            f"{field}: cannot create or write the folder {folder}: {reason}{where}; expected a writable folder"
        ) from None
    return folder
