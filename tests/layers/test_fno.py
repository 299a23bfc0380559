"""FNO layers: SpectralConv1d, the FNO state encoder (Appendix E.2) and the FNO fuser (Eq. A14-A17)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from freamer_rl.layers.fno import FNOFuser, SpectralConv1d, StateFNOEncoder, smoothness_loss

BATCH_SHAPES = [(), (2,), (3, 2)]


def _dense_spectral_reference(x: torch.Tensor, weight: torch.Tensor, modes: int) -> torch.Tensor:
    """Spectral conv from explicit DFT matrices (no torch.fft). x [B, Cin, N] float64, weight [Cin, Cout, K] complex."""
    n = x.shape[-1]
    k = torch.arange(n // 2 + 1, dtype=torch.float64)[:, None]
    pos = torch.arange(n, dtype=torch.float64)[None, :]
    angle = 2 * math.pi * k * pos / n  # [N//2+1, N]
    dft = torch.complex(torch.cos(angle), -torch.sin(angle))  # forward real DFT rows
    x_hat = x.to(torch.complex128) @ dft.T  # [B, Cin, N//2+1]
    y_hat = torch.einsum("bik,iok->bok", x_hat[..., :modes], weight.to(torch.complex128))  # [B, Cout, K]
    # inverse real DFT with Hermitian symmetry: DC and Nyquist once, the other modes twice (real part only)
    coeff = torch.full((modes,), 2.0, dtype=torch.float64)
    coeff[0] = 1.0
    if n % 2 == 0 and modes == n // 2 + 1:
        coeff[-1] = 1.0
    inv = torch.complex(torch.cos(angle[:modes]), torch.sin(angle[:modes]))  # [K, N]
    return (coeff[:, None] * (y_hat[..., :, None] * inv).real).sum(-2) / n


@pytest.mark.parametrize("n,modes", [(16, 5), (16, 9), (15, 8), (49, 12)])
def test_spectral_conv_matches_dense_dft(n, modes):
    conv = SpectralConv1d(3, 2, modes)
    x = torch.randn(4, 3, n, dtype=torch.float64)
    expected = _dense_spectral_reference(x, conv.complex_weight.detach(), modes)
    torch.testing.assert_close(conv(x), expected, atol=1e-5, rtol=1e-5)
    # float32 path too
    torch.testing.assert_close(conv(x.float()).double(), expected, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_spectral_conv_batch_shapes_and_dtypes(batch):
    conv = SpectralConv1d(2, 5, 4)
    x = torch.randn(*batch, 2, 12)
    y = conv(x)
    assert y.shape == (*batch, 5, 12)
    y_bf16 = conv(x.bfloat16())
    assert y_bf16.dtype == torch.bfloat16
    torch.testing.assert_close(y_bf16.float(), y, atol=0.05, rtol=0.05)
    assert conv.weight.dtype == torch.float32 and not conv.weight.is_complex()


def test_mode_validation_errors():
    conv = SpectralConv1d(2, 2, 10)
    with pytest.raises(ValueError, match=r"modes=10.*n//2\+1=9.*n=16"):
        conv(torch.randn(2, 16))
    with pytest.raises(ValueError, match="in_channels=2"):
        conv(torch.randn(3, 32))
    with pytest.raises(ValueError, match="modes=20"):
        FNOFuser(4, 16, modes=20)
    with pytest.raises(ValueError, match="modes=30"):
        StateFNOEncoder(modes=30)


def _band_limited(batch: int, d: int, k_max: int) -> torch.Tensor:
    """Random real signals [batch, d] with energy only in modes 0 < k < k_max."""
    pos = torch.arange(d, dtype=torch.float64)
    k = torch.arange(1, k_max, dtype=torch.float64)
    a, b = torch.randn(batch, k_max - 1, 1, dtype=torch.float64), torch.randn(batch, k_max - 1, 1, dtype=torch.float64)
    angle = 2 * math.pi * k[:, None] * pos[None, :] / d
    return (a * torch.cos(angle) + b * torch.sin(angle)).sum(1)


def test_phase_shift_representation():
    """Eq. A17: a delay tau is the per-mode phase exp(-j 2 pi k tau / d); complex R_k can encode it exactly."""
    d, modes, tau = 64, 10, 5
    fuser = FNOFuser(2, d, modes=modes)
    conv = fuser.spectral
    k = torch.arange(modes, dtype=torch.float64)
    phase = torch.polar(torch.ones(modes, dtype=torch.float64), -2 * math.pi * k * tau / d)
    r = torch.zeros(2, 2, modes, dtype=torch.complex128)
    r[0, 0] = 1.0  # channel 0 -> 0: identity (on the band)
    r[0, 1] = phase  # channel 0 -> 1: delay by tau
    with torch.no_grad():
        conv.weight.copy_(torch.view_as_real(r).float())
    x = _band_limited(8, d, modes).float()
    inp = torch.stack([x, torch.zeros_like(x)], dim=-2)  # [8, 2, d]
    out = conv(inp)
    torch.testing.assert_close(out[:, 0], x, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out[:, 1], torch.roll(x, shifts=tau, dims=-1), atol=1e-5, rtol=1e-5)
    # a real-valued (zero-phase) weight cannot produce the delay
    with torch.no_grad():
        conv.weight.copy_(torch.view_as_real(r.abs().to(torch.complex128)).float())
    assert (conv(inp)[:, 1] - torch.roll(x, shifts=tau, dims=-1)).abs().max() > 0.1


def test_spectral_conv_learns_a_shift():
    torch.manual_seed(0)
    d, modes, tau = 32, 8, 3
    conv = SpectralConv1d(1, 1, modes)
    opt = torch.optim.Adam(conv.parameters(), lr=0.05)
    for _ in range(300):
        x = _band_limited(32, d, modes).float().unsqueeze(-2)
        loss = F.mse_loss(conv(x), torch.roll(x, shifts=tau, dims=-1))
        opt.zero_grad()
        loss.backward()
        opt.step()
    x = _band_limited(64, d, modes).float().unsqueeze(-2)
    target = torch.roll(x, shifts=tau, dims=-1)
    with torch.no_grad():
        rel = F.mse_loss(conv(x), target) / target.pow(2).mean()
    assert rel.item() < 1e-3
    # the learnt phases approximate -2 pi k tau / d on the excited modes 1..modes-1
    learnt = torch.angle(conv.complex_weight.detach()[0, 0, 1:]).double()
    ideal = -2 * math.pi * torch.arange(1, modes, dtype=torch.float64) * tau / d
    wrapped = torch.remainder(learnt - ideal + math.pi, 2 * math.pi) - math.pi
    assert wrapped.abs().max().item() < 0.05


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_fno_fuser_shapes_and_equation(batch):
    m, d = 4, 32
    fuser = FNOFuser(m, d, modes=8)
    assert fuser.residual_scale.item() == pytest.approx(0.1)
    e = torch.randn(*batch, m, d)
    fused, e_out = fuser(e)
    assert fused.shape == (*batch, d) and e_out.shape == (*batch, m, d)
    torch.testing.assert_close(fused, e_out.mean(-2))
    # with scale = 1 the block is exactly Eq. A15: GELU(LN(IFFT(R E^) + W E)) + E
    with torch.no_grad():
        fuser.residual_scale.fill_(1.0)
    _, e_out = fuser(e)
    we = torch.einsum("nm,...md->...nd", fuser.pointwise.weight, e) + fuser.pointwise.bias[:, None]
    expected = F.gelu(F.layer_norm(fuser.spectral(e) + we, (d,), fuser.norm.weight, fuser.norm.bias)) + e
    torch.testing.assert_close(e_out, expected)
    with pytest.raises(ValueError, match=r"M=4, d=32"):
        fuser(torch.randn(*batch, 3, d))


def test_fno_fuser_rejects_non_finite_except_under_vmap():
    fuser = FNOFuser(3, 16, modes=4)
    e = torch.randn(2, 3, 16)
    e[1, 0, 5] = float("nan")
    with pytest.raises(ValueError, match=r"FNOFuser modal_stack: 1 non-finite values \(NaN/Inf\)"):
        fuser(e)
    fused, _ = torch.vmap(fuser)(e)  # maths only under vmap
    assert torch.isfinite(fused[0]).all() and torch.isnan(fused[1]).any()


def test_fno_fuser_gradients_and_defaults():
    fuser = FNOFuser(4, 128)  # Table A20 defaults: K = 16, residual scale 0.1
    assert fuser.spectral.modes == 16
    fused, e_out = fuser(torch.randn(5, 4, 128))
    (fused.pow(2).sum() + fuser.smoothness_loss(e_out)).backward()
    for name, p in fuser.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_smoothness_loss_closed_form():
    e = torch.tensor([[[0.0, 1.0], [1.0, 1.0], [1.0, 3.0]], [[0.0, 0.0], [0.0, 0.0], [2.0, 0.0]]])
    # sample 0: ||(1,0)||^2 + ||(0,2)||^2 = 5; sample 1: 0 + 4 = 4 -> mean 4.5
    assert smoothness_loss(e).item() == pytest.approx(4.5)
    assert smoothness_loss(e[0]).item() == pytest.approx(5.0)
    assert FNOFuser.smoothness_loss(e).item() == pytest.approx(4.5)


def _random_grid(batch, generator=None):
    obj = torch.randint(0, 11, (*batch, 7, 7, 1), generator=generator)
    col = torch.randint(0, 6, (*batch, 7, 7, 1), generator=generator)
    st = torch.randint(0, 3, (*batch, 7, 7, 1), generator=generator)
    return torch.cat([obj, col, st], dim=-1)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_state_encoder_shapes(batch):
    enc = StateFNOEncoder(out_dim=16, channels=8, modes=6)
    grid = _random_grid(batch)
    direction = torch.randint(0, 4, batch)
    out = enc(grid, direction)
    assert out.shape == (*batch, 16)
    # [*B, 1] direction is accepted too
    torch.testing.assert_close(enc(grid, direction.unsqueeze(-1)), out)
    # the direction matters
    assert not torch.allclose(enc(grid, (direction + 1) % 4), out)
    out.sum().backward()
    assert enc.spectral.weight.grad.abs().sum() > 0


def test_state_encoder_batch_consistency():
    enc = StateFNOEncoder(out_dim=16, channels=8, modes=6)
    grid, direction = _random_grid((3, 2)), torch.randint(0, 4, (3, 2))
    out = enc(grid, direction)
    torch.testing.assert_close(out[1, 0], enc(grid[1, 0], direction[1, 0]), atol=1e-6, rtol=1e-5)


def test_state_encoder_validation():
    enc = StateFNOEncoder(out_dim=16, channels=8, modes=6)
    grid, direction = _random_grid((2,)), torch.randint(0, 4, (2,))
    bad = grid.clone()
    bad[0, 3, 3, 0] = 11
    with pytest.raises(ValueError, match=r"object index.*\[0, 10\].*11"):
        enc(bad, direction)
    bad = grid.clone()
    bad[1, 0, 0, 1] = -1
    with pytest.raises(ValueError, match=r"colour index"):
        enc(bad, direction)
    bad = grid.clone()
    bad[1, 0, 0, 2] = 3
    with pytest.raises(ValueError, match=r"state index"):
        enc(bad, direction)
    with pytest.raises(ValueError, match="direction must lie in"):
        enc(grid, torch.tensor([0, 4]))
    with pytest.raises(ValueError, match=r"\[\*B, 7, 7, 3\]"):
        enc(grid[..., :2], direction)
    with pytest.raises(TypeError, match="int64"):
        enc(grid.float(), direction)
    with pytest.raises(ValueError, match="direction must have shape"):
        enc(grid, torch.zeros(3, dtype=torch.long))


def test_state_encoder_index_ranges_are_checked_only_in_eager_mode():
    enc = StateFNOEncoder(out_dim=16, channels=8, modes=6)
    grid, direction = _random_grid((2,)), torch.randint(0, 4, (2,))
    # under vmap the encoder is sync-free: no range check, and the result equals the eager batched forward
    torch.testing.assert_close(torch.vmap(enc)(grid, direction), enc(grid, direction), atol=1e-5, rtol=1e-5)
    bad = grid.clone()
    bad[0, 3, 3, 1] = 7  # colour index 7 (>= 6) lands on the first state embedding row: wrong, but no sync
    with pytest.raises(ValueError, match="colour index"):
        enc(bad, direction)
    assert torch.vmap(enc)(bad, direction).shape == (2, 16)


@pytest.mark.parametrize("n, modes", [(49, 12), (49, 25), (16, 9), (128, 16), (7, 4)])
def test_channels_last_dft_path_matches_fft_path(n, modes):
    """The dense-DFT channels-last path is the same operator as rfft -> truncate -> irfft (incl. Nyquist mode)."""
    torch.manual_seed(0)
    conv = SpectralConv1d(3, 5, modes).double()
    x = torch.randn(4, 3, n, dtype=torch.float64, requires_grad=True)
    y_fft = conv(x)
    y_dft = conv.forward_channels_last(x.transpose(-1, -2)).transpose(-1, -2)
    assert torch.allclose(y_fft, y_dft, atol=1e-10)
    g_fft = torch.autograd.grad(y_fft.square().sum(), (x, conv.weight))
    g_dft = torch.autograd.grad(y_dft.square().sum(), (x, conv.weight))
    for a, b in zip(g_fft, g_dft):
        assert torch.allclose(a, b, atol=1e-9)


@pytest.mark.parametrize("batch", [(), (2,), (3, 2)])
def test_fuser_output_norm_rescales_only_the_pooled_vector(batch):
    torch.manual_seed(0)
    plain = FNOFuser(num_modalities=3, dim=32, modes=8)
    normed = FNOFuser(num_modalities=3, dim=32, modes=8, output_norm=True)
    normed.load_state_dict(plain.state_dict(), strict=False)  # same spectral/pointwise weights
    e = torch.randn(*batch, 3, 32)
    fused_plain, out_plain = plain(e)
    fused, out = normed(e)
    torch.testing.assert_close(out, out_plain)  # E_out (and so the smoothness loss) is unchanged
    torch.testing.assert_close(fused, torch.nn.functional.layer_norm(fused_plain, (32,)), atol=1e-5, rtol=1e-5)
    assert fused.shape == (*batch, 32)
    torch.testing.assert_close(fused.std(dim=-1, unbiased=False), torch.ones(batch), atol=1e-3, rtol=0)


@pytest.mark.parametrize("batch", [(2,), (3, 2)])
def test_smoothness_gradient_scope(batch):
    """L_smooth trains only the fuser by default; with smooth_fuser=None (literal Eq. 6) it reaches the encoders."""
    from tensordict import TensorDict

    from freamer_rl.model.losses import FreamerAuxLoss

    torch.manual_seed(0)
    fuser = FNOFuser(num_modalities=3, dim=32, modes=8)
    encoder = torch.nn.Linear(5, 3 * 32)  # stands in for the encoders + refiners upstream of the stack
    x = torch.randn(*batch, 5)
    stack = encoder(x).reshape(*batch, 3, 32)
    _, rows = fuser(stack)
    td = TensorDict({"modal_stack": stack, "fused_modalities": rows}, batch_size=batch)
    scoped = FreamerAuxLoss(torch.nn.ModuleDict(), lambda_fm=0, lambda_cl=0, lambda_smooth=1e-3, smooth_fuser=fuser)
    literal = FreamerAuxLoss(torch.nn.ModuleDict(), lambda_fm=0, lambda_cl=0, lambda_smooth=1e-3)
    loss_scoped, loss_literal = scoped(td)["loss_smooth"], literal(td)["loss_smooth"]
    torch.testing.assert_close(loss_scoped, loss_literal)  # same value, Eq. A16 on the fuser's output rows
    torch.testing.assert_close(loss_literal, 1e-3 * smoothness_loss(rows))

    enc_grad = torch.autograd.grad(loss_scoped, encoder.weight, allow_unused=True)[0]
    assert enc_grad is None or bool((enc_grad == 0).all())
    fuser_grads = torch.autograd.grad(loss_scoped, [fuser.pointwise.weight, fuser.residual_scale], retain_graph=True)
    assert all(bool(g.abs().sum() > 0) for g in fuser_grads)
    literal_enc_grad = torch.autograd.grad(loss_literal, encoder.weight)[0]
    assert float(literal_enc_grad.abs().sum()) > 0
