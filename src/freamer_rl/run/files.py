"""The files every run directory holds, written the same way by every trainer (MiniGrid/gym PPO, health):

<run_dir>/config.yaml          the resolved config
<run_dir>/run_info.json        git commit (and whether the tree was dirty), versions, command, resumed_from
<run_dir>/metrics/attempt_NN/  the TorchRL logger of one start or resume, with the resolved config logged as
                               hyperparameters (one folder per attempt: an attempt killed after its last
                               checkpoint logged steps that the next attempt logs again; progress.csv is the
                               deduplicated record)
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import tensordict
import torch
import torchrl
import yaml
from torchrl.record.loggers import get_logger

from freamer_rl.errors import FreamerError
from freamer_rl.run.checkpoint import atomic_write_text, run_file_errors
from freamer_rl.run.rundir import next_attempt_name

logger = logging.getLogger(__name__)

__all__ = ["flatten_config", "git_commit", "make_metrics_logger", "write_run_files"]


def git_commit() -> dict[str, Any]:
    """``{"commit": sha, "dirty": bool}`` of the checkout the library runs from (None values outside git)."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        dirty = bool(
            subprocess.run(
                ["git", "status", "--porcelain"], cwd=here, capture_output=True, text=True, timeout=5
            ).stdout.strip()
        )
        return {"commit": sha, "dirty": dirty}
    except (OSError, subprocess.SubprocessError) as err:
        logger.warning("could not read the git commit (%s); run_info.json records none", err)
        return {"commit": None, "dirty": None}


def write_run_files(run_dir: Path, config: dict, resumed_from: Path | None) -> None:
    """``config.yaml`` and ``run_info.json``, each replaced atomically."""
    atomic_write_text(run_dir / "config.yaml", yaml.safe_dump(config, sort_keys=False))
    info = {
        **git_commit(),
        "command": sys.argv,
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "tensordict": tensordict.__version__,
        "resumed_from": str(resumed_from) if resumed_from else None,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    atomic_write_text(run_dir / "run_info.json", json.dumps(info, indent=2))


def flatten_config(d: dict, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}} -> {"a.b": 1}``; lists become strings, None values are left out (loggers take scalars)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_config(v, key + "."))
        elif v is not None:
            out[key] = str(v) if isinstance(v, (list, tuple)) else v
    return out


def make_metrics_logger(run_dir: Path, backend: str, config: dict, *, option: str):
    """The TorchRL logger (``csv | wandb | tensorboard``) of this attempt, ``metrics/attempt_NN``, with ``config``
    logged as hyperparameters. wandb runs offline unless ``WANDB_MODE=online`` and keeps its files in the attempt's
    folder too (``metrics/attempt_NN/wandb``). ``option`` names the config field for the error when the backend's
    package is missing."""
    kwargs: dict[str, Any] = {}
    root = run_dir / "metrics"
    attempt = next_attempt_name(root)
    log_dir = root
    if backend == "wandb":
        # wandb writes into its log_dir (torchrl passes it as wandb's `dir`): the attempt's folder, not the run dir
        log_dir = root / attempt
        kwargs["wandb_kwargs"] = {
            "offline": os.environ.get("WANDB_MODE", "offline") == "offline",
            "project": "freamer_rl",
        }
    try:
        with run_file_errors(log_dir):
            metrics = get_logger(backend, logger_name=str(log_dir), experiment_name=attempt, **kwargs)
    except ImportError as err:
        raise FreamerError(
            f"{option} '{backend}' needs an optional package: from a checkout, pip install -c constraints.txt -e "
            f'".[{backend}]"; from PyPI, pip install "freamer_rl[{backend}]" ({err})'
        ) from err
    logger.info("metrics of this attempt: %s", root / attempt)
    metrics.log_hparams(flatten_config(config))
    return metrics
