"""IMPALA baseline (trainer ``impala``): V-trace targets against hand computations, config validation, and a tiny
run with two asynchronous actor processes that checkpoints, resumes and evaluates."""

import csv
import math
from pathlib import Path

import pytest
import torch

from freamer_rl.errors import ConfigError
from freamer_rl.run.checkpoint import latest_checkpoint, read_checkpoint
from freamer_rl.run.envs import probe_specs
from freamer_rl.trainers.baselines.impala import ImpalaTrainer
from freamer_rl.trainers.registry import TRAINERS, load_config

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "baselines" / "impala_n2s4.yaml"
TINY = [
    "env.id=MiniGrid-Empty-5x5-v0",
    "env.num_envs=2",
    "network.hidden=16",
    "impala.frames_per_batch=64",
    "logging.checkpoint_every_frames=128",
    "logging.progress_bar=false",
]
GAMMA = 0.9
B, T = 2, 6


@pytest.fixture(scope="module")
def trainer(tmp_path_factory):
    cfg = load_config(
        RECIPE,
        [*TINY, "collector.num_collectors=1", f"impala.gamma={GAMMA}", "impala.rho_clip=1.0", "impala.c_clip=1.0"],
    )
    return ImpalaTrainer(cfg, tmp_path_factory.mktemp("vtrace") / "run")


def _batch(trainer):
    """A [B, T] rollout with random observations, on-policy actions (stored log-probs = the current policy's), one
    termination (b=0, t=2) and one truncation (b=1, t=3)."""
    torch.manual_seed(0)
    obs_spec, _ = probe_specs(trainer.cfg)
    keys = trainer.cfg.network.observation_keys
    data = obs_spec.rand((B, T)).select(*keys)
    with torch.no_grad():
        trainer.net.get_policy_operator()(data)
    done = torch.zeros(B, T, 1, dtype=torch.bool)
    terminated = torch.zeros_like(done)
    done[0, 2] = terminated[0, 2] = True
    done[1, 3] = True
    # a rollout: next[t] = obs[t+1], except after done, where obs[t+1] is a reset and next[t] the final observation
    nxt = torch.cat([data[:, 1:].select(*keys), obs_spec.rand((B, 1)).select(*keys)], dim=1)
    final = obs_spec.rand((B, T)).select(*keys)
    nxt = torch.where(done[..., 0], final, nxt)
    nxt.update({"reward": torch.rand(B, T, 1), "done": done, "terminated": terminated})
    data["next"] = nxt
    return data.select(*keys, "action", "action_log_prob", "next")


def _values(trainer, data):
    keys = trainer.cfg.network.observation_keys
    with torch.no_grad():
        v = trainer.value_op(data.select(*keys).clone())["state_value"][..., 0]
        nv = trainer.value_op(data["next"].select(*keys).clone())["state_value"][..., 0]
    return v, nv


def _reference(data, v, nv, log_pi, log_mu, rho_bar, c_bar):
    """V-trace by the paper's recursion, one step at a time (Espeholt et al. 2018, Remark 1)."""
    r, done, term = (data["next", k][..., 0] for k in ("reward", "done", "terminated"))
    rho = (log_pi - log_mu).exp()
    targets, advs = torch.zeros(B, T), torch.zeros(B, T)
    for b in range(B):
        vs_next = None  # v_{s+1} of the same trajectory
        for t in reversed(range(T)):
            boot = 0.0 if term[b, t] else float(nv[b, t])
            delta = min(float(rho[b, t]), rho_bar) * (float(r[b, t]) + GAMMA * boot - float(v[b, t]))
            cont = (
                0.0
                if (done[b, t] or vs_next is None)
                else GAMMA * min(float(rho[b, t]), c_bar) * (vs_next - float(v[b, t + 1]))
            )
            targets[b, t] = float(v[b, t]) + delta + cont
            after = boot if (done[b, t] or vs_next is None) else vs_next
            advs[b, t] = min(float(rho[b, t]), rho_bar) * (float(r[b, t]) + GAMMA * after - float(v[b, t]))
            vs_next = float(targets[b, t])
    return targets, advs


def test_on_policy_vtrace_is_the_n_step_return(trainer):
    data = _batch(trainer)
    adv, target, rho = trainer.vtrace(data)
    assert adv.shape == target.shape == rho.shape == (B, T, 1)
    torch.testing.assert_close(rho, torch.ones_like(rho))
    v, nv = _values(trainer, data)
    r = data["next", "reward"][..., 0]
    # with rho = c = 1 V-trace is TD(lambda=1): the discounted rewards to the end of the trajectory or the batch,
    # bootstrapped from V(next) at a truncation or the batch's end, not at a termination
    expected = torch.zeros(B, T)
    for b in range(B):
        ret = float(nv[b, T - 1])
        for t in reversed(range(T)):
            if data["next", "terminated"][b, t]:
                ret = 0.0
            elif data["next", "done"][b, t]:
                ret = float(nv[b, t])
            ret = float(r[b, t]) + GAMMA * ret
            expected[b, t] = ret
    torch.testing.assert_close(target[..., 0], expected)
    assert math.isclose(float(target[0, 2, 0]), float(r[0, 2]), rel_tol=1e-6)  # terminated: no bootstrap
    # the advantage is r + gamma v_{s+1} - V(x_s) with the same bootstrap rules
    _, ref_adv = _reference(data, v, nv, torch.zeros(B, T), torch.zeros(B, T), 1.0, 1.0)
    torch.testing.assert_close(adv[..., 0], ref_adv)


