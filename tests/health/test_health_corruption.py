"""Sensor corruption on the health task (issue 22, part 5): a corruption restricted to a slice of a key (one IMU site),
the corrupted real-env evaluation of a trained health agent, the corruption sweep and its bad input."""

import csv
import json
import re
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from freamer_rl import cli
from freamer_rl.config.sections import CorruptionConfig
from freamer_rl.errors import ConfigError
from freamer_rl.experiments.health_corruption import difference_ci
from freamer_rl.health.agent import load_agent
from freamer_rl.health.config import load_health_config
from freamer_rl.health.evaluation import evaluate_checkpoint, evaluate_policy
from freamer_rl.run import env_registry
from freamer_rl.run.corruption import ModalityCorruption, corruption_transforms
from freamer_rl.trainers.health import train as train_health

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_health_pipeline import RECIPES  # noqa: E402
from test_health_pipeline import TINY as PIPELINE_TINY  # noqa: E402

from freamer_rl_envs.health import make_health_env  # noqa: E402

TINY = [*PIPELINE_TINY, "collect.iterations=1"]


@pytest.fixture(autouse=True)
def health_adapter(monkeypatch):
    """Use the registered ``health`` entry point; until the project is reinstalled with it, register it here."""
    if "health" not in env_registry.available_adapters():
        orig = env_registry.get_env_factory
        monkeypatch.setattr(env_registry, "get_env_factory", lambda a: make_health_env if a == "health" else orig(a))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two tiny trained health runs, one per encoder compared by the sweep."""
    if "health" not in env_registry.available_adapters():
        pytest.skip("the health adapter is not installed (entry point freamer_rl.envs: health)")
    root = tmp_path_factory.mktemp("health_corrupt")
    out = {}
    for kind in ("mlp", "foundation"):
        torch.manual_seed(0)
        train_health(load_health_config(RECIPES[kind], TINY), root / kind)
        out[kind] = root / kind
    return out


# -- the slice of a key ------------------------------------------------------------------------------------------------
def test_gaussian_on_a_slice_changes_only_the_slice_with_the_slice_std():
    torch.manual_seed(0)
    x = torch.randn(20_000, 36)
    x[:, 12:24] *= 5.0  # the chest site: std 5; the rest std 1
    t = ModalityCorruption("imu", "gaussian", 2.0, channels=(12, 24))
    out = t._corrupt(TensorDict({"imu": x.clone()}, batch_size=[20_000]), None)["imu"]
    assert torch.equal(out[:, :12], x[:, :12]) and torch.equal(out[:, 24:], x[:, 24:])
    assert abs(t.running_std - 5.0) < 0.1  # the slice's std, not the whole key's (~3)
    noise_std = (out[:, 12:24] - x[:, 12:24]).std()
    assert abs(noise_std - 2.0 * 5.0) < 0.2, noise_std


def test_dropout_of_a_site_zeroes_exactly_those_channels():
    torch.manual_seed(0)
    x = torch.rand(64, 36) + 0.5
    t = ModalityCorruption("imu", "dropout", 1.0, channels=(0, 12))
    td = t._corrupt(TensorDict({"imu": x.clone()}, batch_size=[64]), None)
    assert (td["imu"][:, :12] == 0).all() and torch.equal(td["imu"][:, 12:], x[:, 12:])
    assert (td["imu_0_12_present"] == 0).all()


def test_the_key_form_and_the_channels_field_agree():
    a = corruption_transforms([CorruptionConfig(key="imu[24:36]", kind="stale", level=3)], None)[0]
    b = corruption_transforms([CorruptionConfig(key="imu", kind="stale", level=3, channels=[24, 36])], None)[0]
    assert (a.key, a.channels) == (b.key, b.channels) == ("imu", (24, 36))


@pytest.mark.parametrize(
    ("entry", "match"),
    [
        ({"key": "imu[12:4]"}, r"env\.corrupt\[0\]\.channels: expected 0 <= start < stop"),
        ({"key": "imu[0:x]"}, r"env\.corrupt\[0\]\.key: .*KEY\[start:stop\]"),
        ({"key": "imu", "channels": [3]}, r"env\.corrupt\[0\]\.channels: expected \[start, stop\]"),
        ({"key": "imu[0:12]", "channels": [0, 6]}, r"env\.corrupt\[0\]\.channels: \[0, 6\] disagrees"),
    ],
)
def test_bad_slices_name_the_field(entry, match):
    with pytest.raises(ConfigError, match=match):
        corruption_transforms([CorruptionConfig(**entry)], None)


# -- the corrupted evaluation of a trained agent ------------------------------------------------------------------------
def test_level_zero_equals_the_clean_evaluation_exactly(runs):
    """Sampled actions: a level-0 gaussian draws nothing, so every number equals the clean evaluation's."""
    results = []
    for corrupt in ([], [CorruptionConfig(key="imu[0:12]", kind="gaussian", level=0.0, when="eval")]):
        torch.manual_seed(3)
        results.append(evaluate_checkpoint(runs["mlp"], episodes=2, deterministic=False, corrupt=corrupt))
    clean, zero = ({k: v for k, v in r.items() if k != "corrupt"} for r in results)
    assert clean == zero
    torch.manual_seed(3)
    noisy = evaluate_checkpoint(
        runs["mlp"], episodes=2, deterministic=False, corrupt=[CorruptionConfig("imu[0:12]", "gaussian", 4.0, "eval")]
    )
    assert noisy["kl_mean"] != clean["kl_mean"]  # the filter read the noisy hand IMU


