"""``freamer-rl health anomaly RUN --data FILE --labels LABELS.csv``: a tiny run trained here, a generated labelled
recording, the JSON of every metric, and the one-line errors for bad inputs."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from freamer_rl.data.anomaly_labels import write_anomaly_scenario
from freamer_rl.health.agent import load_agent
from freamer_rl.health.anomaly_report import recording_observations, recording_scores
from freamer_rl.health.cli import main
from freamer_rl.health.config import load_health_config
from freamer_rl.run import env_registry
from freamer_rl.trainers.health import train as train_health

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_health_pipeline import TINY as PIPELINE_TINY  # noqa: E402

# the pipeline tests' tiny sizes, an MLP encoder, two envs, one iteration of smaller batches
TINY = [
    *PIPELINE_TINY,
    "encoder.kind=mlp",
    "env.num_envs=2",
    "collect.iterations=1",
    "collect.prefill_frames=96",
    "collect.frames_per_iter=48",
    "imagination.num_seeds=8",
]
METRICS = (
    "events",
    "detected",
    "recall",
    "precision",
    "f1",
    "false_alarms",
    "fa_per_hour",
    "auroc",
    "auc_pr",
    "auroc_point_adjusted",
    "auc_pr_point_adjusted",
    "recall_by_kind",
    "raw_score",
    "z_score",
)


@pytest.fixture(scope="module")
def run_and_scenario(tmp_path_factory):
    orig = None
    if "health" not in env_registry.available_adapters():
        from freamer_rl_envs.health import make_health_env as factory

        orig = env_registry.get_env_factory
        env_registry.get_env_factory = lambda a: factory if a == "health" else orig(a)
    try:
        torch.manual_seed(0)
        run_dir = tmp_path_factory.mktemp("tiny_health")
        train_health(load_health_config(None, TINY), run_dir)
    finally:
        if orig is not None:
            env_registry.get_env_factory = orig
    scen = tmp_path_factory.mktemp("scenario")
    dat, labels = write_anomaly_scenario(scen, hours=3.0, seed=0, per_kind=1)
    return run_dir, scen, dat, labels


@pytest.mark.parametrize(
    "extra",
    [
        [],
        ["--statistic", "ema", "--ema-halflife", "100", "--k-sigma", "1.5"],
        ["--score", "prediction"],
        ["--score", "channel", "--stale-steps", "2"],
        ["--score", "hr_lag", "--stale-steps", "2", "--k-sigma", "8"],
    ],
)
def test_cli_scores_a_labelled_recording(run_and_scenario, tmp_path, capsys, extra):
    run_dir, scen, dat, labels = run_and_scenario
    argv = ["anomaly", str(run_dir), "--data", str(dat), "--labels", str(labels), "--out", str(tmp_path), *extra]
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    on_disk = json.loads((tmp_path / "anomaly_scores.json").read_text())
    assert printed == on_disk
    for key in METRICS:
        assert key in on_disk, key
    assert on_disk["events"] == 4 and set(on_disk["recall_by_kind"]) == {"hr_spike", "dropout", "drift", "arrhythmia"}
    assert on_disk["steps"] == 3 * 3600 // 5 and on_disk["hours"] == pytest.approx(3.0) and not on_disk["wraps"]
    assert on_disk["statistic"] == ("ema" if "ema" in extra else "running")
    assert on_disk["score"] == next((s for s in ("prediction", "channel", "hr_lag") if s in extra), "kl")
    for part in ("raw_score", "z_score"):
        for adj in ("strict", "point_adjusted"):
            assert 0.0 <= on_disk[part][adj]["auroc"] <= 1.0
    assert 0.0 <= on_disk["recall"] <= 1.0 and on_disk["fa_per_hour"] >= 0.0
    assert (tmp_path / "anomaly_timeline.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    arrays = np.load(tmp_path / "anomaly_scores.npz")
    assert arrays["flag"].sum() == on_disk["flagged_steps"] and arrays["label"].sum() == on_disk["anomalous_steps"]
    # the first step of every 48-step filter episode is never flagged
    assert not arrays["flag"][::48].any() and not arrays["valid"][::48].any()
    if "--stale-steps" in extra:
        # the 120 s dropout freezes the forward-filled observation for ~24 steps: all but its first 2 are stale,
        # every stale step is flagged, and only the dropout is stale
        ((start, end),) = arrays["events"][arrays["kinds"] == "dropout"]
        stale = arrays["stale"]
        assert on_disk["stale_flagged_steps"] == stale.sum() > 0 and arrays["flag"][stale].all()
        assert stale[start + 2 : end - 1].all() and stale.sum() <= end - start  # the last step may end after it
        assert on_disk["recall_by_kind"]["dropout"] == 1.0
    else:
        assert on_disk["stale_steps"] == 0 and on_disk["stale_flagged_steps"] == 0
    if "hr_lag" in extra:
        # the heart-rate lag predictor with the frozen-sensor check finds all four events and flags nothing else
        assert on_disk["recall"] == 1.0 and on_disk["false_alarms"] == 0, on_disk
    # the folder holding the one subject file works as --data too
    assert main([*argv[:3], str(scen), *argv[4:]]) == 0
    assert json.loads(capsys.readouterr().out)["recall"] == on_disk["recall"]


def error_lines(capsys):
    err = capsys.readouterr().err
    return [line for line in err.splitlines() if line.startswith("error:")]


@pytest.mark.parametrize(
    "labels_text, where",
    [
        ("start_s,end_s,kind\n100,200,hr_spike\n150,300,drift\n", "line 3: interval"),
        ("start_s,end_s,kind\n100,200,hr_spike\n300,x,drift\n", "line 3: end_s: not a finite number"),
        ("start_s,end_s,kind\n100,99999,hr_spike\n", "line 2: interval [100, 99999) s is outside the recording"),
    ],
)
def test_cli_bad_labels_give_one_error_line(run_and_scenario, tmp_path, capsys, labels_text, where):
    run_dir, _, dat, _ = run_and_scenario
    bad = tmp_path / "bad_labels.csv"
    bad.write_text(labels_text)
    assert main(["anomaly", str(run_dir), "--data", str(dat), "--labels", str(bad), "--out", str(tmp_path)]) == 2
    lines = error_lines(capsys)
    assert len(lines) == 1 and f"{bad}: {where}" in lines[0], lines


def test_cli_bad_data_and_flags_give_one_error_line(run_and_scenario, tmp_path, capsys):
    run_dir, _, _, labels = run_and_scenario
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["anomaly", str(run_dir), "--data", str(empty), "--labels", str(labels)]) == 2
    lines = error_lines(capsys)
    assert len(lines) == 1 and "no subjectNNN.dat files (expected subject101.dat .. subject109.dat)" in lines[0]
    assert main(["anomaly", str(run_dir), "--data", str(empty)]) == 2
    assert "--data and --labels" in error_lines(capsys)[0]
    assert main(["anomaly", str(run_dir), "--statistic", "ema", "--ema-halflife", "-1"]) == 2
    assert "--ema-halflife: expected a number of steps > 0" in error_lines(capsys)[0]


def test_observations_restart_the_reset_features():
    """Each filter episode starts as an env reset does: rate of change and cumulative exertion at 0."""
    from freamer_rl.data import pamap2_features, synthetic_recording

    feat = pamap2_features(synthetic_recording(101, duration_s=600.0, row_rate_hz=1.0), rate_hz=0.2)  # 120 steps
    obs, valid = recording_observations(feat, 50)
    assert obs["hr_features"].shape == (3, 50, 16) and valid.sum() == 120 and not valid[2, 20:].any()
    hr = obs["hr_features"]
    assert (hr[:, 0, 13] == 0).all() and (hr[:, 0, 14] == 0).all()
    # inside an episode the cumulative exertion grows by the loader's increments
    d_loader = np.diff(feat.hr_features[50:100, 14])
    np.testing.assert_allclose(np.diff(hr[1, :, 14]), d_loader, rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(obs["imu"].reshape(-1, 36)[:120], feat.imu)


def test_prediction_score_is_zero_where_the_observation_is_what_the_prior_expected(run_and_scenario):
    """The prior at a filter episode's first step does not depend on that step's observation (the latent and action
    are zeroed), so an observation equal to its decoded prior mean has prediction error 0 (up to float rounding),
    and any other observation a positive one."""
    agent = load_agent(run_and_scenario[0])
    wm = agent.world_model.eval()
    rng = np.random.default_rng(0)
    obs = {k: rng.normal(size=(2, 3, d)).astype(np.float32) for k, d in wm.obs_dims.items()}
    with torch.no_grad():
        h, z = wm.rssm.initial_state((1,))
        h0 = wm.rssm.transition(h, z, torch.zeros(1, wm.action_dim))  # what is_first makes of any previous state
        prior_mean, _ = wm.rssm.prior(h0)
        expected = wm.decode(torch.cat([h0, prior_mean], dim=-1))  # raw units
    before = recording_scores(agent, obs)
    for k in obs:
        obs[k][0, 0] = expected[k][0].numpy()
    after = recording_scores(agent, obs)
    assert after["prediction"][0, 0] == pytest.approx(0.0, abs=1e-6)
    assert before["prediction"][0, 0] > 1e-3 and after["prediction"][1, 0] == pytest.approx(before["prediction"][1, 0])
    assert after["kl"].shape == after["prediction"].shape == (2, 3)


def test_anomaly_sweep_calibrates_on_one_scenario_and_scores_another(run_and_scenario, tmp_path):
    """benchmarks/anomaly_sweep.py on the tiny run and two 3-hour scenarios: every score (and its frozen-sensor
    variant) gets the smallest k whose false alarms on the calibration scenario are within the limit, scored on the
    test scenario; the heart-rate lag predictor with the frozen-sensor check finds every event there."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "anomaly_sweep.py"
    spec = importlib.util.spec_from_file_location("anomaly_sweep", path)
    sweep = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sweep)
    out = tmp_path / "sweep"
    argv = [str(run_and_scenario[0]), "--out", str(out), "--hours", "3", "--k", "4", "8", "--stale-steps", "2"]
    sweep.main(argv)
    result = json.loads((out / "anomaly_sweep.json").read_text())
    labels = {"kl", "prediction", "channel", "hr_lag"}
    assert {r["score"] for r in result["calibrated"]} == labels | {f"{s}+stale" for s in labels}
    for best in result["calibrated"]:
        cal = {
            r["k"]: r["fa_per_hour"]
            for r in result["rows"]
            if r["score"] == best["score"] and r["scenario"] == "calibration"
        }
        ok = [k for k, fa in cal.items() if fa <= 1.0]
        assert best["k"] == (min(ok) if ok else max(cal)) and best["scenario"] == "test"
    hr_lag = next(r for r in result["calibrated"] if r["score"] == "hr_lag+stale")
    assert hr_lag["recall"] == 1.0, hr_lag
    assert "| hr_lag+stale |" in (out / "anomaly_sweep.md").read_text()
