"""KL anomaly detection (Appendix J.5): running statistics, the online TorchRL transform, the Fig. 4 plot."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import check_env_specs

from freamer_rl.world_model import (
    KLAnomalyDetector,
    KLAnomalyTransform,
    WorldModel,
    detect_anomalies,
    plot_anomaly_timeline,
)
from freamer_rl.world_model.anomaly import anomaly_statistic

OBS_DIMS = {"imu": 6, "hr_features": 3}
N_ACT = 3


def stationary(T, shape=()):
    """Bounded periodic signal: std = 0.1/sqrt(2) ~ 0.071, so mean + 2 std ~ 1.141 > max 1.1 -- never flagged."""
    t = torch.arange(T, dtype=torch.float32)
    phase = torch.arange(math.prod(shape) or 1, dtype=torch.float32).reshape(*shape, 1) if shape else 0.0
    return 1.0 + 0.1 * torch.sin(0.7 * t + phase)


@pytest.mark.parametrize("momentum", [None, 0.02])
@pytest.mark.parametrize("shape", [(), (3,)])
def test_detector_flags_spike_not_stationary(momentum, shape):
    T, spike_at = 300, 200
    kl = stationary(T, shape)
    det = KLAnomalyDetector(k_sigma=2.0, warmup=30, momentum=momentum)
    flags = torch.stack([det.update(kl[..., t]) for t in range(T)], -1)
    assert flags.shape == (*shape, T)
    assert not flags.any()  # stationary: nothing flagged
    kl_spiked = kl.clone()
    kl_spiked[..., spike_at] += 1.0
    det.reset()
    flags = torch.stack([det.update(kl_spiked[..., t]) for t in range(T)], -1)
    assert flags[..., spike_at].all()
    assert flags.sum() == flags[..., spike_at].sum()  # only the spike
    # the offline helper agrees with the streaming module
    off, thr = detect_anomalies(kl_spiked, warmup=30, momentum=momentum)
    assert torch.equal(off, flags)
    assert torch.isnan(thr[..., :30]).all() and torch.isfinite(thr[..., 30:]).all()


def test_detector_warmup_and_welford_stats():
    det = KLAnomalyDetector(warmup=10)
    x = torch.tensor([1.0, 2.0, 3.0, 4.0, 100.0])
    flags = [bool(det.update(v)) for v in x]
    assert not any(flags)  # a huge value during warm-up is not flagged
    assert det.mean.item() == pytest.approx(x.mean().item())
    assert det.std.item() == pytest.approx(x.std().item(), rel=1e-5)
    with pytest.raises(ValueError, match="kl"):
        det.update(torch.zeros(2))
    with pytest.raises(ValueError, match="momentum"):
        KLAnomalyDetector(momentum=1.5)


class ToySensorEnv(EnvBase):
    """Tiny batched env with the health env's interface shape: obs "imu" [6], "hr_features" [3], Categorical(3)."""

    def __init__(self, batch_size=()):
        super().__init__(batch_size=torch.Size(batch_size))
        bs = self.batch_size
        self.observation_spec = Composite(imu=Unbounded((*bs, 6)), hr_features=Unbounded((*bs, 3)), shape=bs)
        self.state_spec = Composite(t=Unbounded((*bs, 1)), shape=bs)
        self.action_spec = Categorical(N_ACT, shape=bs)
        self.reward_spec = Unbounded((*bs, 1))
        self.done_spec = Composite(
            {k: Categorical(2, (*bs, 1), dtype=torch.bool) for k in ("done", "terminated", "truncated")}, shape=bs
        )

    def _obs(self, t, action=None):
        bs = self.batch_size
        a = torch.zeros(*bs, 1) if action is None else action.float().unsqueeze(-1)
        imu = torch.cat([torch.sin(0.3 * t).expand(*bs, 3), torch.cos(0.3 * t).expand(*bs, 3)], -1) + 0.1 * a
        hr = torch.cat([torch.sin(0.1 * t), t / 100, a], -1).expand(*bs, 3)
        return imu, hr

    def _reset(self, td):
        t = torch.zeros(*self.batch_size, 1)
        imu, hr = self._obs(t)
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(
            {
                "imu": imu,
                "hr_features": hr,
                "t": t,
                "done": done,
                "terminated": done.clone(),
                "truncated": done.clone(),
            },
            self.batch_size,
        )

    def _step(self, td):
        t = td["t"] + 1
        imu, hr = self._obs(t, td["action"])
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(
            {
                "imu": imu,
                "hr_features": hr,
                "t": t,
                "reward": imu[..., :1],
                "done": done,
                "terminated": done.clone(),
                "truncated": done.clone(),
            },
            self.batch_size,
        )

    def _set_seed(self, seed):
        return seed


