"""What a careless user types ends in one ``error:`` line and exit status 2: sizes too large, a shaping term the env
cannot provide; and ``--version``."""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

import pytest

from freamer_rl import __version__, cli
from freamer_rl.errors import ConfigError
from freamer_rl.trainers.registry import load_recipe

ROOT = Path(__file__).resolve().parents[2]
RECIPES = ROOT / "recipes"


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"freamer-rl {__version__}"


@pytest.mark.parametrize(
    "recipe, override, field",
    [
        ("baselines/ppo_mlp_n2s4.yaml", "network.hidden=1000000000", "network.hidden"),
        ("baselines/impala_n2s4.yaml", "network.hidden=1000000000", "network.hidden"),
        ("baselines/dreamer_v3_n2s4.yaml", "dreamer.batch_size=1000000000", "dreamer.batch_size"),
        ("baselines/dreamer_v3_n2s4.yaml", "dreamer.deter=1000000000", "dreamer.deter"),
    ],
)
def test_huge_baseline_sizes_are_refused_at_load(recipe, override, field, capsys):
    with pytest.raises(ConfigError, match=rf"^{field}: got 1000000000, expected an integer in \[1, "):
        load_recipe(RECIPES / recipe, [override])
    assert cli.main(["train", str(RECIPES / recipe), override]) == 2
    assert _one_error_line(capsys).startswith(f"error: {field}: got 1000000000")


def _limit_address_space() -> None:  # a failed allocation on any machine, never a swapping one
    resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))


def test_a_size_beyond_the_bound_is_refused_at_load(capsys):
    assert cli.main(["params", str(RECIPES / "tiny.yaml"), "model.embed_dim=1000000000"]) == 2
    assert _one_error_line(capsys) == "error: model.embed_dim: got 1000000000, expected an integer in [1, 16,384]"


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_AS")
def test_a_model_too_large_to_allocate_is_one_line(tmp_path):
    """Sizes within the bounds that still do not fit in memory (a 3 x 16k -> 16k concat MLP: 3.2 GB, under a
    limited address space): the allocation failure is named, no traceback."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "freamer_rl.cli",
            "train",
            str(RECIPES / "tiny.yaml"),
            "model.embed_dim=16384",
            "model.fusion=concat",
            "model.fusion_hidden=16384",
            "model.fno.modes=8",
            "--run-dir",
            str(tmp_path / "run"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=_limit_address_space,
    )
    assert done.returncode == 2, done.stderr[-2000:]
    err = done.stderr.strip().splitlines()
    assert err[-1].startswith("error: out of memory (") and "too large" in err[-1]
    assert "Traceback" not in done.stderr


def test_a_shaping_term_the_env_cannot_provide_is_refused(tmp_path, capsys):
    """R_lang parses a MiniGrid mission: on Crafter (no mission) ``shaping.language.weight`` is refused up front."""
    argv = ["train", str(RECIPES / "crafter_cpu.yaml"), "shaping.language.weight=0.2", "--run-dir", str(tmp_path)]
    assert cli.main(argv) == 2
    line = _one_error_line(capsys)
    assert line.startswith("error: shaping.language.weight: got 0.2, but env.adapter 'crafter' cannot provide R_lang")
    assert "shaping.language.weight=0" in line and "env.adapter minigrid" in line
