"""Score-based reliability of the Layer-2 refiner (issue 20 part 7): the refiner's own score ``E_t ||v||^2`` at the
encoder output, standardised by statistics of the training embeddings, opens the residual gate and lowers the
modality's mixing weight when an embedding is unlike those it was trained on; plus the relative FM noise scale."""

from __future__ import annotations

import math

import pytest
import torch

from freamer_rl.layers.flow_matching import COMPLEXITY_TIMES, FlowMatchingRefiner

BATCH_SHAPES = [(), (5,), (3, 4)]


def _manifold(n: int, basis: torch.Tensor) -> torch.Tensor:
    """Points of the 3-D subspace spanned by ``basis [3, d]``: the clean embeddings of the toy modality."""
    return torch.randn(n, basis.shape[0]) @ basis


@pytest.fixture(scope="module")
def trained():
    """A refiner trained by its CFM loss on a 3-D subspace of R^32 (the statistics come from those calls)."""
    torch.manual_seed(0)
    basis = torch.randn(3, 32)
    ref = FlowMatchingRefiner(32, hidden=64, reliability="both")
    opt = torch.optim.Adam(ref.parameters(), 1e-3)
    for _ in range(250):
        loss = ref.cfm_loss(_manifold(256, basis), noise_std=1.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return ref, basis


def test_off_adds_no_state_and_keeps_eq3():
    torch.manual_seed(0)
    ref = FlowMatchingRefiner(8, hidden=16)
    assert not any("score" in k or "beta" in k for k in ref.state_dict())
    e = torch.randn(4, 8)
    with torch.no_grad():
        expected = e + torch.sigmoid(ref.alpha) * (ref.integrate(e) - e)
    torch.testing.assert_close(ref(e), expected)


def test_first_statistics_are_the_batch_moments_of_log_score():
    torch.manual_seed(1)
    ref = FlowMatchingRefiner(8, hidden=16, reliability="weight")
    e = torch.randn(64, 8)
    with torch.no_grad():  # closed form: c(e) = mean_t ||v(e, t)||^2 / d, first update = the batch's moments
        log_c = torch.log(torch.stack([ref.velocity(e, t).pow(2).mean(-1) for t in COMPLEXITY_TIMES]).mean(0) + 1e-8)
    ref.cfm_loss(e)
    count, mean, var = ref.score_stats.tolist()
    assert count == 1
    assert mean == pytest.approx(log_c.mean().item(), rel=1e-5)
    assert var == pytest.approx(log_c.var(unbiased=False).item(), rel=1e-4)


def test_untrained_statistics_leave_the_modality_alone():
    ref = FlowMatchingRefiner(8, hidden=16, reliability="both", gate_init=-3.0)
    gate, weight = ref.reliability_terms(torch.randn(6, 8) * 100)  # count 0: z = 0 however odd the input
    torch.testing.assert_close(weight, torch.ones(6, 1))
    torch.testing.assert_close(gate, torch.full((6, 1), 1 / (1 + math.e**3)))


def test_score_flags_corrupted_embeddings(trained):
    ref, basis = trained
    torch.manual_seed(2)
    clean = _manifold(512, basis)
    noisy = clean + 0.5 * clean.std(dim=-1, keepdim=True) * torch.randn_like(clean)  # Table 13's k = 0.5
    with torch.no_grad():
        z_clean, z_noisy = ref.score_z(clean), ref.score_z(noisy)
        (g_clean, w_clean), (g_noisy, w_noisy) = ref.reliability_terms(clean), ref.reliability_terms(noisy)
    assert z_clean.abs().mean() < 1.0 and z_noisy.mean() > 5.0, (z_clean.mean(), z_noisy.mean())
    assert w_clean.mean() > 0.95 and w_noisy.mean() < 0.1  # the corrupted modality weighs less in the mix
    assert g_noisy.mean() > 0.9 > 0.2 > g_clean.mean()  # and its filter opens


def test_forward_applies_weight_and_input_gate(trained):
    ref, basis = trained
    e = _manifold(16, basis) + torch.randn(16, 32)
    with torch.no_grad():
        gate, weight = ref.reliability_terms(e)
        expected = weight * (e + gate * (ref.integrate(e) - e))
        torch.testing.assert_close(ref(e), expected)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_reliability_forward_keeps_shapes_and_runs_under_vmap(trained, batch):
    ref, basis = trained
    e = torch.randn(*batch, 32)
    out = ref(e)
    assert out.shape == e.shape
    rows = e.reshape(-1, 32)
    with torch.no_grad():
        torch.testing.assert_close(torch.vmap(ref)(rows), ref(rows), rtol=1e-4, atol=1e-5)


def test_vmap_does_not_write_the_statistics(trained):
    ref, basis = trained
    before = ref.score_stats.clone()
    torch.vmap(lambda e: ref.cfm_loss(e.unsqueeze(0)), randomness="different")(_manifold(4, basis))
    torch.testing.assert_close(ref.score_stats, before)


def test_relative_noise_of_zero_field_is_noise_times_row_variance():
    ref = FlowMatchingRefiner(32, hidden=16)
    with torch.no_grad():
        ref.net[-1].weight.zero_()
        ref.net[-1].bias.zero_()
    e = torch.randn(4096, 32) * torch.linspace(0.1, 3.0, 4096).unsqueeze(-1)  # rows of very different scales
    loss = ref.cfm_loss(e, noise_std=0.5, relative=True)
    expected = 0.25 * e.var(dim=-1).mean()  # E[(sigma std_row eps)^2] averaged over rows
    assert loss.item() == pytest.approx(expected.item(), rel=0.03)
