"""One run directory for every trainer: config.yaml, run_info.json and a TorchRL logger with the hyperparameters."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from freamer_rl.run.files import flatten_config
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config

TINY = Path(__file__).resolve().parents[2] / "recipes" / "tiny.yaml"


def test_minigrid_run_files_and_hyperparameters(tmp_path):
    run = tmp_path / "run"
    Trainer(load_config(TINY, ["logging.progress_bar=false", "optim.lr=7e-4"]), run).train()
    assert yaml.safe_load((run / "config.yaml").read_text())["optim"]["lr"] == 7e-4
    info = json.loads((run / "run_info.json").read_text())
    assert {"commit", "dirty", "torch", "torchrl", "tensordict", "command", "resumed_from"} <= set(info)
    # TorchRL's CSV logger writes log_hparams as "key: value" lines
    lines = (run / "metrics" / "attempt_01" / "texts" / "hparams0.txt").read_text().splitlines()
    assert "optim.lr: 0.0007" in lines and "model.modalities: ['state', 'language', 'reward']" in lines


def test_flatten_config_drops_none_and_stringifies_lists():
    assert flatten_config({"a": {"b": 1, "c": None, "d": [1, 2]}, "e": "x"}) == {"a.b": 1, "a.d": "[1, 2]", "e": "x"}
