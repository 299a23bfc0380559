"""Slot Attention with the four numerical stabilisers of FreamerV1 (Section 3.2, Appendix E.1, Eq. A19-A20).

The iterative competitive assignment of Locatello et al. (2020)::

    A_ij = softmax_i( (W_q s_i)^T (W_k F_j) / sqrt(d) )              (Eq. A19, softmax over the K slots)
    s'_i = GRU( sum_j A_ij / sum_j' A_ij' * W_v F_j , s_i )          (Eq. A20, weighted mean over inputs)
    s'_i = s'_i + MLP(LN(s'_i))                                      (residual MLP)

Stabilisers (Appendix E.1, Table 5):

1. masked inputs get the logit ``-1e9`` instead of ``-inf`` (an all ``-inf`` softmax is NaN), and are then given
   exactly zero weight in the weighted mean, so padding never changes the output;
2. NaN fallback: an attention column (the distribution of one input over the K slots) that contains NaN/inf is
   replaced by the uniform ``1/K``; every substituted column is counted in :attr:`SlotAttention.nan_fallbacks`
   and reported with a rate-limited ``logger.warning`` (counting reads the count on the host, so it is skipped
   under ``torch.vmap``/``torch.func``/``torch.compile``; the substitution itself always applies). The fallback
   handles NaN arising *inside* attention; a NaN input token still poisons its sample's slots through the
   values, so the encoders reject non-finite inputs before calling Slot Attention;
3. GRU initialisation: Xavier-uniform (gain 0.5) input weights, orthogonal (gain 0.5) hidden weights, zero biases;
4. variance clipping of the slot initialisation: ``sigma = max(exp(log_sigma), 1e-6)``.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Literal

import torch
from torch import nn

from freamer_rl.layers.checks import value_checks_active

logger = logging.getLogger(__name__)

MASK_VALUE = -1e9  # stabiliser (1): finite mask logit
SIGMA_MIN = 1e-6  # stabiliser (4): lower bound of the slot-initialisation scale
GRU_GAIN = 0.5  # stabiliser (3)


def init_gru_cell(cell: nn.GRUCell, gain: float = GRU_GAIN) -> None:
    """Stabiliser (3): Xavier-uniform input weights and orthogonal hidden weights, both with ``gain``; zero biases.

    ``nn.GRUCell`` stacks the reset/update/new gates along dim 0 (``weight_ih``: ``[3*H, D_in]``,
    ``weight_hh``: ``[3*H, H]``); each gate block is initialised separately so that every ``[H, H]`` hidden
    block is itself ``gain`` times an orthogonal matrix.
    """
    hidden = cell.hidden_size
    with torch.no_grad():
        for g in range(3):
            nn.init.xavier_uniform_(cell.weight_ih[g * hidden : (g + 1) * hidden], gain=gain)
            nn.init.orthogonal_(cell.weight_hh[g * hidden : (g + 1) * hidden], gain=gain)
        if cell.bias_ih is not None:
            cell.bias_ih.zero_()
            cell.bias_hh.zero_()


class SlotAttention(nn.Module):
    """Stabilised Slot Attention (Eq. A19-A20).

    Args:
        num_slots: K, the number of slots.
        dim: d, the slot dimension (also the q/k/v dimension).
        input_dim: D_in, the feature dimension of the inputs (defaults to ``dim``).
        iters: number of attention iterations T (3 in the paper).
        hidden: hidden width of the residual MLP (defaults to ``max(dim, 128)``).
        eps: added to the attention before normalising over the inputs (Eq. A20's denominator).
        train_init: slot initialisation in training mode. ``"random"`` (default, the original method):
            ``mu + sigma * N(0, 1)`` with fresh noise at every call. ``"fixed"``: ``mu + sigma * z`` with a fixed
            noise draw ``z`` (the ``init_noise`` buffer), which makes the module deterministic in training too.
        eval_init: slot initialisation in eval mode. ``"fixed"`` (default): ``mu + sigma * z`` with the fixed
            ``init_noise`` draw. ``"mean"``: every slot starts at ``mu``.
        fast: run :meth:`_iterate` (bmm, fewer temporaries; the default) instead of the reference
            :meth:`_iterate_reference`; the maths and the parameters are the same (tested to float rounding).

    Why a deterministic initialisation in eval mode: the slots feed the policy, so at collection/evaluation time
    the same observation must give the same policy input (otherwise action log-probabilities are not reproducible).
    Using plain ``mu`` for every slot (``eval_init="mean"``) is deterministic but *degenerate*: K identical slots
    receive identical attention (the softmax over slots is uniform) and identical updates, so they stay identical
    for all iterations. ``"fixed"`` keeps determinism while breaking the symmetry with one frozen sample from the
    training distribution, so eval-mode slots look like training-mode slots.

    Attributes:
        num_slots, slot_dim (= dim), out_dim (= dim), input_dim.
        nan_fallbacks (int): cumulative number of attention columns replaced by the uniform fallback (stabiliser 2),
            counted in eager calls only (not under vmap/compile).

    Shapes:
        forward(inputs ``[*B, N, D_in]``, mask ``[*B, N]`` bool or None) -> slots ``[*B, K, d]``.
        ``mask`` is True for valid tokens. Rows with no valid token produce finite slots (all weights zero).
    """

    def __init__(
        self,
        num_slots: int,
        dim: int,
        input_dim: int | None = None,
        iters: int = 3,
        hidden: int | None = None,
        eps: float = 1e-8,
        train_init: Literal["random", "fixed"] = "random",
        eval_init: Literal["fixed", "mean"] = "fixed",
        warn_interval_s: float = 60.0,
        fast: bool = True,
    ) -> None:
        super().__init__()
        if num_slots < 1:
            raise ValueError(f"num_slots must be >= 1, got {num_slots}")
        if iters < 1:
            raise ValueError(f"iters must be >= 1, got {iters}")
        if train_init not in ("random", "fixed"):
            raise ValueError(f"train_init must be 'random' or 'fixed', got {train_init!r}")
        if eval_init not in ("fixed", "mean"):
            raise ValueError(f"eval_init must be 'fixed' or 'mean', got {eval_init!r}")
        input_dim = dim if input_dim is None else input_dim
        hidden = max(dim, 128) if hidden is None else hidden
        self.num_slots = num_slots
        self.slot_dim = dim
        self.out_dim = dim
        self.input_dim = input_dim
        self.iters = iters
        self.eps = eps
        self.scale = dim**-0.5  # 1/sqrt(d) of Eq. A19
        self.train_init = train_init
        self.eval_init = eval_init
        self.fast = bool(fast)

        # Slot initialisation N(mu, sigma^2) with a shared (learned) mu and log_sigma.
        self.slots_mu = nn.Parameter(torch.empty(1, 1, dim))
        self.slots_log_sigma = nn.Parameter(torch.empty(1, 1, dim))
        bound = math.sqrt(6.0 / (1 + dim))  # xavier-uniform on a [1, dim] matrix
        nn.init.uniform_(self.slots_mu, -bound, bound)
        nn.init.uniform_(self.slots_log_sigma, -bound, bound)
        # A frozen N(0, 1) draw for the deterministic initialisations (saved with the module).
        self.register_buffer("init_noise", torch.randn(num_slots, dim))

        self.norm_inputs = nn.LayerNorm(input_dim)
        self.norm_slots = nn.LayerNorm(dim)
        self.norm_mlp = nn.LayerNorm(dim)
        self.to_q = nn.Linear(dim, dim, bias=False)
        self.to_k = nn.Linear(input_dim, dim, bias=False)
        self.to_v = nn.Linear(input_dim, dim, bias=False)
        self.gru = nn.GRUCell(dim, dim)
        init_gru_cell(self.gru)  # stabiliser (3)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.ReLU(), nn.Linear(hidden, dim))

        # Stabiliser (2) bookkeeping: a plain int (not a buffer) so that functional calls that swap buffers
        # (TensorDict.to_module in TorchRL losses) still count into the module itself.
        self.nan_fallbacks: int = 0
        self._warn_interval_s = warn_interval_s
        self._last_warn: float | None = None

    # ------------------------------------------------------------------ helpers
    def sigma(self) -> torch.Tensor:
        """Stabiliser (4): ``max(exp(log_sigma), 1e-6)``, shape ``[1, 1, d]``."""
        return self.slots_log_sigma.exp().clamp_min(SIGMA_MIN)

    def initial_slots(self, batch: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        """Initial slots ``[batch, K, d]`` (random in training unless ``train_init='fixed'``; see class doc)."""
        mu = self.slots_mu.to(dtype)
        sigma = self.sigma().to(dtype)
        mode = self.train_init if self.training else self.eval_init
        if mode == "random":
            noise = torch.randn(batch, self.num_slots, self.slot_dim, device=device, dtype=dtype)
            return mu + sigma * noise
        if mode == "fixed":
            return (mu + sigma * self.init_noise.to(dtype)).expand(batch, -1, -1)
        return mu.expand(batch, self.num_slots, -1)

    def _report_fallbacks(self, count: int) -> None:
        self.nan_fallbacks += count
        now = time.monotonic()
        if self._last_warn is None or now - self._last_warn >= self._warn_interval_s:
            self._last_warn = now
            logger.warning(
                "SlotAttention NaN fallback: %d non-finite attention column(s) replaced by uniform 1/K in this call "
                "(%d in total for this module; warnings limited to one per %.0f s)",
                count,
                self.nan_fallbacks,
                self._warn_interval_s,
            )

    # ------------------------------------------------------------------ forward
    def forward_with_attention(
        self, inputs: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Like :meth:`forward` but also returns the last iteration's attention ``[*B, K, N]``.

        The returned attention is the softmax over slots (Eq. A19) after the NaN fallback, with masked inputs zeroed.
        """
        if inputs.dim() < 2:
            raise ValueError(f"SlotAttention inputs: expected [*B, N, {self.input_dim}], got {tuple(inputs.shape)}")
        if inputs.shape[-1] != self.input_dim:
            raise ValueError(
                f"SlotAttention inputs: expected last dim {self.input_dim}, got shape {tuple(inputs.shape)}"
            )
        batch_shape = inputs.shape[:-2]
        n_tokens = inputs.shape[-2]
        x = inputs.reshape(-1, n_tokens, self.input_dim)
        b = x.shape[0]
        if mask is not None:
            if mask.shape != inputs.shape[:-1]:
                raise ValueError(
                    f"SlotAttention mask: expected shape {tuple(inputs.shape[:-1])} (= inputs[..., 0]), "
                    f"got {tuple(mask.shape)}"
                )
            valid = mask.reshape(b, n_tokens).to(torch.bool)
            # Zero padded tokens so that garbage (even NaN) in padding cannot leak through k/v.
            x = x.masked_fill(~valid.unsqueeze(-1), 0.0)
        else:
            valid = None

        iterate = self._iterate if self.fast else self._iterate_reference
        slots, attn, fallback_count = iterate(x, valid)

        # Reading the count is a host sync: eager mode only (it is batched under vmap, also when only the
        # parameters are vmapped).
        if value_checks_active(fallback_count):
            count = int(fallback_count)  # one host sync per call (never per iteration)
            if count:
                self._report_fallbacks(count)
        return (
            slots.reshape(*batch_shape, self.num_slots, self.slot_dim),
            attn.reshape(*batch_shape, self.num_slots, n_tokens),
        )

    def _iterate(self, x: torch.Tensor, valid: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The iterations of Eq. A19-A20 with fewer, larger ops (same maths as :meth:`_iterate_reference`).

        ``x [b, N, D_in]`` (padding zeroed), ``valid [b, N]`` bool or None -> (slots ``[b, K, d]``, last attention
        ``[b, K, N]``, number of NaN-fallback columns over all iterations ``[]``). Differences from the reference,
        all exact up to float rounding: the logits are ``bmm(q, k^T)`` with ``k^T`` a view taken once (no einsum
        permute copies per iteration), scaled in place; the weighted mean is a plain ``bmm``; the fallback writes the
        scalar ``1/K`` with ``masked_fill`` (no full-size constant tensor per iteration); the validity masks are built
        once. (Fusing k and v into one matmul with the stacked ``[W_k; W_v]`` measured no faster: its backward
        concatenates the two ``[b, N, d]`` gradients.)
        """
        b, n_tokens = x.shape[0], x.shape[1]
        d = self.slot_dim
        x = self.norm_inputs(x)
        k_t = self.to_k(x).transpose(1, 2)  # [b, d, N]
        v = self.to_v(x)  # [b, N, d]
        if valid is not None:
            v = v.masked_fill(~valid.unsqueeze(-1), 0.0)
            weight_mask = valid.unsqueeze(1).to(x.dtype)  # [b, 1, N]
            masked_logits = ~valid.unsqueeze(1)  # [b, 1, N]

        slots = self.initial_slots(b, x.device, x.dtype)
        fallback_count = x.new_zeros((), dtype=torch.long)
        attn = x.new_zeros(b, self.num_slots, n_tokens)
        for _ in range(self.iters):
            slots_prev = slots
            q = self.to_q(self.norm_slots(slots))  # [b, K, d]
            # in-place scaling of the fresh bmm output: d(c*y)/dy = c needs no saved tensor
            logits = torch.bmm(q, k_t).mul_(self.scale)  # Eq. A19 numerator, [b, K, N]
            if valid is not None:
                logits = logits.masked_fill(masked_logits, MASK_VALUE)  # stabiliser (1)
            attn = logits.softmax(dim=1)  # competition over the K slots
            bad = ~torch.isfinite(attn).all(dim=1, keepdim=True)  # stabiliser (2), [b, 1, N]
            attn = attn.masked_fill(bad, 1.0 / self.num_slots)
            fallback_count = fallback_count + bad.sum()
            weights = attn + self.eps  # Eq. A20: weighted mean over inputs
            if valid is not None:
                weights = weights * weight_mask
                attn = attn * weight_mask
            weights = weights / weights.sum(dim=-1, keepdim=True).clamp_min(self.eps)
            updates = torch.bmm(weights, v)  # [b, K, d]
            slots = self.gru(updates.reshape(-1, d), slots_prev.reshape(-1, d)).reshape(b, self.num_slots, d)
            slots = slots + self.mlp(self.norm_mlp(slots))
        return slots, attn, fallback_count

    def _iterate_reference(
        self, x: torch.Tensor, valid: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The reference iterations (the original code, kept for tests and ``benchmarks/throughput_pixels.py``).

        ``x [b, N, D_in]`` (padding zeroed), ``valid [b, N]`` bool or None -> (slots ``[b, K, d]``, last attention
        ``[b, K, N]``, number of NaN-fallback columns over all iterations ``[]``).
        """
        b, n_tokens = x.shape[0], x.shape[1]
        x = self.norm_inputs(x)
        k = self.to_k(x)  # [b, N, d]
        v = self.to_v(x)  # [b, N, d]
        if valid is not None:
            v = v.masked_fill(~valid.unsqueeze(-1), 0.0)
            weight_mask = valid.unsqueeze(1).to(x.dtype)  # [b, 1, N]

        slots = self.initial_slots(b, x.device, x.dtype)
        fallback_count = x.new_zeros((), dtype=torch.long)
        attn = x.new_zeros(b, self.num_slots, n_tokens)
        for _ in range(self.iters):
            slots_prev = slots
            q = self.to_q(self.norm_slots(slots))  # [b, K, d]
            logits = torch.einsum("bkd,bnd->bkn", q, k) * self.scale  # Eq. A19 numerator
            if valid is not None:
                logits = logits.masked_fill(~valid.unsqueeze(1), MASK_VALUE)  # stabiliser (1)
            attn = logits.softmax(dim=1)  # competition over the K slots
            # Stabiliser (2): uniform 1/K for every input column that is not finite.
            bad = ~torch.isfinite(attn).all(dim=1, keepdim=True)  # [b, 1, N]
            attn = torch.where(bad, torch.full_like(attn, 1.0 / self.num_slots), attn)
            n_bad = bad.sum()
            fallback_count = fallback_count + n_bad
            # Eq. A20: weighted mean over inputs (masked inputs get exactly zero weight).
            weights = attn + self.eps
            if valid is not None:
                weights = weights * weight_mask
                attn = attn * weight_mask
            weights = weights / weights.sum(dim=-1, keepdim=True).clamp_min(self.eps)
            updates = torch.einsum("bkn,bnd->bkd", weights, v)
            slots = self.gru(updates.reshape(-1, self.slot_dim), slots_prev.reshape(-1, self.slot_dim))
            slots = slots.reshape(b, self.num_slots, self.slot_dim)
            slots = slots + self.mlp(self.norm_mlp(slots))

        return slots, attn, fallback_count

    def forward(self, inputs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Slots ``[*B, K, d]`` from inputs ``[*B, N, D_in]`` and an optional validity mask ``[*B, N]`` (True = valid)."""
        return self.forward_with_attention(inputs, mask)[0]

    def extra_repr(self) -> str:
        return (
            f"num_slots={self.num_slots}, dim={self.slot_dim}, input_dim={self.input_dim}, iters={self.iters}, "
            f"eps={self.eps}, train_init={self.train_init!r}, eval_init={self.eval_init!r}"
        )
