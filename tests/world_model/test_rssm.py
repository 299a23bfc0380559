"""RSSM world model (Appendix J.1/J.3): shapes, resets, KL free nats, loss on TorchRL SliceSampler slices."""

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler

from freamer_rl.world_model import (
    RSSM,
    MLPObsEncoder,
    WorldModel,
    action_to_onehot,
    as_sequences,
    free_nats_kl,
    gaussian_kl,
    train_world_model,
)

BATCH_SHAPES = [(), (2,), (3, 2)]
OBS_DIMS = {"imu": 6, "hr_features": 3}
N_ACT = 5


def small_wm(**kw) -> WorldModel:
    return WorldModel(OBS_DIMS, N_ACT, embed_dim=16, deter_dim=24, stoch_dim=8, hidden=32, **kw)


def random_slice(shape, terminal_last=False) -> TensorDict:
    """A TorchRL-layout slice [*B, T] with root obs, action, and ("next", obs/reward/done/terminated)."""
    done = torch.zeros(*shape, 1, dtype=torch.bool)
    if terminal_last:
        done[..., -1, :] = True
    return TensorDict(
        {
            "imu": torch.randn(*shape, 6),
            "hr_features": torch.randn(*shape, 3),
            "action": torch.randint(0, N_ACT, shape),
            "next": {
                "imu": torch.randn(*shape, 6),
                "hr_features": torch.randn(*shape, 3),
                "reward": torch.randn(*shape, 1),
                "done": done,
                "terminated": done.clone(),
                "truncated": torch.zeros_like(done),
            },
        },
        batch_size=shape,
    )


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_rssm_shapes(batch):
    T, E, A, D, S = 5, 7, N_ACT, 12, 4
    rssm = RSSM(E, A, deter_dim=D, stoch_dim=S, hidden=16)
    embeds = torch.randn(*batch, T, E)
    actions = action_to_onehot(torch.randint(0, A, (*batch, T)), A, len(batch) + 1)
    is_first = torch.zeros(*batch, T, dtype=torch.bool)
    out = rssm.observe(embeds, actions, is_first)
    for k, d in {"h": D, "z": S, "prior_mean": S, "prior_std": S, "post_mean": S, "post_std": S}.items():
        assert out[k].shape == (*batch, T, d), k
    assert (out["prior_std"] >= 0.1).all() and (out["post_std"] >= 0.1).all()
    h, (m, s), z = rssm.imagine_step(out["h"][..., -1, :], out["z"][..., -1, :], actions[..., -1, :])
    assert h.shape == (*batch, D) and m.shape == s.shape == z.shape == (*batch, S)
    h0, z0 = rssm.initial_state(batch)
    assert h0.shape == (*batch, D) and z0.shape == (*batch, S)