@pytest.mark.parametrize("batch", [(), (2,)])
def test_transform_writes_keys_in_rollout(batch):
    wm = WorldModel(OBS_DIMS, N_ACT, embed_dim=16, deter_dim=24, stoch_dim=8, hidden=32)
    env = TransformedEnv(ToySensorEnv(batch), KLAnomalyTransform(wm, detector=KLAnomalyDetector(warmup=5)))
    check_env_specs(env)
    env.transform.detector.reset()
    T = 25
    traj = env.rollout(T)
    assert traj.batch_size == (*batch, T)
    assert traj["next", "kl"].shape == (*batch, T, 1) and traj["next", "anomaly"].dtype == torch.bool
    assert traj["next", "kl_filter", "deter"].shape == (*batch, T, 24)
    assert (traj["next", "kl"] >= 0).all() and torch.isfinite(traj["next", "kl"]).all()
    assert not traj["anomaly"][..., 0, :].any()  # reset step never flagged
    assert not traj["next", "anomaly"][..., :4, :].any()  # warm-up
    # filtering state is carried: root of step t+1 == next of step t
    torch.testing.assert_close(traj["kl_filter", "deter"][..., 1:, :], traj["next", "kl_filter", "deter"][..., :-1, :])
    # the online KL equals the offline KL of the recorded episode (same filter, posterior means)
    offline = wm.episode_kl(traj)
    torch.testing.assert_close(offline[..., 0], traj["kl"][..., 0, 0])
    torch.testing.assert_close(offline[..., 1:], traj["next", "kl"][..., 0], rtol=1e-4, atol=1e-5)
    # statistics follow every env step
    assert env.transform.detector.count.shape == batch and (env.transform.detector.count == T).all()


