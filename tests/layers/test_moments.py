"""merge_moments: batches merged one at a time give the moments of all the data at once."""

import pytest
import torch

from freamer_rl.layers.moments import merge_moments


@pytest.mark.parametrize("shape", [(), (3,)])
def test_merging_batches_gives_the_moments_of_everything(shape):
    gen = torch.Generator().manual_seed(0)
    batches = [torch.randn(n, *shape, generator=gen, dtype=torch.float64) * 3 + 1 for n in (5, 1, 12)]
    count, mean, var = torch.zeros(()), torch.zeros(shape, dtype=torch.float64), torch.zeros(shape, dtype=torch.float64)
    for b in batches:
        count, mean, var = merge_moments(count, mean, var, b.shape[0], b.mean(0), b.var(0, unbiased=False))
    everything = torch.cat(batches)
    assert float(count) == 18
    assert torch.allclose(mean, everything.mean(0)) and torch.allclose(var, everything.var(0, unbiased=False))