def test_rssm_shape_errors():
    rssm = RSSM(7, N_ACT, deter_dim=12, stoch_dim=4, hidden=16)
    with pytest.raises(ValueError, match="embed"):
        rssm.observe(torch.randn(2, 3, 6), torch.zeros(2, 3, N_ACT), torch.zeros(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="is_first"):
        rssm.observe(torch.randn(2, 3, 7), torch.zeros(2, 3, N_ACT), torch.zeros(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="action"):
        action_to_onehot(torch.tensor([0, N_ACT]), N_ACT, 1)


def test_reset_on_is_first():
    """Where is_first is True the filter restarts: outputs equal a fresh observe() of the remaining sequence,
    whatever came before (deterministic: posterior means fed forward)."""
    rssm = RSSM(7, N_ACT, deter_dim=12, stoch_dim=4, hidden=16)
    T, k = 8, 3
    embeds = torch.randn(2, T, 7)
    actions = action_to_onehot(torch.randint(0, N_ACT, (2, T)), N_ACT, 2)
    is_first = torch.zeros(2, T, dtype=torch.bool)
    is_first[:, 0] = True
    is_first[:, k] = True
    full = rssm.observe(embeds, actions, is_first, sample=False)
    tail = rssm.observe(embeds[:, k:], actions[:, k:], is_first[:, k:], sample=False)
    for key in full:
        torch.testing.assert_close(full[key][:, k:], tail[key])
    # the carried state h0/z0 does not matter at a reset step, but does otherwise
    h0, z0 = torch.randn(2, 12), torch.randn(2, 4)
    with_state = rssm.observe(embeds, actions, is_first, h0=h0, z0=z0, sample=False)
    torch.testing.assert_close(with_state["h"], full["h"])
    no_reset = rssm.observe(embeds, actions, torch.zeros_like(is_first), h0=h0, z0=z0, sample=False)
    assert not torch.allclose(no_reset["h"][:, 0], full["h"][:, 0])


def test_kl_closed_form_and_free_nats():
    # KL(N(0,1) || N(1,1)) = 0.5 per dim; KL(N(0,2) || N(0,1)) = log(1/2) + 4/2 - 1/2
    one = torch.ones(1)
    assert gaussian_kl(0 * one, one, one, one).item() == pytest.approx(0.5)
    assert gaussian_kl(0 * one, 2 * one, 0 * one, one).item() == pytest.approx(math.log(0.5) + 1.5)
    # summed over latent dims: 4 dims of 0.5 -> 2.0
    assert gaussian_kl(torch.zeros(4), torch.ones(4), torch.ones(4), torch.ones(4)).item() == pytest.approx(2.0)
    # per-step clamp at free nats BEFORE averaging: steps (0.5, 2.0, 1.0) -> mean(1.0, 2.0, 1.0)
    kl = torch.tensor([0.5, 2.0, 1.0], requires_grad=True)
    loss = free_nats_kl(kl, free_nats=1.0)
    assert loss.item() == pytest.approx(4.0 / 3.0)
    loss.backward()
    torch.testing.assert_close(kl.grad, torch.tensor([0.0, 1.0 / 3.0, 1.0 / 3.0]))  # no gradient below free nats
    # same number through a hand-made step of the world model's KL
    mq = torch.tensor([[0.0], [0.0], [0.0]])
    mp = torch.tensor([[1.0], [2.0], [math.sqrt(2.0)]])  # KL 0.5, 2.0, 1.0
    out = {"post_mean": mq, "post_std": torch.ones(3, 1), "prior_mean": mp, "prior_std": torch.ones(3, 1)}
    assert free_nats_kl(small_wm().kl(out), 1.0).item() == pytest.approx(4.0 / 3.0)


@pytest.mark.parametrize("shape", [(6,), (2, 6), (3, 2, 6)])
def test_world_model_loss(shape):
    wm = small_wm()
    losses, latents = wm.loss(random_slice(shape, terminal_last=True), return_latents=True)
    for k in ("loss_rec", "loss_kl", "loss_rew", "loss_con", "total", "kl", "mse_imu", "mse_hr_features"):
        assert losses[k].shape == () and torch.isfinite(losses[k]), k
    assert losses["loss_kl"] >= 1.0  # free nats floor
    expected = losses["loss_rec"] + wm.beta * losses["loss_kl"] + losses["loss_rew"] + losses["loss_con"]
    torch.testing.assert_close(losses["total"], expected)
    n = math.prod(shape[:-1]) * (shape[-1] + 1)
    assert latents.batch_size == (n,) and latents["deter"].shape == (n, 24) and latents["stoch"].shape == (n, 8)
    assert not latents["deter"].requires_grad
    losses["total"].backward()
    assert all(p.grad is not None for p in wm.rssm.parameters())


def test_beta_and_episode_boundary_error():
    wm = small_wm(beta=0.5)
    batch = random_slice((2, 5))
    losses = wm.loss(batch)
    torch.testing.assert_close(
        losses["total"], losses["loss_rec"] + 0.5 * losses["loss_kl"] + losses["loss_rew"] + losses["loss_con"]
    )
    batch["next", "done"][0, 2] = True
    with pytest.raises(ValueError, match="episode"):
        wm.loss(batch)


class _DictEncoder(nn.Module):  # any module mapping the obs tensors to [*, E]
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(9, 16)

    def forward(self, obs):
        return self.lin(torch.cat([obs["imu"], obs["hr_features"]], -1))


class _TwoInputs(nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(9, 16)

    def forward(self, imu, hr):
        return self.lin(torch.cat([imu, hr], -1))


ENCODERS = {
    "dict_module": _DictEncoder,
    "tensordict_module": lambda: TensorDictModule(_TwoInputs(), in_keys=["imu", "hr_features"], out_keys=["embed"]),
    "mlp": lambda: MLPObsEncoder(OBS_DIMS, 16, hidden=8, symlog_inputs=False),
}


@pytest.mark.parametrize("kind", list(ENCODERS))
def test_pluggable_encoders(kind):
    """Any encoder kind plugs in: the world-model loss trains every one of its parameters."""
    enc = ENCODERS[kind]()
    wm = small_wm(encoder=enc)
    losses = wm.loss(random_slice((2, 4)))
    assert torch.isfinite(losses["total"])
    losses["total"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.parameters())


def _synthetic_buffer(n_episodes=24, length=16, seed=0) -> ReplayBuffer:
    """Easy dynamics: x' = 0.9 R x + 0.3 B[a]; imu = [x, -x] (+ small noise), hr = [sum x, x0 x1, 1];
    reward = x0; terminated at the last step of each episode."""
    g = torch.Generator().manual_seed(seed)
    th = 0.3
    R = torch.eye(3)
    R[:2, :2] = torch.tensor([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    Bm = torch.randn(N_ACT, 3, generator=g)

    def obs(x):
        imu = torch.cat([x, -x], -1) + 0.01 * torch.randn(x.shape[0], 6, generator=g)
        hr = torch.stack([x.sum(-1), x[:, 0] * x[:, 1], torch.ones(x.shape[0])], -1)
        return imu, hr

    x = torch.randn(n_episodes, 3, generator=g)
    steps = []
    for t in range(length):
        a = torch.randint(0, N_ACT, (n_episodes,), generator=g)
        x_next = 0.9 * x @ R.T + 0.3 * Bm[a]
        imu, hr = obs(x)
        nimu, nhr = obs(x_next)
        term = torch.full((n_episodes, 1), t == length - 1)
        steps.append(
            TensorDict(
                {
                    "imu": imu,
                    "hr_features": hr,
                    "action": a,
                    "episode": torch.arange(n_episodes),
                    "next": {
                        "imu": nimu,
                        "hr_features": nhr,
                        "reward": x_next[:, :1],
                        "done": term,
                        "terminated": term.clone(),
                        "truncated": torch.zeros_like(term),
                    },
                },
                [n_episodes],
            )
        )
        x = x_next
    data = torch.stack(steps, 1).reshape(-1)  # episodes stored contiguously
    rb = ReplayBuffer(
        storage=LazyTensorStorage(data.shape[0]),
        sampler=SliceSampler(slice_len=8, traj_key="episode"),
        batch_size=64,
    )
    rb.extend(data)
    return rb


def test_loss_decreases_on_slice_sampler_data():
    torch.manual_seed(0)
    rb = _synthetic_buffer()
    sample = as_sequences(rb.sample(), replay_buffer=rb)
    assert sample.batch_size == (8, 8)
    assert (sample["episode"] == sample["episode"][:, :1]).all()  # slices stay inside one episode
    wm = WorldModel(OBS_DIMS, N_ACT, embed_dim=32, deter_dim=32, stoch_dim=8, hidden=64)
    opt = torch.optim.Adam(wm.parameters(), lr=3e-3)
    hist = train_world_model(wm, rb, opt, steps=50)
    assert len(hist) == 50 and all(math.isfinite(h["total"]) for h in hist)
    first = sum(h["total"] for h in hist[:5]) / 5
    last = sum(h["total"] for h in hist[-5:]) / 5
    assert last < 0.6 * first, (first, last)
    rec_first = sum(h["loss_rec"] for h in hist[:5]) / 5
    rec_last = sum(h["loss_rec"] for h in hist[-5:]) / 5
    assert rec_last < 0.5 * rec_first, (rec_first, rec_last)


def test_recon_norm_running_stats_and_decode():
    """recon_norm: the running per-feature mean/var equal those of all training batches seen; decode() inverts the
    standardisation; eval mode leaves the statistics alone; the buffers round-trip through the state dict."""
    torch.manual_seed(0)
    wm = small_wm(recon_norm=True)
    b1, b2 = random_slice((4, 5)), random_slice((3, 5))
    b1["imu"] = b1["imu"] * 10 + 3
    b1["next", "imu"] = b1["next", "imu"] * 10 + 3
    wm.train()
    wm.loss(b1)
    wm.loss(b2)
    seqs = [wm.sequence(b)["obs"] for b in (b1, b2)]
    for i, k in enumerate(OBS_DIMS):
        x = torch.cat([s[k].reshape(-1, OBS_DIMS[k]) for s in seqs]).double()
        assert torch.allclose(wm.recon_mean_0 if i == 0 else wm.recon_mean_1, x.mean(0).float(), atol=1e-5)
        assert torch.allclose(wm.recon_var_0 if i == 0 else wm.recon_var_1, x.var(0, unbiased=False).float(), atol=1e-4)
    assert float(wm.recon_count) == 4 * 6 + 3 * 6
    # targets are standardised; decode(latent) maps the decoder output back to raw units
    tgt = wm.recon_target("imu", b1["imu"])
    assert tgt.mean().abs() < 1.0 and 0.3 < tgt.std() < 3.0
    latent = torch.randn(2, wm.latent_dim)
    raw = wm.decode(latent)
    std = wm.recon_var_0.sqrt().clamp_min(wm.norm_std_floor)
    assert torch.allclose(raw["imu"], wm.decoder(latent)["imu"] * std + wm.recon_mean_0, atol=1e-5)
    # eval mode: no update
    before = wm.recon_mean_0.clone()
    wm.eval()
    wm.loss(random_slice((2, 5)))
    assert torch.equal(before, wm.recon_mean_0)
    wm2 = small_wm(recon_norm=True)
    wm2.load_state_dict(wm.state_dict())
    assert torch.equal(wm2.recon_var_1, wm.recon_var_1)
    with pytest.raises(ValueError, match="norm_std_floor"):
        small_wm(recon_norm=True, norm_std_floor=0.0)


def test_recon_norm_weights_small_scale_features():
    """With recon_norm a small-scale feature (std 0.01) weighs as much in L_rec as a large one; with symlog targets
    its error is invisible next to the large one (the cause of the health world model ignoring heart rate)."""
    torch.manual_seed(0)
    batch = random_slice((8, 6))
    for key in ("hr_features", ("next", "hr_features")):
        batch[key] = batch[key] * 0.01
    for key in ("imu", ("next", "imu")):
        batch[key] = batch[key] * 20.0
    wm = small_wm(recon_norm=True)
    wm.train()
    wm.loss(batch)  # fit the statistics
    seq = wm.sequence(batch)["obs"]
    hr_norm = wm.recon_target("hr_features", seq["hr_features"]).pow(2).sum(-1).mean()
    imu_norm = wm.recon_target("imu", seq["imu"]).pow(2).sum(-1).mean()
    assert hr_norm / imu_norm > 0.3  # per feature both ~1: 3 vs 6 features
    from freamer_rl.world_model.functional import symlog

    assert symlog(seq["hr_features"]).pow(2).sum(-1).mean() / symlog(seq["imu"]).pow(2).sum(-1).mean() < 1e-3