def test_off_policy_vtrace_clips_the_ratios(trainer):
    data = _batch(trainer)
    on_adv, on_target, _ = trainer.vtrace(data)
    log_pi = data["action_log_prob"].clone()
    # behaviour twice less likely than pi (rho = 2, clipped to 1) on b=0; twice more likely (rho = 0.5) on b=1
    shift = torch.tensor([[-math.log(2)], [math.log(2)]]).expand(B, T)
    data["action_log_prob"] = log_pi + shift
    adv, target, rho = trainer.vtrace(data)
    torch.testing.assert_close(rho[..., 0], (-shift).exp())
    torch.testing.assert_close(target[0], on_target[0])  # rho = 2 > rho_clip = 1: as on-policy
    torch.testing.assert_close(adv[0], on_adv[0])
    assert not torch.allclose(target[1], on_target[1])  # rho = 0.5: corrected
    v, nv = _values(trainer, data)
    ref_target, ref_adv = _reference(data, v, nv, log_pi, data["action_log_prob"], 1.0, 1.0)
    torch.testing.assert_close(target[..., 0], ref_target)
    torch.testing.assert_close(adv[..., 0], ref_adv)


@pytest.mark.parametrize(
    "override,field",
    [
        ("impala.rho_clip=0.0", "impala.rho_clip"),
        ("impala.c_clip=2.0", "impala.c_clip"),
        ("impala.optimizer=sgd", "impala.optimizer"),
        ("impala.rmsprop_alpha=1.0", "impala.rmsprop_alpha"),
        ("impala.minibatches=3", "impala.minibatches"),
        ("network.kind=rnn", "network.kind"),
    ],
)
def test_validation_names_the_field(override, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        load_config(RECIPE, [*TINY, override])


def test_async_run_checkpoints_resumes_and_evaluates(tmp_path):
    spec = TRAINERS["impala"]
    run = tmp_path / "run"
    first = [*TINY, "collector.num_collectors=2", "impala.minibatches=2", "run.total_frames=256"]
    summary = spec.train(load_config(RECIPE, first), run)
    assert summary["trainer"] == "impala" and summary["frames"] == 256
    ckpt = latest_checkpoint(run)
    assert ckpt is not None and read_checkpoint(ckpt)["trainer"] == "impala"
    with (run / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    for col in ("loss_objective", "loss_critic", "loss_entropy", "grad_norm", "rho_mean", "rho_clipped", "policy_lag"):
        assert col in rows[0] and all(math.isfinite(float(r[col])) for r in rows), col
    assert all(float(r["policy_lag"]) >= 0 for r in rows)
    # the resume goes on with one actor: the learner's checkpoint does not depend on the actors (and no second worker
    # start-up is paid here)
    summary = spec.train(load_config(RECIPE, [*first, "collector.num_collectors=1", "run.total_frames=384"]), run)
    assert summary["frames"] == 384 and read_checkpoint(latest_checkpoint(run))["frames"] == 384
    result = spec.evaluate(latest_checkpoint(run), episodes=2, deterministic=True)
    assert result["episodes"] == 2 and "success_rate" in result
    rows = spec.params(load_config(RECIPE, first))
    assert rows[-1]["component"] == "Total" and rows[-1]["trainable"] > 0


def test_rmsprop_option(tmp_path):
    cfg = load_config(RECIPE, [*TINY, "collector.num_collectors=1", "impala.optimizer=rmsprop", "run.total_frames=64"])
    trainer = ImpalaTrainer(cfg, tmp_path / "run")
    assert isinstance(trainer.optimizer, torch.optim.RMSprop)
    assert trainer.train()["frames"] == 64


def test_version_stamp_is_a_copy():
    from freamer_rl.trainers.baselines.impala import PolicyVersion

    stamp = PolicyVersion(event_dims=0)
    out = stamp(torch.zeros(4, dtype=torch.long))
    stamp.version.fill_(3)  # the learner's next update: frames already stamped keep their version
    assert out.tolist() == [0, 0, 0, 0] and stamp(torch.zeros(2)).tolist() == [3, 3]


def test_resume_refuses_another_optimizer(tmp_path):
    from freamer_rl.errors import CheckpointError

    one = [*TINY, "collector.num_collectors=1", "run.total_frames=64"]
    TRAINERS["impala"].train(load_config(RECIPE, one), tmp_path / "run")
    # Adam's moments loaded into RMSprop would crash at the first step (no 'square_avg'): refused by name instead
    with pytest.raises(CheckpointError, match="impala.optimizer=adam"):
        TRAINERS["impala"].train(
            load_config(RECIPE, [*one, "impala.optimizer=rmsprop", "run.total_frames=128"]), tmp_path / "run"
        )