def test_the_agent_reads_the_corrupted_observations(runs):
    agent = load_agent(runs["foundation"])
    drop = [CorruptionConfig(key="imu[0:12]", kind="dropout", level=1.0, when="eval")]
    _, traj = evaluate_policy(agent, num_envs=2, seed=5, deterministic=True, corrupt=drop)
    _, clean = evaluate_policy(agent, num_envs=2, seed=5, deterministic=True)
    imu = traj["imu"]  # what the policy's filter read at every step (the rollout records its inputs)
    assert (imu[..., :12] == 0).all() and (clean["imu"][..., :12] != 0).any()
    assert torch.equal(imu[:, 0, 12:], clean["imu"][:, 0, 12:])  # the first observation: only the hand is gone
    assert not torch.equal(traj["kl"], clean["kl"])


# -- the sweep ----------------------------------------------------------------------------------------------------------
def test_sweep_writes_the_table_per_run_and_level(runs, tmp_path, capsys):
    out = tmp_path / "sweep"
    argv = ["health", "corruption", str(runs["mlp"]), str(runs["foundation"]), "--key", "imu[0:12]"]
    assert cli.main([*argv, "--levels", "0,1", "--episodes", "2", "--out", str(out)]) == 0
    with open(out / "corruption.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted((r["encoder"], float(r["level"])) for r in rows) == [
        ("foundation", 0.0),
        ("foundation", 1.0),
        ("mlp", 0.0),
        ("mlp", 1.0),
    ]
    assert all(float(r["R"]) == 1.0 for r in rows if float(r["level"]) == 0)  # level 0 is the clean evaluation
    data = json.loads((out / "corruption.json").read_text())
    assert [d["level"] for d in data["differences"]] == [0.0, 1.0]
    assert data["differences"][0]["R_diff"] == 0.0
    md = (out / "corruption.md").read_text()
    assert "## foundation - mlp per level" in md and "| mlp | 1 | 1 |" in md and "| foundation | 0 | 1 |" in md


def test_difference_ci_is_the_iqm_difference_with_a_bracketing_interval():
    d, low, high = difference_ci([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    assert d == 2.0 and 1.0 <= low <= d <= high <= 3.0
    assert difference_ci([5.0], [2.0]) == (3.0, 3.0, 3.0)  # one run each: no spread to resample


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--key", "heart_rate"], r"env\.corrupt\[0\]\.key: the health agent reads imu, hr_features"),
        (["--key", "imu[0:40]"], r"env\.corrupt\[0\]\.channels: \[0, 40\] does not fit 'imu'"),
        (["--key", "imu", "--kind", "salt", "--levels", "0.5"], r"kind: salt replaces integer entries"),
        (["--key", "imu", "--levels", "0,abc"], r"--levels: expected comma-separated numbers"),
        (["--key", "imu", "--kind", "dropout", "--levels", "2"], r"corruption\.level: dropout needs"),
        (["--key", "imu[1:]"], r"corruption\.key: 'imu\[1:\]'"),
    ],
)
def test_sweep_bad_input_is_one_error_line(runs, tmp_path, capsys, extra, match):
    argv = ["health", "corruption", str(runs["mlp"]), *extra, "--episodes", "1", "--out", str(tmp_path / "o")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert re.search(match, err[0]), err[0]


def test_eval_of_a_health_run_takes_corrupt(runs, capsys):
    argv = ["eval", str(runs["mlp"]), "--episodes", "2", "--corrupt", "hr_features:noisy_tv:0.5"]
    assert cli.main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["corrupt"][0]["key"] == "hr_features" and out["episodes"] == 2
