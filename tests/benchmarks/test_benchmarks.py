"""Smoke tests of the benchmark harness (tiny budgets; the real figures come from the benchmark commands)."""

import sys
from pathlib import Path

from torchrl.data import Categorical

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import minigrid_benchmark  # noqa: E402
from ppo_mlp_baseline import make_flat_env  # noqa: E402


def test_baseline_env_takes_integer_actions():
    """GymWrapper defaults to one-hot actions; an integer Categorical policy then always turns left."""
    env = make_flat_env("MiniGrid-MultiRoom-N2-S4-v0", seed=0)
    assert isinstance(env.action_spec, Categorical)
    rollout = env.rollout(30)
    assert rollout["action"].unique().numel() > 1
    env.close()


def test_benchmark_harness_writes_report(tmp_path):
    minigrid_benchmark.main(
        ["--frames", "512", "--seeds", "0", "--workers", "1", "--out", str(tmp_path),
         "env.num_envs=2", "ppo.frames_per_batch=256", "ppo.minibatch_size=128", "ppo.epochs=1"]
    )
    text = (tmp_path / "results.md").read_text()
    assert "FreamerV1" in text and "PPO-MLP" in text and "Throughput ratio" in text
    assert (tmp_path / "learning_curves.png").is_file()
    assert (tmp_path / "results.csv").read_text().count("\n") == 3


def test_health_benchmark_report_and_reuse(tmp_path):
    import health_benchmark

    args = ["--quick", "--encoders", "mlp", "--seeds", "0", "--workers", "1", "--skip-throughput", "--out",
            str(tmp_path)]  # fmt: skip
    health_benchmark.main(args)
    text = (tmp_path / "results.md").read_text()
    assert "MLP (vanilla)" in text and "| Encoder | Reward | Violations | MSE | Horizon |" in text
    first = (tmp_path / "results.csv").read_text()
    summary = tmp_path / "runs" / "mlp_s0" / "summary.json"
    stamp = summary.stat().st_mtime_ns
    health_benchmark.main([*args, "--reuse"])  # same resolved config: the finished run is read back, not retrained
    assert summary.stat().st_mtime_ns == stamp
    assert (tmp_path / "results.csv").read_text() == first
    health_benchmark.main([*args, "--reuse", "collect.iterations=2"])  # another config: trained again
    assert summary.stat().st_mtime_ns != stamp


def test_gym_benchmark_report_and_resume(tmp_path):
    """FreamerV1 and PPO-MLP on CartPole through the shared harness; a rerun reads finished runs back."""
    import gym_benchmark

    args = ["recipes/gym/cartpole.yaml", "--frames", "512", "--seeds", "0", "--workers", "1", "--target", "500",
            "--out", str(tmp_path), "env.num_envs=2", "ppo.frames_per_batch=256", "ppo.minibatch_size=128",
            "ppo.epochs=1"]  # fmt: skip
    gym_benchmark.main(args)
    text = (tmp_path / "results.md").read_text()
    assert "FreamerV1" in text and "PPO-MLP" in text and "frames to return >= 500" in text
    assert (tmp_path / "learning_curves.png").is_file()
    job = tmp_path / "jobs" / "freamer_s0.json"
    stamp = job.stat().st_mtime_ns
    gym_benchmark.main(args)  # finished runs are not retrained
    assert job.stat().st_mtime_ns == stamp
    assert (tmp_path / "runs" / "freamer_s0" / "checkpoints" / "latest").is_file()  # resumable mid-run too


def test_curriculum_benchmark_reports_chain_frames_and_reads_back(tmp_path):
    import shutil

    import curriculum_benchmark

    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    chain = tmp_path / "c.chain.yaml"
    chain.write_text("name: demo\nstages:\n  - {name: a, recipe: tiny.yaml}\n"
                     "  - {name: b, recipe: tiny.yaml, overrides: [env.id=MiniGrid-MultiRoom-N1-S4-v0]}\n")
    out = tmp_path / "out"
    text = curriculum_benchmark.main([str(chain), "--seeds", "0", "--workers", "1", "--out", str(out)])
    assert "| 0 | a 256 |" in text and "MiniGrid-MultiRoom-N1-S4-v0" in text
    assert (out / "learning_curve.png").is_file() and (out / "results.csv").read_text().startswith("seed,")
    stamp = (out / "runs" / "demo-s0" / "b" / "summary.json").stat().st_mtime
    curriculum_benchmark.main([str(chain), "--seeds", "0", "--workers", "1", "--out", str(out)])  # read back
    assert (out / "runs" / "demo-s0" / "b" / "summary.json").stat().st_mtime == stamp


def test_hard_task_benchmark_runs_every_method_and_reads_back(tmp_path, monkeypatch):
    import shutil

    import hard_task_benchmark

    shutil.copy(ROOT / "recipes" / "tiny.yaml", tmp_path / "tiny.yaml")
    chain = tmp_path / "c.chain.yaml"
    chain.write_text("name: demo\nstages:\n  - {name: a, recipe: tiny.yaml}\n  - {name: b, recipe: tiny.yaml}\n")
    monkeypatch.setitem(hard_task_benchmark.TASKS, "demo",
                        {"env": "MiniGrid-Empty-5x5-v0", "frames": 512, "target": 0.8, "chain": str(chain)})
    out = tmp_path / "out"
    argv = ["--task", "demo", "--frames", "512", "--seeds", "0", "--workers", "1", "--out", str(out)]
    text = hard_task_benchmark.main(argv)
    for method in ("| freamer | 0 |", "| ppo_mlp | 0 |", "| ppo_mlp_novelty | 0 |"):
        assert method in text
    assert (out / "learning_curve.png").is_file()
    rows = (out / "results.csv").read_text().splitlines()
    assert rows[0].startswith("method,seed,frames_to_80") and len(rows) == 4
    stamps = {p.name: p.stat().st_mtime for p in (out / "jobs").iterdir()}
    hard_task_benchmark.main(argv)  # finished runs are read back, not rerun
    assert {p.name: p.stat().st_mtime for p in (out / "jobs").iterdir()} == stamps


def test_ablation_benchmark_reports_each_arm_against_base(tmp_path):
    import ablation_benchmark

    text = ablation_benchmark.main(["--recipe", str(ROOT / "recipes" / "tiny.yaml"), "--env", "MiniGrid-Empty-5x5-v0",
                                    "--frames", "256", "--seeds", "0", "--workers", "1", "--out", str(tmp_path),
                                    "--arms", "base", "novelty", "ppo_mlp"])  # fmt: skip
    for arm in ("| base |", "| novelty | shaping.novelty.weight=0.1 |", "| ppo_mlp |"):
        assert arm in text
    assert (tmp_path / "learning_curves.png").is_file()
    assert (tmp_path / "results.csv").read_text().count("\n") == 4
