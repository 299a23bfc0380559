"""The benchmarks: every shipped suite (recipes/suites/) plans, the suites' PPO-MLP recipes stand beside the FreamerV1
runs they are compared with, and the suite report's health table (tiny budgets; the real figures come from the
benchmark commands; a curriculum chain as a suite entry: tests/experiments/test_suite.py)."""

import json
import os
import statistics
from pathlib import Path

import pytest
import torch

from freamer_rl.experiments.chain import is_chain
from freamer_rl.experiments.report import RunRecord, write_report
from freamer_rl.experiments.suite import describe, load_suite, plan_suite, run_suite
from freamer_rl.trainers.baselines.common import build_network
from freamer_rl.trainers.registry import load_recipe

ROOT = Path(__file__).resolve().parents[2]
SUITES = sorted((ROOT / "recipes" / "suites").glob("*.yaml"))


@pytest.mark.parametrize("path", SUITES, ids=[p.stem for p in SUITES])
def test_every_shipped_suite_plans(path, tmp_path):
    """What ``freamer-rl suite <file> --dry-run`` checks: every run's config loads (trainer, overrides, env id)."""
    suite, root, runs = plan_suite(path, tmp_path / "out")
    assert root == tmp_path / "out"
    seeds = sum(len(e.seeds if e.seeds is not None else suite.seeds) for e in suite.entries)  # an entry's own seeds
    assert len(runs) == seeds * max(1, len(suite.envs))
    assert [r.error for r in runs if r.error] == []
    assert {row["status"] for row in describe(runs)} == {"new"}
    if suite.total_frames is not None:  # an entry's own run.total_frames override wins over the suite's
        own = {e.label for e in suite.entries if any(o.startswith("run.total_frames=") for o in e.overrides)}
        own |= {e.label for e in suite.entries if is_chain(e.recipe)}  # a chain's stages have their own caps
        assert {r.target_frames for r in runs if r.label not in own} == {suite.total_frames}


def test_suites_name_their_results_folder_after_themselves():
    """Two suites never share a results folder (each defaults to results/<name>)."""
    names = [load_suite(p).name for p in SUITES]
    assert sorted(names) == sorted(p.stem for p in SUITES)


@pytest.mark.parametrize("task", ["cartpole", "pendulum"])
@pytest.mark.parametrize("kind", ["mlp", "mlp_lstm"])
def test_gym_baseline_recipes_differ_from_freamer_only_in_the_network(task, kind):
    """The PPO-MLP and PPO-LSTM of the gym suites train with the FreamerV1 recipe's env, PPO settings, optimiser and
    budget (the recurrent one with its sequence length too)."""
    _, freamer = load_recipe(ROOT / "recipes" / "gym" / f"{task}.yaml")
    name, mlp = load_recipe(ROOT / "recipes" / "baselines" / f"ppo_{kind.split('_')[-1]}_{task}.yaml")
    assert name == "ppo_baseline" and mlp.network.kind == kind and mlp.network.observation_keys == ["observation"]
    assert (mlp.env.adapter, mlp.env.id, mlp.env.num_envs) == (
        freamer.env.adapter,
        freamer.env.id,
        freamer.env.num_envs,
    )
    # feed-forward PPO steps need no sequence layout
    fields = [f for f in vars(freamer.ppo) if kind == "mlp_lstm" or f != "sequence_length"]
    assert {f: getattr(mlp.ppo, f) for f in fields} == {f: getattr(freamer.ppo, f) for f in fields}
    assert vars(mlp.optim) == vars(freamer.optim)
    assert mlp.shaping.reward_scale == freamer.shaping.reward_scale  # the same value targets
    assert mlp.run.total_frames == freamer.run.total_frames


@pytest.mark.parametrize(
    "recipe,init",
    [("ppo_mlp_n2s4", "torch_default"), ("ppo_mlp_cartpole", "torch_default"), ("impala_n2s4", "orthogonal")],
)
def test_baseline_recipes_build_the_init_they_name(recipe, init):
    """PyTorch's init: every Linear weight and bias inside U(+-1/sqrt(fan_in)), biases not zero; orthogonal: zero
    biases and the encoder's weight orthogonal with gain sqrt 2."""
    _, cfg = load_recipe(ROOT / "recipes" / "baselines" / f"{recipe}.yaml")
    net = build_network(cfg)
    linears = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
    assert len(linears) == 6  # two encoders (shared: false), two layers per head
    for layer in linears:
        bound = layer.in_features**-0.5
        if init == "torch_default":
            assert layer.weight.abs().max() <= bound and layer.bias.abs().max() <= bound
            assert layer.bias.abs().max() > 0
        else:
            assert layer.bias.abs().max() == 0
    if init == "orthogonal":
        w = linears[0].weight.detach()  # the encoder's [256, 148]: orthogonal columns (rows where it is wide)
        gram = w.T @ w if w.shape[0] >= w.shape[1] else w @ w.T
        torch.testing.assert_close(gram, 2.0 * torch.eye(gram.shape[0]), atol=1e-4, rtol=0)