def test_plot_anomaly_timeline_png(tmp_path):
    T = 240
    t = torch.arange(T, dtype=torch.float32)
    hr = 90 + 60 * torch.sin(t / 40).clamp(min=0) + 30 * (t > 200).float()
    actions = (t // 30).long() % 5
    kl = stationary(T)
    kl[150] += 2.0
    flags, thr = detect_anomalies(kl, warmup=20)
    out = plot_anomaly_timeline(
        hr,
        actions,
        kl,
        flags,
        tmp_path / "fig" / "anomaly.png",
        threshold=thr,
        time_hours=t * 48 / T,
        title="48 h scenario",
    )
    with open(out, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="actions"):
        plot_anomaly_timeline(hr, actions[:-1], kl, flags, tmp_path / "bad.png")


@pytest.mark.parametrize("kind", ["mlp", "cnn", "slotattn", "foundation"])
def test_transform_works_with_every_health_encoder(kind):
    """The online filter drives each health encoder through its step API (the foundation encoder's DNC memory is
    carried in the tensordict) and its KL equals the offline KL of the recorded episode (sequence mode)."""
    from freamer_rl.health.encoders import make_health_encoder
    from freamer_rl_envs.health import make_health_env

    torch.manual_seed(0)
    small = {
        "mlp": {"hidden": 16},
        "cnn": {"channels": 4, "hidden": 16},
        "slotattn": {"dim": 8, "heads": 2, "hr_tokens": 2, "hidden": 16},
        "foundation": {
            "dim": 8,
            "heads": 2,
            "hr_tokens": 2,
            "hidden": 16,
            "fm_hidden": 16,
            "fm_steps": 2,
            "fno_modes": 4,
            "memory_slots": 4,
            "memory_width": 6,
        },
    }
    enc = make_health_encoder(kind, 12, **small[kind])
    wm = WorldModel(
        {"imu": 36, "hr_features": 16}, 5, encoder=enc, embed_dim=12, deter_dim=16, stoch_dim=4, hidden=16
    ).eval()
    env = TransformedEnv(
        make_health_env(batch_size=2, episode_length=40, seed=0, rate_hz=0.2),
        KLAnomalyTransform(wm, detector=KLAnomalyDetector(warmup=3)),
    )
    check_env_specs(env)
    traj = env.rollout(12)
    assert traj["next", "kl"].shape == (2, 12, 1) and torch.isfinite(traj["next", "kl"]).all()
    if kind == "foundation":
        mem = traj["next", "kl_filter", "enc", "memory"]
        assert mem.shape == (2, 12, 4, 6) and mem.abs().sum() > 0
        torch.testing.assert_close(traj["kl_filter", "enc", "memory"][:, 1:], mem[:, :-1])
    with torch.no_grad():
        offline = wm.episode_kl(traj)
    torch.testing.assert_close(offline[..., 0], traj["kl"][..., 0, 0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(offline[..., 1:], traj["next", "kl"][..., 0], rtol=1e-4, atol=1e-5)


def test_ema_statistic_halflife_closed_form():
    """With ``statistic="ema"`` a value's weight halves every ``halflife`` steps: after a unit step from 0 the mean
    is exactly ``1 - 2^(-n / h)`` n steps later."""
    h = 8.0
    det = KLAnomalyDetector(warmup=2, statistic="ema", halflife=h)
    assert det.momentum == pytest.approx(1 - 0.5 ** (1 / h)) and det.statistic == "ema"
    det.update(torch.tensor(0.0))
    for n in range(1, 25):
        det.update(torch.tensor(1.0))
        assert det.mean.item() == pytest.approx(1 - 0.5 ** (n / h), rel=1e-5)
    assert KLAnomalyDetector(statistic="ema").halflife == 720.0
    for kwargs, field in (
        ({"statistic": "median"}, "statistic"),
        ({"statistic": "ema", "halflife": 0.0}, "halflife"),
        ({"halflife": 5.0}, "halflife"),
        ({"statistic": "ema", "momentum": 0.1}, "momentum"),
    ):
        with pytest.raises(ValueError, match=field):
            KLAnomalyDetector(**kwargs)


@pytest.mark.parametrize("statistic", ["running", "ema"])
def test_excluded_steps_are_neither_flagged_nor_counted(statistic):
    """``include=False`` steps (e.g. a filter reset) leave the statistics as they were and are never flagged; the
    z-score is flagged exactly where it exceeds k."""
    kl = stationary(200)
    kl[[60, 120]] += 5.0
    include = torch.ones(200, dtype=torch.bool)
    include[60] = False
    hl = 50.0 if statistic == "ema" else None
    out = anomaly_statistic(kl, warmup=20, statistic=statistic, halflife=hl, include=include)
    assert not out["flags"][60] and out["flags"][120]
    # the excluded spike changed nothing: the same stream without it gives the same statistics afterwards
    dropped = torch.cat([kl[:60], kl[61:]])
    ref = anomaly_statistic(dropped, warmup=20, statistic=statistic, halflife=hl)
    torch.testing.assert_close(out["mean"][61:], ref["mean"][60:])
    torch.testing.assert_close(out["flags"][61:], ref["flags"][60:])
    z = out["z"]
    assert torch.isnan(z[:20]).all() and torch.isnan(z[60])
    ok = torch.isfinite(z)
    assert torch.equal(out["flags"][ok], z[ok] > 2.0)
    flags, _ = detect_anomalies(kl, warmup=20, statistic=statistic, halflife=hl, include=include)
    assert torch.equal(out["flags"], flags)


@pytest.mark.parametrize("shape", [(), (3,)])
def test_running_statistic_in_closed_form_matches_the_streaming_detector(shape):
    """anomaly_statistic computes the running statistic from prefix sums; the streaming KLAnomalyDetector, fed one
    step at a time, gives the same mean, std and flags."""
    g = torch.Generator().manual_seed(0)
    kl = torch.rand(*shape, 300, generator=g).exp()
    kl[..., 150] += 10.0
    include = torch.rand(*shape, 300, generator=g) > 0.1
    out = anomaly_statistic(kl, k_sigma=2.5, warmup=10, include=include)
    det = KLAnomalyDetector(k_sigma=2.5, warmup=10)
    nan = torch.full(shape, float("nan"))
    for t in range(300):
        ready = det.count >= 10 if det.count is not None else torch.zeros(shape, dtype=torch.bool)
        mean = torch.where(ready, det.mean, nan) if det.count is not None else nan
        torch.testing.assert_close(out["mean"][..., t], mean, equal_nan=True, rtol=1e-5, atol=1e-6)
        if det.count is not None:
            std = torch.where(ready, det.std.clamp(min=1e-4), nan)
            torch.testing.assert_close(out["std"][..., t], std, equal_nan=True, rtol=1e-4, atol=1e-6)
        flags = det.update(kl[..., t], include[..., t])
        assert torch.equal(out["flags"][..., t], flags), t
    assert out["flags"][..., 150].all()
