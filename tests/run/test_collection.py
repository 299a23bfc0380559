"""``freamer_rl.run.collection.make_collector``: the local backend's batch layout, the ``collector`` section's checks, and
(when the ``ray`` extra is installed) TorchRL's Ray backend on localhost: same layout, weights synced, a real run."""

from __future__ import annotations

import csv
import functools
import importlib.util
import math
from pathlib import Path

import pytest
import torch

from freamer_rl.config.checks import check_ray_backend
from freamer_rl.errors import ConfigError
from freamer_rl.run.collection import make_collector
from freamer_rl.run.envs import make_batched_env
from freamer_rl.trainers.minigrid_ppo import build_modules, train
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"  # 2 envs, 128 frames per batch
CPU = {"policy_device": "cpu", "env_device": "cpu", "storing_device": "cpu"}


def _collector(overrides: list[str], total_frames: int = 128, **kwargs):
    cfg = load_config(TINY, overrides)
    modules = build_modules(cfg)
    env_fns = [
        functools.partial(make_batched_env, cfg, modules.primers(), 1000 * i)
        for i in range(cfg.collector.num_collectors)
    ]
    collector = make_collector(
        cfg.collector,
        env_fns,
        modules.policy,
        frames_per_batch=cfg.ppo.frames_per_batch,
        total_frames=total_frames,
        devices=CPU,
        **kwargs,
    )
    return collector, modules


def _first_batch(overrides: list[str]):
    collector, _ = _collector(overrides)
    try:
        return next(iter(collector))
    finally:
        collector.shutdown()


@pytest.mark.parametrize(("n", "shape"), [(1, (2, 64)), (2, (2, 2, 32))])
def test_local_backend_batch_layout(n, shape):
    """One collector: [num_envs, T]; several (MultiSyncCollector): stacked, [num_collectors, num_envs, T]."""
    data = _first_batch([f"collector.num_collectors={n}"])
    assert data.batch_size == shape and data.names[-1] == "time"
    assert data.numel() == 128


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("collector.backend=ray2", r"collector\.backend: expected local or ray, got 'ray2'"),
        ("collector.ray_collector_cpus=0", r"collector\.ray_collector_cpus: got 0\.0, expected a finite number > 0"),
        ("collector.ray_num_cpus=0", r"collector\.ray_num_cpus: got 0, expected an integer >= 1"),
    ],
)
def test_collector_section_errors_name_the_field(override, match):
    with pytest.raises(ConfigError, match=match):
        load_config(TINY, [override])


def test_ray_num_cpus_only_for_a_local_ray_start():
    with pytest.raises(ConfigError, match=r"collector\.ray_num_cpus: got 2, but collector\.ray_address='auto'"):
        load_config(TINY, ["collector.backend=ray", "collector.ray_address=auto", "collector.ray_num_cpus=2"])


def test_ray_backend_without_ray_says_how_to_install(monkeypatch):
    cfg = load_config(TINY, ["collector.backend=ray"])  # loading does not need ray (a Ray-trained run evaluates)
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else find_spec(name, *a))
    with pytest.raises(ConfigError, match=r'collector\.backend: .*ray is not installed; pip install .*"\.\[ray\]"'):
        check_ray_backend(cfg.collector, torch.nn.Linear(2, 2))


# -- Ray on localhost (the `ray` extra) -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_not_enough_cpus_is_a_config_error(local_ray):
    with pytest.raises(ConfigError, match=r"collector\.ray_collector_cpus: 2 collector\(s\) x 1\.5 CPU need 3 CPUs"):
        _collector(["collector.backend=ray", "collector.num_collectors=2", "collector.ray_collector_cpus=1.5"])


def test_ray_backend_layout_and_weight_sync(local_ray):
    """Two actors: the local backend's [2, 2, 32]; update_policy_weights_() reaches both actors' policies."""
    collector, modules = _collector(["collector.backend=ray", "collector.num_collectors=2"], total_frames=10**6)
    try:
        data = next(iter(collector))
        assert data.batch_size == (2, 2, 32) and data.names[-1] == "time"
        assert data["next", "reward"].shape == (2, 2, 32, 1)
        name, param = next(iter(modules.policy.named_parameters()))
        with torch.no_grad():
            param.add_(1.0)
        collector.update_policy_weights_()
        for remote in collector.map_fn("policy.state_dict"):
            (key,) = [k for k in remote if k.endswith(name)]
            torch.testing.assert_close(remote[key], param.detach())
    finally:
        collector.shutdown()


def test_ray_backend_one_actor_layout(local_ray):
    collector, _ = _collector(["collector.backend=ray"], total_frames=256)
    try:
        batches = [d.batch_size for d in collector]
    finally:
        collector.shutdown()
    assert batches == [(2, 64), (2, 64)]


def test_ray_backend_trains_through_the_trainer(local_ray, tmp_path):
    cfg = load_config(TINY, ["collector.backend=ray", "collector.num_collectors=2", "run.total_frames=384"])
    summary = train(cfg, tmp_path / "run")
    assert summary["frames"] == 384
    with open(tmp_path / "run" / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["frames"]) for r in rows] == [128, 256, 384]
    losses = [float(r["loss_objective"]) for r in rows]
    assert all(math.isfinite(v) for v in losses) and len(set(losses)) > 1


@pytest.mark.parametrize("update_threads", [None, 2])
def test_learning_runs_at_update_threads_and_collection_at_run_threads(tmp_path, monkeypatch, update_threads):
    """``run.update_threads``: torch's thread count is that value inside every learning step of ``train()`` and
    ``run.threads`` again for the next batch's collection (None: run.threads throughout)."""
    from freamer_rl.trainers.minigrid_ppo import Trainer

    seen = {"learn": [], "collect": []}
    learn = Trainer._learn

    def spy_learn(self, data):
        seen["learn"].append(torch.get_num_threads())
        return learn(self, data)

    monkeypatch.setattr(Trainer, "_learn", spy_learn)
    extra = [] if update_threads is None else [f"run.update_threads={update_threads}"]
    cfg = load_config(TINY, ["run.total_frames=256", "run.threads=1", "logging.progress_bar=false", *extra])
    trainer = Trainer(cfg, tmp_path / "run", resume=False)
    make = trainer._make_collector

    def counting_collector(remaining):  # the thread count each time the loop asks for the next batch
        collector = make(remaining)

        class Counting:
            def __iter__(self):
                it = iter(collector)
                while True:
                    seen["collect"].append(torch.get_num_threads())
                    try:
                        yield next(it)
                    except StopIteration:
                        return

            def __getattr__(self, name):
                return getattr(collector, name)

        return Counting()

    trainer._make_collector = counting_collector
    trainer.train()
    assert seen["learn"] == [update_threads or 1] * 2  # two batches of 128 frames
    assert len(seen["collect"]) >= 2 and set(seen["collect"]) == {1}
    assert torch.get_num_threads() == 1