def _suite_file(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "suite.yaml"
    path.write_text(body.replace("RECIPES", os.path.relpath(ROOT / "recipes", tmp_path)))
    return path


def test_gym_suite_trains_ppo_baseline_discrete_and_continuous(tmp_path):
    """The gym suites' PPO-MLP (CartPole's categorical head, Pendulum's TanhNormal one) trains through
    ``freamer-rl suite``, reports a return, and a rerun trains nothing."""
    path = _suite_file(
        tmp_path,
        "name: gym_smoke\nseeds: [0]\ntotal_frames: 512\n"
        "overrides: [env.num_envs=2, ppo.frames_per_batch=256, ppo.minibatch_size=128, ppo.epochs=1]\n"
        "entries:\n  - {label: cartpole, recipe: RECIPES/baselines/ppo_mlp_cartpole.yaml}\n"
        "  - {label: pendulum, recipe: RECIPES/baselines/ppo_mlp_pendulum.yaml}\n",
    )
    out = run_suite(path, jobs=1, output=tmp_path / "out")
    assert out["failed"] == [] and len(out["trained"]) == 2
    rows = {r["label"]: r for r in out["runs"]}
    assert {r["status"] for r in rows.values()} == {"done"}
    for label in ("cartpole", "pendulum"):
        summary = json.loads((Path(rows[label]["run_dir"]) / "summary.json").read_text())
        assert summary["trainer"] == "ppo_baseline" and summary["frames"] == 512
        assert rows[label]["return_mean"] == pytest.approx(summary["final_return_mean"])
    text = (tmp_path / "out" / "summary.md").read_text()
    assert "| cartpole | CartPole-v1 |" in text and "| pendulum | Pendulum-v1 |" in text
    assert "final success" not in text  # neither env has a notion of success
    assert (tmp_path / "out" / "curve_CartPole-v1_return_mean.png").is_file()
    assert run_suite(path, jobs=1, output=tmp_path / "out")["trained"] == []


def _health_run(root: Path, label: str, seed: int, values: dict) -> RunRecord:
    run_dir = root / "runs" / label / "pamap2-health" / f"seed{seed}"
    run_dir.mkdir(parents=True)
    (run_dir / "summary.json").write_text(json.dumps({"frames": 1024, "episodes": 8, **values}))
    (run_dir / "done.json").write_text(json.dumps({"total_frames": None, "frames": 1024}))
    return RunRecord(label=label, env="pamap2-health", env_dir="pamap2-health", seed=seed, run_dir=run_dir)


def test_report_adds_the_health_table_from_the_runs_summaries(tmp_path):
    """Table 15's columns: mean +- sample std across seeds of each summary.json metric, the encoder's parameters,
    the reward difference to the first label, the reward's bootstrap interval, per-seed values and the ratio to the
    first label with its interval."""
    returns = {"mlp": [50.0, 60.0, 64.0], "foundation": [48.0, 52.0, 53.0]}
    records = []
    for label, rets in returns.items():
        for seed, ret in enumerate(rets):
            records.append(
                _health_run(
                    tmp_path,
                    label,
                    seed,
                    {
                        "eval_return_mean": ret,
                        "eval_violations_mean": 0.5 * seed,
                        "recon_mse": 0.25,
                        "imagination_horizon": 10.0 + seed,
                        "eval_fraction_of_oracle": 0.5 + 0.1 * seed,
                        "params_encoder": 1234 if label == "mlp" else 5678,
                    },
                )
            )
    write_report(tmp_path, "health_demo", records)
    text = (tmp_path / "summary.md").read_text()
    assert "## Health world model (paper Table 15)" in text
    table = text.split("## Health world model (paper Table 15)")[1]
    rows = {line.split(" | ")[0].strip("| "): line for line in table.splitlines() if line.startswith("| ")}
    mlp, foundation = returns["mlp"], returns["foundation"]
    assert (
        f"| mlp | 3 | {statistics.mean(mlp):.1f} +- {statistics.stdev(mlp):.1f} | 0.50 +- 0.50 | 0.250 +- 0.000 "
        f"| 11.0 +- 1.0 | 0.600 +- 0.100 |  |  |  | 1,234 |  |" in rows["mlp"]  # no rule or rank columns here
    )
    delta = statistics.mean(foundation) - statistics.mean(mlp)
    assert f"| 5,678 | {delta:+.1f} | {statistics.mean(foundation):.1f} [" in rows["foundation"]
    assert "| 48.0 / 52.0 / 53.0 |" in rows["foundation"] and rows["mlp"].endswith("| 50.0 / 60.0 / 64.0 |  |")
    # the reward's bootstrap interval holds the mean, and the ratio's holds the ratio of means
    cells = rows["foundation"].strip("| ").split(" | ")
    low, high = (float(v) for v in cells[-3].split("[")[1].rstrip("]").split(", "))
    assert low <= statistics.mean(foundation) <= high and low >= 48.0 and high <= 53.0
    ratio, bounds = cells[-1].split(" [")
    r_low, r_high = (float(v) for v in bounds.rstrip("]").split(", "))
    assert float(ratio) == round(statistics.mean(foundation) / statistics.mean(mlp), 2)
    assert r_low <= float(ratio) <= r_high and r_low >= 48.0 / 64.0 and r_high <= 53.0 / 50.0
    header = (tmp_path / "runs.csv").read_text().splitlines()[0].split(",")
    assert header[-10:] == [  # a health column appears only when some run has it (no rule or rank values here)
        "eval_return_mean",
        "eval_violations_mean",
        "recon_mse",
        "imagination_horizon",
        "eval_fraction_of_oracle",
        "params_encoder",
        "encoder",
        "eval_subjects",
        "error",
        "run_dir",
    ]
    assert "Leave-one-subject-out" not in text  # no run names its held-out subjects


def test_report_adds_the_loso_overall_row_per_encoder(tmp_path):
    """Leave-one-subject-out: per encoder, the reward over the folds (the mean of the fold means, whatever the seeds
    done per fold) with a two-level bootstrap interval inside the folds' range, and each fold's mean."""
    folds = {("mlp", 101): [80.0, 82.0], ("mlp", 102): [70.0], ("foundation", 101): [90.0, 92.0, 94.0]}
    folds[("foundation", 102)] = [60.0, 62.0]
    records = []
    for (enc, subject), rets in folds.items():
        for seed, ret in enumerate(rets):
            values = {"eval_return_mean": ret, "encoder": enc, "eval_subjects": [subject]}
            records.append(_health_run(tmp_path, f"{enc}_fold{subject}", seed, values))
    # an encoder evaluated on one held-out set only gets no overall row
    records.append(
        _health_run(tmp_path, "cnn_fold101", 0, {"eval_return_mean": 1.0, "encoder": "cnn", "eval_subjects": [101]})
    )
    write_report(tmp_path, "loso_demo", records)
    section = (tmp_path / "summary.md").read_text().split("## Leave-one-subject-out, overall (per encoder)")[1]
    rows = {
        line.split(" | ")[0].strip("| "): line.strip("| ").split(" | ")
        for line in section.splitlines()
        if line.startswith("| ") and not line.startswith("| encoder")
    }
    assert set(rows) == {"mlp", "foundation"}
    enc, n_folds, runs, reward, rule, oracle, vs_rule, vs_controller, of_oracle, at_rule, per_fold = rows["mlp"]
    assert (n_folds, runs, per_fold) == ("2", "3", "101: 81.0, 102: 70.0")
    # these runs record no references
    assert (rule, oracle, vs_rule, vs_controller, of_oracle, at_rule) == ("", "", "", "", "", "")
    point, bounds = reward.split(" [")
    low, high = (float(v) for v in bounds.rstrip("]").split(", "))
    assert float(point) == 75.5  # (81 + 70) / 2, not the pooled (80 + 82 + 70) / 3
    assert 70.0 <= low <= 75.5 <= high <= 82.0
    assert rows["foundation"][3].startswith("76.5 [")  # (92 + 61) / 2
    csv_rows = (tmp_path / "runs.csv").read_text().splitlines()
    assert any(",mlp,101," in line for line in csv_rows)


def test_health_quick_suite_trains_and_tables_a_real_health_run(tmp_path):
    """health_quick's sizes, one encoder and seed: the health trainer's summary.json feeds the Table 15 section."""
    quick = load_suite(ROOT / "recipes" / "suites" / "health_quick.yaml")
    path = _suite_file(
        tmp_path,
        f"name: health_smoke\nseeds: [0]\noverrides: {json.dumps(quick.overrides)}\n"
        "entries:\n  - {label: mlp, recipe: RECIPES/health/health_mlp.yaml}\n",
    )
    out = run_suite(path, jobs=1, output=tmp_path / "out")
    assert out["failed"] == [] and out["trained"] == ["mlp/pamap2-health/seed0"]
    summary = json.loads((Path(out["runs"][0]["run_dir"]) / "summary.json").read_text())
    table = (tmp_path / "out" / "summary.md").read_text().split("## Health world model (paper Table 15)")[1]
    row = next(line for line in table.splitlines() if line.startswith("| mlp |"))
    assert f"| {summary['eval_return_mean']:.1f} +- 0.0 |" in row and f"{summary['params_encoder']:,}" in row


def test_report_has_no_health_table_without_health_runs(tmp_path):
    run_dir = tmp_path / "runs" / "a" / "e" / "seed0"
    run_dir.mkdir(parents=True)
    (run_dir / "summary.json").write_text(json.dumps({"frames": 10, "final_return_mean": 1.0}))
    (run_dir / "done.json").write_text(json.dumps({"total_frames": 10, "frames": 10}))
    write_report(tmp_path, "plain", [RunRecord(label="a", env="e", env_dir="e", seed=0, run_dir=run_dir)])
    assert "Health world model" not in (tmp_path / "summary.md").read_text()
    assert "eval_return_mean" not in (tmp_path / "runs.csv").read_text().splitlines()[0]
