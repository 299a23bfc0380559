"""Fourier Neural Operator layers: spectral convolution, the FNO state encoder (Layer 1, Appendix E.2) and the
FNO spectral fusion of the refined modality embeddings (Layer 3, Section 3.4, Appendix D.2-D.3, Eq. A14-A17).

Spectral convolution (Eq. A14 and the spectral term of A15): for an input ``x [*B, C_in, N]``

    X_k = rfft(x)_k,                        k = 0 .. N//2
    Y_{o,k} = sum_i R_{i,o,k} X_{i,k}        for k < K (the kept modes), Y_{o,k} = 0 for k >= K
    y = irfft(Y, n=N)                        [*B, C_out, N]

with complex weights ``R_k in C^{C_in x C_out}``. A complex weight multiplies each Fourier mode by a gain and a
*phase*: ``R_k = exp(-j 2 pi k tau / N)`` is a circular delay by ``tau`` samples (Eq. A17), so the layer can
represent phase-shifted correlations between channels, which a real-valued pointwise mixing cannot.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from freamer_rl.layers.checks import check_finite, is_transformed, value_checks_active
from freamer_rl.layers.compiled import CompileOrEager

__all__ = ["SpectralConv1d", "StateFNOEncoder", "FNOFuser", "smoothness_loss"]


def _compute_dtype(x: torch.Tensor) -> torch.dtype:
    """The dtype the spectral maths runs in: float64 for float64 inputs, float32 otherwise (autocast is off)."""
    return torch.float64 if x.dtype == torch.float64 else torch.float32


class SpectralConv1d(nn.Module):
    """1-D spectral convolution ``y = IFFT(R_k . FFT(x))`` on the first ``modes`` Fourier modes (Eq. A14-A15).

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        modes: number ``K`` of lowest Fourier modes kept (must be ``<= N//2 + 1`` for input length ``N``).

    The complex weights are stored as a real parameter ``weight [C_in, C_out, K, 2]`` (real, imaginary) and viewed
    as complex in :meth:`forward`: optimisers then only ever see real tensors (Adam/AdamW with weight decay had bugs
    on complex parameters, pytorch#100707). The FFTs run in float32 (autocast disabled) when the input is
    half/bfloat16; float64 inputs stay float64. The output has the input's dtype.

    Shapes:
        forward: ``x [*B, C_in, N] -> y [*B, C_out, N]``.
    """

    def __init__(self, in_channels: int, out_channels: int, modes: int) -> None:
        super().__init__()
        if in_channels <= 0 or out_channels <= 0:
            raise ValueError(
                f"in_channels and out_channels must be positive; got in_channels={in_channels}, "
                f"out_channels={out_channels}"
            )
        if modes < 1:
            raise ValueError(f"modes must be >= 1; got modes={modes}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.modes = modes
        # |R|^2 has expectation 1/in_channels: a mode's output power matches its input power at init.
        std = (2.0 * in_channels) ** -0.5
        self.weight = nn.Parameter(torch.randn(in_channels, out_channels, modes, 2) * std)

    @property
    def complex_weight(self) -> torch.Tensor:
        """The weights as a complex tensor ``R [C_in, C_out, K]`` (a view of :attr:`weight`)."""
        return torch.view_as_complex(self.weight)

    def check_length(self, n: int) -> None:
        """Raise ``ValueError`` if ``modes`` exceeds the ``n//2 + 1`` modes of a length-``n`` real signal."""
        if self.modes > n // 2 + 1:
            raise ValueError(
                f"SpectralConv1d: modes={self.modes} exceeds the number of rfft modes n//2+1={n // 2 + 1} "
                f"available for input length n={n}; use modes <= {n // 2 + 1}"
            )

    def _checked_length(self, x: torch.Tensor, *, channels_last: bool) -> int:
        """Length ``N`` of ``x [*B, C_in, N]`` (``[*B, N, C_in]`` if ``channels_last``); ``ValueError`` if the
        channels or the length (:meth:`check_length`) do not fit."""
        if x.ndim < 2 or x.shape[-1 if channels_last else -2] != self.in_channels:
            if channels_last:
                raise ValueError(
                    f"SpectralConv1d.forward_channels_last expects x of shape [*B, N, in_channels={self.in_channels}]; "
                    f"got {tuple(x.shape)}"
                )
            raise ValueError(
                f"SpectralConv1d expects x of shape [*B, in_channels={self.in_channels}, N]; got {tuple(x.shape)}"
            )
        n = x.shape[-2 if channels_last else -1]
        self.check_length(n)
        return n

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = self._checked_length(x, channels_last=False)
        out_dtype = x.dtype
        compute_dtype = _compute_dtype(x)
        with torch.autocast(device_type=x.device.type, enabled=False):
            xf = x.to(compute_dtype)
            x_ft = torch.fft.rfft(xf, dim=-1)[..., : self.modes]  # [*B, C_in, K]
            weight = torch.view_as_complex(self.weight.to(compute_dtype).contiguous())
            y_low = torch.einsum("...ix,iox->...ox", x_ft, weight)  # [*B, C_out, K]
            n_freq = n // 2 + 1
            if n_freq > self.modes:
                pad = y_low.new_zeros(*y_low.shape[:-1], n_freq - self.modes)
                y_ft = torch.cat([y_low, pad], dim=-1)
            else:
                y_ft = y_low
            y = torch.fft.irfft(y_ft, n=n, dim=-1)
        return y.to(out_dtype)

    def _dft_bases(self, n: int, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, ...]:
        """Real DFT bases for the kept modes, cached per ``(n, dtype, device)``.

        Forward: ``Re X = C x``, ``Im X = S x`` with ``C = cos(2 pi k n / N)``, ``S = -sin(...)`` (``[K, N]``).
        Inverse (irfft of a spectrum that is zero beyond mode K): ``y = A Re Y + B Im Y`` with
        ``A = c_k cos(.)^T / N`` and ``B = -c_k sin(.)^T / N`` (``[N, K]``), ``c_0 = 1``, ``c_k = 2``, and ``c = 1``
        for the Nyquist mode of an even ``N``; the imaginary parts of the DC and Nyquist modes drop out as in irfft.
        """
        key = (n, dtype, device)
        if getattr(self, "_basis_key", None) != key:
            k = torch.arange(self.modes, dtype=torch.float64)
            t = torch.arange(n, dtype=torch.float64)
            ang = 2.0 * torch.pi * k[:, None] * t[None, :] / n  # [K, N]
            c = torch.full((self.modes,), 2.0, dtype=torch.float64)
            c[0] = 1.0
            if n % 2 == 0 and self.modes - 1 == n // 2:
                c[-1] = 1.0
            bases = (
                torch.cos(ang),
                -torch.sin(ang),
                (c[:, None] * torch.cos(ang) / n).T.contiguous(),
                (-c[:, None] * torch.sin(ang) / n).T.contiguous(),
            )
            self._bases = tuple(b.to(dtype=dtype, device=device) for b in bases)
            self._basis_key = key
        return self._bases

    def forward_channels_last(self, x: torch.Tensor) -> torch.Tensor:
        """The same operator on a channels-last input ``x [*B, N, C_in] -> [*B, N, C_out]`` (through
        :meth:`forward_length_first`)."""
        self._checked_length(x, channels_last=True)
        return self.forward_length_first(x.movedim(-2, 0)).movedim(0, -2)

    def forward_length_first(self, x: torch.Tensor) -> torch.Tensor:
        """The same operator on a length-first input ``x [N, *B, C_in] -> [N, *B, C_out]``.

        Uses dense real DFT bases instead of FFTs: for the short lengths here (49 grid cells) three matmuls with
        the batch folded into the columns (``[2K, N] @ [N, B*C]``, a per-mode ``[K, B, 2C] x [K, 2C, 2C_out]``
        real form of the complex product, ``[N, 2K] @ [2K, B*C_out]``) are several times faster on CPU than FFTs or
        per-sample small matmuls, forward and backward.
        """
        if x.ndim < 2 or x.shape[-1] != self.in_channels:
            raise ValueError(
                f"SpectralConv1d.forward_length_first expects x of shape [N, *B, in_channels={self.in_channels}]; "
                f"got {tuple(x.shape)}"
            )
        n, batch = x.shape[0], x.shape[1:-1]
        self.check_length(n)
        rows, k = math.prod(batch), self.modes
        out_dtype = x.dtype
        compute_dtype = _compute_dtype(x)
        with torch.autocast(device_type=x.device.type, enabled=False):
            fwd_re, fwd_im, inv_re, inv_im = self._dft_bases(n, compute_dtype, x.device)
            xf = x.to(compute_dtype).reshape(n, rows * self.in_channels)
            spec = (torch.cat([fwd_re, fwd_im]) @ xf).view(2, k, rows, self.in_channels)  # Re X, Im X
            w = self.weight.to(compute_dtype).permute(2, 0, 1, 3)  # [K, C_in, C_out, 2]
            w_re, w_im = w[..., 0], w[..., 1]
            # Y_k = X_k R_k as real matmuls: [Re Y, Im Y] = Re X [w_re, w_im] + Im X [-w_im, w_re]
            y = torch.baddbmm(spec[0] @ torch.cat([w_re, w_im], -1), spec[1], torch.cat([-w_im, w_re], -1))
            y = y.view(k, rows, 2, self.out_channels).permute(2, 0, 1, 3).reshape(2 * k, rows * self.out_channels)
            out = torch.cat([inv_re, inv_im], dim=1) @ y  # [N, B*C_out]
        return out.view(n, *batch, self.out_channels).to(out_dtype)

    def extra_repr(self) -> str:
        return f"in_channels={self.in_channels}, out_channels={self.out_channels}, modes={self.modes}"


class StateFNOEncoder(nn.Module):
    """FNO state encoder for MiniGrid's symbolic view (Layer 1, Appendix E.2: ``e = IFFT(R_k FFT(o)) + W o``).

    Pipeline: object/colour/state indices are embedded (three ``nn.Embedding(., channels)``, summed) ->
    the ``view_size x view_size`` cells are flattened to a length-``L = view_size**2`` sequence with ``channels``
    channels -> one FNO block ``h = GELU(SpectralConv1d(o) + W o)`` (``W`` a 1x1 convolution) -> flatten ->
    ``Linear(channels * L, out_dim)`` -> plus a direction embedding ``nn.Embedding(num_directions, out_dim)``.

    Args:
        out_dim: output size ``d``.
        channels: FNO channel width.
        modes: Fourier modes kept along the length-``L`` cell sequence (``<= L//2 + 1``).
        num_objects, num_colors, num_states, num_directions: index ranges (MiniGrid: 11, 6, 3, 4).
        view_size: side of the agent's square view (MiniGrid default 7).
        compile: run the maths (after the eager input checks) through ``torch.compile`` with dynamic shapes
            (:class:`~freamer_rl.layers.compiled.CompileOrEager`); eager under ``torch.vmap``/``torch.func``.

    Shapes:
        forward: ``grid int64 [*B, view_size, view_size, 3]``, ``direction int64 [*B]`` (or ``[*B, 1]``)
        -> ``[*B, out_dim]``.

    Index ranges are checked (``ValueError``) in eager mode only; under ``torch.vmap``/``torch.func``/
    ``torch.compile`` the forward is sync-free and computes the same maths without that check
    (see :mod:`freamer_rl.layers.checks`).
    """

    def __init__(
        self,
        out_dim: int = 128,
        channels: int = 32,
        modes: int = 12,
        num_objects: int = 11,
        num_colors: int = 6,
        num_states: int = 3,
        num_directions: int = 4,
        *,
        view_size: int = 7,
        compile: bool = False,
    ) -> None:
        super().__init__()
        self.out_dim = out_dim
        self.channels = channels
        self.view_size = view_size
        self.seq_len = view_size * view_size
        self.ranges = (num_objects, num_colors, num_states)
        self.num_directions = num_directions
        self.object_embed = nn.Embedding(num_objects, channels)
        self.color_embed = nn.Embedding(num_colors, channels)
        self.state_embed = nn.Embedding(num_states, channels)
        self.spectral = SpectralConv1d(channels, channels, modes)
        self.spectral.check_length(self.seq_len)
        self.pointwise = nn.Conv1d(channels, channels, kernel_size=1)
        self.proj = nn.Linear(channels * self.seq_len, out_dim)  # input flattened cell-major: [L, C]
        self.direction_embed = nn.Embedding(num_directions, out_dim)
        self.register_buffer("_offsets", torch.tensor([0, num_objects, num_objects + num_colors]), persistent=False)
        # a plain attribute (not a Module): parameters and state dict are unchanged
        self._compiled_encode = CompileOrEager(self._encode, "StateFNOEncoder", dynamic=True) if compile else None

    @property
    def compile_fallbacks(self) -> int:
        """How often ``compile=True`` fell back to eager execution (0 or 1)."""
        return self._compiled_encode.fallbacks if self._compiled_encode is not None else 0

    def _validate(self, grid: torch.Tensor, direction: torch.Tensor) -> None:
        v = self.view_size
        if grid.ndim < 3 or tuple(grid.shape[-3:]) != (v, v, 3):
            raise ValueError(f"grid must have shape [*B, {v}, {v}, 3]; got {tuple(grid.shape)}")
        if grid.dtype.is_floating_point or grid.dtype == torch.bool or grid.dtype.is_complex:
            raise TypeError(f"grid must hold integer indices (int64); got dtype {grid.dtype}")
        if direction.shape != grid.shape[:-3]:  # [*B, 1] is squeezed by the caller (forward)
            raise ValueError(
                f"direction must have shape [*B]={tuple(grid.shape[:-3])} matching grid [*B, {v}, {v}, 3]; "
                f"got {tuple(direction.shape)}"
            )
        if direction.dtype.is_floating_point or direction.dtype == torch.bool or direction.dtype.is_complex:
            raise TypeError(f"direction must hold integer indices (int64); got dtype {direction.dtype}")
        if not value_checks_active(grid, direction):
            return  # under vmap/grad/compile: index ranges are not checked (reading them is a host sync)
        if grid.numel() > 0:
            for c, (name, size) in enumerate(zip(("object", "colour", "state"), self.ranges)):
                lo, hi = int(grid[..., c].min()), int(grid[..., c].max())
                if lo < 0 or hi >= size:
                    raise ValueError(
                        f"grid[..., {c}] ({name} index) must lie in [0, {size - 1}]; got values in [{lo}, {hi}]"
                    )
        if direction.numel() > 0:
            lo, hi = int(direction.min()), int(direction.max())
            if lo < 0 or hi >= self.num_directions:
                raise ValueError(f"direction must lie in [0, {self.num_directions - 1}]; got values in [{lo}, {hi}]")

    def forward(self, grid: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        if grid.ndim >= 3 and direction.shape == (*grid.shape[:-3], 1):
            direction = direction.squeeze(-1)
        self._validate(grid, direction)
        eager = self._compiled_encode is None or is_transformed(grid, direction)
        return (self._encode if eager else self._compiled_encode)(grid, direction)

    def _encode(self, grid: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        """The maths of :meth:`forward` on validated inputs (``direction [*B]``)."""
        batch_shape = grid.shape[:-3]
        g = grid.long().reshape(-1, self.seq_len, 3).transpose(0, 1)  # [L, B', 3]: cell-major for the DFT matmuls
        # The three embeddings summed, as one multi-hot matmul (identical maths, much faster backward than three
        # lookups): o = multi_hot [L, B', n_obj + n_col + n_state] @ stacked tables. The 1x1 convolution is linear
        # too: W o + b = multi_hot @ (table W^T) + b, a 20-row product instead of a [L B', C] x [C, C] matmul.
        table = torch.cat([self.object_embed.weight, self.color_embed.weight, self.state_embed.weight])
        pointwise_table = F.linear(table, self.pointwise.weight.squeeze(-1))
        # Out-of-place scatter: under vmap ``g`` is batched but a fresh zeros tensor is not, and an in-place
        # scatter into it is refused.
        multi_hot = torch.zeros(*g.shape[:-1], table.shape[0], dtype=table.dtype, device=g.device)
        multi_hot = multi_hot.scatter(-1, g + self._offsets.to(g.device), 1.0)
        o = multi_hot @ table  # [L, B', C]
        pointwise = multi_hot @ pointwise_table + self.pointwise.bias  # the 1x1 conv W o
        h = F.gelu(self.spectral.forward_length_first(o) + pointwise)  # Appendix E.2, [L, B', C]
        flat = h.transpose(0, 1).reshape(h.shape[1], self.seq_len * self.channels)  # [B', L*C] cell-major (proj)
        e = self.proj(flat) + self.direction_embed(direction.long().reshape(-1))
        return e.reshape(*batch_shape, self.out_dim)


def smoothness_loss(e: torch.Tensor) -> torch.Tensor:
    """Cross-modal smoothness regulariser (Eq. A16, without ``lambda_s`` which the caller applies).

    ``sum_{m=1}^{M-1} ||E[m, :] - E[m+1, :]||^2`` (squared L2 over ``d``, summed over adjacent modality pairs),
    averaged over the leading batch dims.

    Args:
        e: ``[*B, M, d]``.

    Returns:
        0-d tensor.
    """
    if e.ndim < 2:
        raise ValueError(f"smoothness_loss expects E of shape [*B, M, d]; got {tuple(e.shape)}")
    diff = e[..., 1:, :] - e[..., :-1, :]
    per_sample = diff.pow(2).sum(dim=(-2, -1))  # [*B]
    return per_sample.mean()


class FNOFuser(nn.Module):
    """FNO spectral fusion of the refined modality embeddings (Layer 3, Section 3.4, Eq. A14-A15).

    ``E [*B, M, d]`` stacks the ``M`` refined embeddings. The Fourier transform runs along ``d`` and the modality
    axis plays the role of channels, so ``R_k in C^{M x M}`` for the first ``K`` modes mixes modalities per
    frequency (a :class:`SpectralConv1d` with ``M`` in/out channels). The pointwise path ``W E`` is a 1x1 mixing
    *across modalities*, ``(W E)[m, :] = sum_{m'} W[m, m'] E[m', :] + b[m]`` (an ``nn.Linear(M, M)`` applied along
    the modality axis) -- the same role as the 1x1 convolution bypass of an FNO block, and it keeps the fuser's
    parameter count independent of ``d``. Then

        E_out = E + s * GELU(LN_d(IFFT(R_k E^_k) + W E))

    with ``LN_d`` a LayerNorm over ``d`` and ``s`` a learnable scalar initialised to ``residual_scale``
    (Table A20: 0.1). With ``s = 1`` this is exactly Eq. A15. The fused vector is the mean over modalities,
    optionally followed by a LayerNorm over ``d`` (``output_norm``).

    Why ``output_norm``: the mean over ``M`` modalities scales each modality's own (state-dependent) content by
    ``1/M``, while modalities that are constant over an episode (MiniGrid's mission, an all-zero reward history)
    add only an offset. Without a norm the policy input therefore shrinks as modalities are added (MultiRoom-N2-S4:
    per-dimension spread of ``fused`` over states 0.29 with the state modality alone, 0.095 with three), and the
    heads need proportionally larger weight changes to act on it. A LayerNorm makes the scale independent of
    ``M``.

    Args:
        num_modalities: ``M``.
        dim: ``d``.
        modes: ``K`` (Table A20: 16; ``<= d//2 + 1``).
        residual_scale: initial value of ``s``.
        output_norm: apply a LayerNorm over ``d`` to the pooled vector (not to ``E_out``).

    Shapes:
        forward: ``E [*B, M, d] -> (fused [*B, d], E_out [*B, M, d])``.

    A NaN/Inf in ``E`` raises ``ValueError`` in eager mode; the check is skipped (same maths) under
    ``torch.vmap``/``torch.func``/``torch.compile`` (see :mod:`freamer_rl.layers.checks`).
    """

    def __init__(
        self, num_modalities: int, dim: int, modes: int = 16, residual_scale: float = 0.1, output_norm: bool = False
    ) -> None:
        super().__init__()
        if num_modalities < 1 or dim < 1:
            raise ValueError(f"num_modalities and dim must be positive; got {num_modalities}, {dim}")
        self.num_modalities = num_modalities
        self.dim = dim
        self.spectral = SpectralConv1d(num_modalities, num_modalities, modes)
        self.spectral.check_length(dim)
        self.pointwise = nn.Linear(num_modalities, num_modalities)
        self.norm = nn.LayerNorm(dim)
        self.residual_scale = nn.Parameter(torch.tensor(float(residual_scale)))
        self.output_norm = nn.LayerNorm(dim) if output_norm else None

    def forward(self, e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if e.ndim < 2 or tuple(e.shape[-2:]) != (self.num_modalities, self.dim):
            raise ValueError(
                f"FNOFuser expects E of shape [*B, M={self.num_modalities}, d={self.dim}]; got {tuple(e.shape)}"
            )
        check_finite(e, "FNOFuser modal_stack")
        # [*B, M, d]  IFFT(R_k E^_k) (Eq. A14), as DFT matmuls along d (faster than FFTs for d = 128 on CPU)
        spec = self.spectral.forward_length_first(e.movedim(-1, 0)).movedim(0, -1)
        # [*B, M, d]  W E, the 1x1 mixing across modalities (einsum: 4x faster than a Linear on the transpose)
        pw = torch.einsum("nm,...md->...nd", self.pointwise.weight, e) + self.pointwise.bias[:, None]
        e_out = e + self.residual_scale.to(e.dtype) * F.gelu(self.norm(spec + pw))  # Eq. A15 (scaled residual)
        fused = e_out.mean(dim=-2)
        if self.output_norm is not None:
            fused = self.output_norm(fused)
        return fused, e_out

    smoothness_loss = staticmethod(smoothness_loss)
