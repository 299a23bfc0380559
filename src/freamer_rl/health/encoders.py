"""Observation encoders of the health domain (paper Section 5.2 / Table 15, Appendix J.2).

Four encoders map a wearable-sensor observation ``{"imu": [*B, 36], "hr_features": [*B, 16]}`` to an embedding
``o_t^embed`` of shape ``[*B, E]`` that enters the RSSM posterior (Eq. A25). Each one plugs into
:class:`~freamer_rl.world_model.rssm.WorldModel` as its ``encoder``:

==============================  ====================================================================  ==============
class                           what it does                                                          WorldModel API
==============================  ====================================================================  ==============
:class:`MLPHealthEncoder`       vanilla MLP over ``[symlog(imu); hr_features]``                         plain module
:class:`CNNHealthEncoder`       1-D conv over the 3 IMU sites (12 channels each) + an HR MLP            plain module
:class:`SlotCrossAttnHealthEncoder`  J.2 Stage 1 only: sites as slots -> self-attention ->            plain module
                                cross-attention with ``MLP(HR)`` (Eq. A26) -> pooled
:class:`FoundationHealthEncoder`  J.2 Stages 1-4: Stage 1 -> per-modality flow matching (Eq. 1-3)    TensorDictModule
                                -> FNO fusion (Eq. A14-A15) -> DNC memory (Appendix F.1)                (stateful)
==============================  ====================================================================  ==============

Inputs: ``imu`` is the health env's 36-dim vector, ordered ``hand, chest, ankle`` x ``acc16 xyz, acc6 xyz, gyro
xyz, mag xyz`` (:data:`freamer_rl.data.pamap2.IMU_FEATURE_NAMES`), viewed here as ``[*B, 3 sites, 12 channels]``;
``hr_features`` are the 16 heart-rate features (already scaled to O(1) by the loader). The IMU goes through
:func:`~freamer_rl.world_model.rssm.symlog` (``symlog_inputs``, default True) like the world model's default
encoder; the HR features are used as they are.

Common interface (all four): ``out_dim`` (= ``E``), ``obs_keys``, ``forward``, and the online *step* API used when
filtering a real env step by step: ``state_shapes()`` (``{name: per-element shape}``, empty for the stateless ones),
``initial_state(batch_shape)`` and ``step(obs, state, is_first) -> (embed [*B, E], new_state)``; plus
``aux_loss()`` (``{}`` except for the foundation encoder), ``clear_cache()`` and ``gates`` (``{}`` except for the
foundation encoder). :class:`HealthEncoder` is that interface as a typed ``Protocol``: the pipeline calls it
without probing what an encoder can do.

The foundation encoder is recurrent (the DNC memory). Inside :meth:`WorldModel.loss` it receives a TensorDict of
batch ``[*B, T+1]`` holding the observations and ``"is_init"`` (``[*B, T+1, 1]``, True where a sequence starts) and
loops the DNC over time itself, zeroing the memory wherever ``is_init`` is True; online it is driven with
:meth:`FoundationHealthEncoder.step`. Looping over a sequence equals stepping through it (tested).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn

from freamer_rl.layers.dnc import DNCMemory
from freamer_rl.layers.encoders import CrossModalAttention
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fno import FNOFuser, smoothness_loss
from freamer_rl.world_model.encoder import StatelessStepMixin, StepEncoder
from freamer_rl.world_model.rssm import mlp, symlog

logger = logging.getLogger(__name__)

__all__ = [
    "HealthEncoder",
    "ENCODER_KINDS",
    "IMU_DIM",
    "HR_DIM",
    "IMU_SITES",
    "IMU_CHANNELS",
    "MLPHealthEncoder",
    "CNNHealthEncoder",
    "HealthStage1",
    "SlotCrossAttnHealthEncoder",
    "FoundationHealthEncoder",
    "make_health_encoder",
]

IMU_DIM, HR_DIM = 36, 16
IMU_SITES, IMU_CHANNELS = 3, 12
#: Names accepted by :func:`make_health_encoder` (Table 15 rows).
ENCODER_KINDS: tuple[str, ...] = ("mlp", "cnn", "slotattn", "foundation")
#: Modality names of the foundation encoder (Stage 2 refiners, ``gate_init`` keys), as in CONVENTIONS ("embed", m).
MODALITIES: tuple[str, ...] = ("imu", "heart_rate")


#: What every health encoder can do (the four of :data:`ENCODER_KINDS`; any encoder implementing it plugs into the
#: health pipeline): the world model's :class:`~freamer_rl.world_model.encoder.StepEncoder` protocol.
HealthEncoder = StepEncoder


def _check(name: str, x: torch.Tensor, dim: int) -> None:
    if x.ndim < 1 or x.shape[-1] != dim:
        raise ValueError(f"observation {name!r}: expected shape [*B, {dim}], got {tuple(x.shape)}")


class _HealthEncoderMixin(StatelessStepMixin):
    """Input handling and the stateless step API shared by the four encoders."""

    imu_key: NestedKey
    hr_key: NestedKey
    symlog_inputs: bool

    @property
    def obs_keys(self) -> tuple[NestedKey, NestedKey]:
        return (self.imu_key, self.hr_key)

    def _inputs(self, obs: Mapping | TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``obs`` mapping -> ``(imu [*B, 36], hr [*B, 16])`` float, IMU symlog-squashed; batch dims must agree."""
        try:
            imu, hr = obs[self.imu_key], obs[self.hr_key]
        except KeyError as err:
            raise KeyError(
                f"{type(self).__name__}: observation key {err.args[0]!r} missing (needs {self.imu_key!r} [*B, "
                f"{IMU_DIM}] and {self.hr_key!r} [*B, {HR_DIM}])"
            ) from None
        _check(str(self.imu_key), imu, IMU_DIM)
        _check(str(self.hr_key), hr, HR_DIM)
        if imu.shape[:-1] != hr.shape[:-1]:
            raise ValueError(
                f"{type(self).__name__}: batch dims differ: {self.imu_key!r} {tuple(imu.shape)} vs "
                f"{self.hr_key!r} {tuple(hr.shape)}"
            )
        imu = imu.float()
        return (symlog(imu) if self.symlog_inputs else imu), hr.float()

    # -- online step API: the stateless defaults of StatelessStepMixin, stepping through ``_embed`` -----------------
    def step(
        self, obs: Mapping, state: Mapping[str, torch.Tensor] | None = None, is_first: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One online step: ``obs {key: [*B, d]}`` -> ``(embed [*B, E], new_state)``. Stateless: ``forward``."""
        return self._embed(obs), {}


class MLPHealthEncoder(_HealthEncoderMixin, nn.Module):
    """Vanilla MLP encoder (Table 15 "MLP (vanilla)").

    ``[symlog(imu); hr_features]`` ``[*B, 52]`` -> ``layers`` x (Linear -> LayerNorm -> SiLU) -> Linear ->
    ``[*B, out_dim]``.

    Args:
        out_dim: embedding size ``E``.
        hidden, layers: MLP width and depth.
        imu_key, hr_key: observation keys. symlog_inputs: squash the IMU with symlog.
    """

    def __init__(self, out_dim: int = 128, hidden: int = 256, layers: int = 2, *, imu_key: NestedKey = "imu",
                 hr_key: NestedKey = "hr_features", symlog_inputs: bool = True) -> None:  # fmt: skip
        super().__init__()
        self.out_dim = out_dim
        self.imu_key, self.hr_key, self.symlog_inputs = imu_key, hr_key, symlog_inputs
        self.net = mlp(IMU_DIM + HR_DIM, hidden, out_dim, layers)

    def _embed(self, obs: Mapping) -> torch.Tensor:
        imu, hr = self._inputs(obs)
        return self.net(torch.cat([imu, hr], dim=-1))

    def forward(self, obs: Mapping) -> torch.Tensor:
        """``{imu: [*B, 36], hr_features: [*B, 16]}`` -> ``[*B, out_dim]``."""
        return self._embed(obs)


class CNNHealthEncoder(_HealthEncoderMixin, nn.Module):
    """1-D convolutional encoder (Table 15 "CNN").

    The IMU is viewed as a length-3 sequence (hand, chest, ankle) with 12 channels, ``[b, 12, 3]``, and passes
    through ``Conv1d(12, C, 3, padding=1) -> SiLU -> Conv1d(C, C, 3, padding=1) -> SiLU`` -> flatten ``[b, 3C]``;
    the HR features through ``MLP(16 -> hidden)``; both are concatenated -> Linear -> LayerNorm -> SiLU -> Linear
    -> ``[*B, out_dim]``.

    Args:
        out_dim: ``E``. channels: conv width ``C``. hidden: HR MLP / head width.
    """

    def __init__(self, out_dim: int = 128, channels: int = 32, hidden: int = 128, *, imu_key: NestedKey = "imu",
                 hr_key: NestedKey = "hr_features", symlog_inputs: bool = True) -> None:  # fmt: skip
        super().__init__()
        self.out_dim = out_dim
        self.imu_key, self.hr_key, self.symlog_inputs = imu_key, hr_key, symlog_inputs
        self.conv = nn.Sequential(
            nn.Conv1d(IMU_CHANNELS, channels, 3, padding=1),
            nn.SiLU(),
            nn.Conv1d(channels, channels, 3, padding=1),
            nn.SiLU(),
        )
        self.hr_net = mlp(HR_DIM, hidden, hidden, layers=1)
        self.head = mlp(channels * IMU_SITES + hidden, hidden, out_dim, layers=1)

    def _embed(self, obs: Mapping) -> torch.Tensor:
        imu, hr = self._inputs(obs)
        lead = imu.shape[:-1]
        x = imu.reshape(-1, IMU_SITES, IMU_CHANNELS).transpose(1, 2)  # [b, 12, 3]
        f_imu = self.conv(x).flatten(1)  # [b, 3C]
        f_hr = self.hr_net(hr.reshape(-1, HR_DIM))
        return self.head(torch.cat([f_imu, f_hr], dim=-1)).reshape(*lead, self.out_dim)

    def forward(self, obs: Mapping) -> torch.Tensor:
        """``{imu: [*B, 36], hr_features: [*B, 16]}`` -> ``[*B, out_dim]``."""
        return self._embed(obs)


class HealthStage1(nn.Module):
    """Appendix J.2 Stage 1 (Eq. A26): ``o_slot = CrossAttn(SelfAttn(IMU_t), MLP(HR_t))``.

    * IMU slots: the three sites ``[b, 3, 12]`` -> ``Linear(12, d)`` + a learned site embedding ``[3, d]``.
    * Self-attention over the 3 slots: one pre-norm transformer layer (``heads`` heads, FFN ``2d``, no dropout).
    * HR tokens: ``MLP(16 -> hidden -> hr_tokens * d)`` reshaped to ``[b, hr_tokens, d]`` (several tokens so that
      the cross-attention has something to choose from: with a single key the softmax would be constant).
    * Cross-attention: :class:`~freamer_rl.layers.encoders.CrossModalAttention` (Eq. A21-A22 with IMU in the
      vision role): ``S'_imu = S_imu + MHA(S_imu, S_hr, S_hr)`` (Eq. A26) and ``S'_hr = S_hr + MHA(S_hr, S_imu,
      S_imu)``.
    * Pooling (:class:`SlotPool`-style mean): ``e_imu = mean(S'_imu)``, ``e_hr = mean(S'_hr)``, each ``[*B, d]``.

    Shapes: ``forward(imu [*B, 36] (already symlog-ed), hr [*B, 16]) -> (e_imu [*B, d], e_hr [*B, d])``.
    """

    def __init__(self, dim: int = 64, heads: int = 4, hr_tokens: int = 4, hidden: int = 128) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim ({dim}) must be divisible by heads ({heads})")
        if hr_tokens < 1:
            raise ValueError(f"hr_tokens must be >= 1, got {hr_tokens}")
        self.dim, self.hr_tokens = dim, hr_tokens
        self.site_proj = nn.Linear(IMU_CHANNELS, dim)
        self.site_embed = nn.Parameter(torch.randn(IMU_SITES, dim) * 0.02)
        self.self_attn = nn.TransformerEncoderLayer(
            dim, heads, dim_feedforward=2 * dim, dropout=0.0, batch_first=True, norm_first=True
        )
        self.hr_mlp = mlp(HR_DIM, hidden, hr_tokens * dim, layers=1)
        self.cross = CrossModalAttention(dim, heads)
        self.norm_imu = nn.LayerNorm(dim)
        self.norm_hr = nn.LayerNorm(dim)

    def forward(self, imu: torch.Tensor, hr: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lead = imu.shape[:-1]
        slots = self.site_proj(imu.reshape(-1, IMU_SITES, IMU_CHANNELS)) + self.site_embed  # [b, 3, d]
        slots = self.self_attn(slots)  # SelfAttn(IMU_t)
        hr_tok = self.hr_mlp(hr.reshape(-1, HR_DIM)).reshape(-1, self.hr_tokens, self.dim)  # MLP(HR_t)
        slots, hr_tok = self.cross(slots, hr_tok)  # Eq. A26 (+ the reverse direction)
        e_imu = self.norm_imu(slots.mean(dim=-2)).reshape(*lead, self.dim)
        e_hr = self.norm_hr(hr_tok.mean(dim=-2)).reshape(*lead, self.dim)
        return e_imu, e_hr


class SlotCrossAttnHealthEncoder(_HealthEncoderMixin, nn.Module):
    """Table 15 "SlotAttn+CrossAttn": :class:`HealthStage1` only, then ``Linear([e_imu; e_hr]) -> [*B, out_dim]``.

    Args:
        out_dim: ``E``. dim: attention width ``d``. heads, hr_tokens, hidden: see :class:`HealthStage1`.
    """

    def __init__(self, out_dim: int = 128, dim: int = 64, heads: int = 4, hr_tokens: int = 4, hidden: int = 128,
                 *, imu_key: NestedKey = "imu", hr_key: NestedKey = "hr_features",
                 symlog_inputs: bool = True) -> None:  # fmt: skip
        super().__init__()
        self.out_dim = out_dim
        self.imu_key, self.hr_key, self.symlog_inputs = imu_key, hr_key, symlog_inputs
        self.stage1 = HealthStage1(dim, heads, hr_tokens, hidden)
        self.out = nn.Linear(2 * dim, out_dim)

    def _embed(self, obs: Mapping) -> torch.Tensor:
        e_imu, e_hr = self.stage1(*self._inputs(obs))
        return self.out(torch.cat([e_imu, e_hr], dim=-1))

    def forward(self, obs: Mapping) -> torch.Tensor:
        """``{imu: [*B, 36], hr_features: [*B, 16]}`` -> ``[*B, out_dim]``."""
        return self._embed(obs)


class FoundationHealthEncoder(_HealthEncoderMixin, TensorDictModuleBase):
    """The FreamerV1 foundation encoder of the health domain (Appendix J.2, Stages 1-4).

    Per step::

        e_imu, e_hr = Stage1(symlog(imu), hr)                      Eq. A26 (HealthStage1)        [*B, d] each
        ê_m = e_m + sigmoid(alpha_m) (Euler_N(v_m; e_m) - e_m)    Eq. 1-3, m in (imu, heart_rate) [*B, d] each
        fused, E_out = FNOFuser([ê_imu; ê_hr])                    Eq. A14-A15                    [*B, d], [*B, 2, d]
        o_embed, M_t = DNC(fused, M_{t-1})                        Appendix F.1                   [*B, E], [*B, N, W]

    Args:
        out_dim: ``E`` (DNC output size). dim: modality width ``d``. heads, hr_tokens, hidden: Stage 1.
        fm_hidden, fm_steps: velocity MLP width / Euler steps (Table A20: 128, 4).
        gate_init: ``{"imu": a, "heart_rate": b}`` initial gate logits (default -1 each: the noisy-sensor setting,
            ``sigmoid(-1) = 0.27``; Table A20's -3 is for a strong pre-trained encoder).
        fm_noise_std: ``sigma`` of the denoising CFM loss (Eq. A13, :meth:`FlowMatchingRefiner.cfm_loss`).
        fno_modes, fno_residual_scale: FNO Fourier modes (clipped to ``d // 2 + 1``) and residual scale (16, 0.1).
        memory_slots, memory_width: DNC ``N``, ``W`` (Table A20: 32, 64).
        imu_key, hr_key: observation keys. is_init_key: episode-start marker. memory_key: DNC state key
            (root = before the step, ``("next", key)`` = after). out_key: embedding key (the WorldModel reads it).

    TensorDict forward (what :meth:`WorldModel.embed` calls):
        * **sequence mode** -- when ``torchrl.modules.set_recurrent_mode(True)`` is active, or when no such context
          is active and ``memory_key`` is absent (the WorldModel.loss case): batch ``[*B, T]`` with time last;
          starting from ``memory_key[..., 0, :, :]`` if present, else zeros, the DNC loops over ``T`` and zeroes
          its memory wherever ``is_init[..., t]`` is True. Stages 1-3 and the DNC projections run on all steps at
          once. Writes ``out_key [*B, T, E]`` and ``("next", memory_key) [*B, T, N, W]``.
        * **step mode** -- ``set_recurrent_mode(False)``, or ``memory_key`` present without a context: every
          leading dim is batch; memory zeroed where ``is_init``, one step.
        ``is_init`` (``[*B, 1]`` or ``[*B]``) is required in sequence mode; in step mode it defaults to False.

    Tensor API: :meth:`encode_sequence` and :meth:`step` (online filtering). :meth:`aux_loss` returns the
    auxiliary terms of the last forward pass with gradients enabled: ``loss_fm`` (mean over the two modalities of
    the denoising CFM loss on the Stage-1 embeddings, Eq. A13; weight ``lambda_FM(WM) = 0.1``, Table A20) and
    ``loss_smooth`` (FNO smoothness Eq. A16 on ``E_out``, without ``lambda_s``).
    """

    def __init__(
        self,
        out_dim: int = 128,
        dim: int = 64,
        heads: int = 4,
        hr_tokens: int = 4,
        hidden: int = 128,
        *,
        fm_hidden: int = 128,
        fm_steps: int = 4,
        gate_init: Mapping[str, float] | None = None,
        fm_noise_std: float = 1.0,
        fno_modes: int = 16,
        fno_residual_scale: float = 0.1,
        memory_slots: int = 32,
        memory_width: int = 64,
        imu_key: NestedKey = "imu",
        hr_key: NestedKey = "hr_features",
        is_init_key: NestedKey = "is_init",
        memory_key: NestedKey = ("dnc", "memory"),
        out_key: NestedKey = "obs_embed",
        symlog_inputs: bool = True,
    ) -> None:
        super().__init__()
        gates = {"imu": -1.0, "heart_rate": -1.0}
        for k, v in (gate_init or {}).items():
            if k not in MODALITIES:
                raise ValueError(f"gate_init: unknown modality {k!r} (known: {', '.join(MODALITIES)})")
            gates[k] = float(v)
        self.out_dim, self.dim = out_dim, dim
        self.imu_key, self.hr_key, self.symlog_inputs = unravel_key(imu_key), unravel_key(hr_key), symlog_inputs
        self.is_init_key = unravel_key(is_init_key)
        self.memory_key = unravel_key(memory_key)
        self.out_key = unravel_key(out_key)
        mk = self.memory_key if isinstance(self.memory_key, tuple) else (self.memory_key,)
        self.next_memory_key = ("next", *mk)
        self.in_keys = [self.imu_key, self.hr_key, self.is_init_key, self.memory_key]
        self.out_keys = [self.out_key, self.next_memory_key]
        self.fm_noise_std = fm_noise_std
        self.stage1 = HealthStage1(dim, heads, hr_tokens, hidden)
        self.refiners = nn.ModuleDict(
            {m: FlowMatchingRefiner(dim, fm_hidden, fm_steps, gate_init=gates[m]) for m in MODALITIES}
        )
        self.fuser = FNOFuser(len(MODALITIES), dim, modes=min(fno_modes, dim // 2 + 1),
                              residual_scale=fno_residual_scale)  # fmt: skip
        self.dnc = DNCMemory(dim, memory_slots, memory_width, output_dim=out_dim)
        self._cache: dict[str, torch.Tensor] | None = None

    # -- stages 1-3 (stateless, any batch shape) -----------------------------------------------------------------
    def features(self, obs: Mapping) -> dict[str, torch.Tensor]:
        """Stages 1-3 on ``obs {imu: [*B, 36], hr_features: [*B, 16]}``.

        Returns ``("embed", m)``-style entries: ``embed_imu``/``embed_heart_rate`` ``[*B, d]`` (Stage 1),
        ``refined_imu``/``refined_heart_rate`` ``[*B, d]`` (Stage 2), ``fused_modalities [*B, 2, d]`` and
        ``fused [*B, d]`` (Stage 3).
        """
        e_imu, e_hr = self.stage1(*self._inputs(obs))
        r_imu = self.refiners["imu"](e_imu)
        r_hr = self.refiners["heart_rate"](e_hr)
        fused, e_out = self.fuser(torch.stack([r_imu, r_hr], dim=-2))
        out = {
            "embed_imu": e_imu, "embed_heart_rate": e_hr, "refined_imu": r_imu, "refined_heart_rate": r_hr,
            "fused_modalities": e_out, "fused": fused,
        }  # fmt: skip
        if torch.is_grad_enabled():
            self._cache = {"imu": e_imu, "heart_rate": e_hr, "fused_modalities": e_out}
        return out

    @property
    def gates(self) -> dict[str, float]:
        """Current FM gates ``sigmoid(alpha_m)`` per modality (Eq. 3)."""
        return {m: float(r.gate.detach()) for m, r in self.refiners.items()}

    # -- DNC (Stage 4) ---------------------------------------------------------------------------------------------
    def state_shapes(self) -> dict[str, tuple[int, ...]]:
        return {"memory": self.dnc.memory_shape}

    def step(
        self, obs: Mapping, state: Mapping[str, torch.Tensor] | None = None, is_first: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One online step. ``obs {key: [*B, d]}``, ``state {"memory": [*B, N, W]}`` (zeros when omitted),
        ``is_first`` bool ``[*B]`` (memory zeroed there) -> ``(embed [*B, E], {"memory": [*B, N, W]})``."""
        x = self.features(obs)["fused"]
        lead = x.shape[:-1]
        memory = None if state is None else state.get("memory")
        if memory is None:
            memory = self.dnc.initial_memory(tuple(lead), dtype=x.dtype, device=x.device)
        if is_first is not None:
            first = is_first.reshape(lead).bool()
            memory = torch.where(first[..., None, None], torch.zeros_like(memory), memory)
        out, memory = self.dnc.step(x, memory)
        return out, {"memory": memory}

    def encode_sequence(
        self, obs: Mapping, is_init: torch.Tensor, memory: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Sequence mode on tensors: ``obs {key: [*B, T, d]}``, ``is_init`` bool ``[*B, T]`` (or ``[*B, T, 1]``),
        ``memory [*B, N, W]`` before step 0 (zeros when omitted) -> ``(embed [*B, T, E], memories [*B, T, N, W])``
        where ``memories[..., t]`` is the memory after step ``t``."""
        x = self.features(obs)["fused"]  # [*B, T, d]
        if x.ndim < 2:
            raise ValueError(f"encode_sequence: expected observations [*B, T, d], got fused shape {tuple(x.shape)}")
        lead, T = x.shape[:-2], x.shape[-2]
        if is_init.shape == (*x.shape[:-1], 1):
            is_init = is_init.squeeze(-1)
        if is_init.shape != x.shape[:-1]:
            raise ValueError(f"is_init: expected shape {tuple(x.shape[:-1])} (or with a trailing 1), got "
                             f"{tuple(is_init.shape)}")  # fmt: skip
        m = memory if memory is not None else self.dnc.initial_memory(tuple(lead), dtype=x.dtype, device=x.device)
        if tuple(m.shape) != (*lead, *self.dnc.memory_shape):
            raise ValueError(f"memory: expected shape {(*lead, *self.dnc.memory_shape)}, got {tuple(m.shape)}")
        controls = self.dnc.interface_vectors(x)  # memory-independent projections, all steps at once
        first = is_init.bool()
        reads, mems = [], []
        for t in range(T):
            m = torch.where(first[..., t, None, None], torch.zeros_like(m), m)
            r, m = self.dnc.memory_step({k: v[..., t, :] if v.ndim == x.ndim else v[..., t]
                                         for k, v in controls.items()}, m)  # fmt: skip
            reads.append(r)
            mems.append(m)
        out = self.dnc.output(x, torch.stack(reads, dim=-2))
        return out, torch.stack(mems, dim=-3)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        from torchrl.modules import recurrent_mode

        keys = tensordict.keys(include_nested=True)
        rm = recurrent_mode()
        sequence = bool(rm) if rm is not None else self.memory_key not in keys
        is_init = tensordict.get(self.is_init_key, None)
        obs = {self.imu_key: tensordict.get(self.imu_key), self.hr_key: tensordict.get(self.hr_key)}
        if sequence:
            if is_init is None:
                raise KeyError(
                    f"FoundationHealthEncoder (sequence mode: no {self.memory_key!r} in the tensordict) needs "
                    f"{self.is_init_key!r} [*B, T, 1] marking sequence starts; for online use call .step() or "
                    f"provide {self.memory_key!r} (step mode)"
                )
            if tensordict.batch_dims < 1:
                raise ValueError("FoundationHealthEncoder sequence mode needs a [*B, T] tensordict (time last)")
            memory = tensordict.get(self.memory_key, None)
            if memory is not None:
                memory = memory[..., 0, :, :]
            out, mems = self.encode_sequence(obs, is_init, memory)
        else:
            state = {"memory": tensordict.get(self.memory_key)} if self.memory_key in keys else None
            first = None if is_init is None else is_init.reshape(tensordict.batch_size)
            out, new_state = self.step(obs, state, first)
            mems = new_state["memory"]
        tensordict.set(self.out_key, out)
        tensordict.set(self.next_memory_key, mems)
        return tensordict

    def make_tensordict_primer(self):
        """A ``TensorDictPrimer`` declaring ``memory_key`` ``[N, W]`` (zeros at reset) for TorchRL envs."""
        from torchrl.data import Unbounded
        from torchrl.envs.transforms import TensorDictPrimer

        return TensorDictPrimer({self.memory_key: Unbounded(shape=self.dnc.memory_shape, dtype=torch.float32)},
                                expand_specs=True)  # fmt: skip

    # -- auxiliary losses ------------------------------------------------------------------------------------------
    def aux_loss(self) -> dict[str, torch.Tensor]:
        """Auxiliary terms of the last forward pass run with gradients enabled.

        * ``loss_fm``: mean over ``imu`` and ``heart_rate`` of ``FlowMatchingRefiner.cfm_loss(e_m, fm_noise_std)``
          on the Stage-1 embeddings (Eq. A13; the embeddings are detached inside: only the velocity fields learn).
        * ``loss_smooth``: :func:`~freamer_rl.layers.fno.smoothness_loss` of the FNO output ``E_out`` (Eq. A16
          without ``lambda_s``).
        Raises ``RuntimeError`` when no forward pass with gradients has run yet.
        """
        if self._cache is None:
            raise RuntimeError("FoundationHealthEncoder.aux_loss: run a forward pass with gradients enabled first")
        c = self._cache
        fm = sum(self.refiners[m].cfm_loss(c[m], self.fm_noise_std) for m in MODALITIES) / len(MODALITIES)
        return {"loss_fm": fm, "loss_smooth": smoothness_loss(c["fused_modalities"])}

    def clear_cache(self) -> None:
        """Drop the tensors kept for :meth:`aux_loss`."""
        self._cache = None


def make_health_encoder(kind: str, out_dim: int = 128, **kwargs) -> nn.Module:
    """Build one of :data:`ENCODER_KINDS` (``mlp``, ``cnn``, ``slotattn``, ``foundation``); ``kwargs`` go to the
    class (unknown ones raise ``TypeError`` naming them)."""
    classes = {
        "mlp": MLPHealthEncoder,
        "cnn": CNNHealthEncoder,
        "slotattn": SlotCrossAttnHealthEncoder,
        "foundation": FoundationHealthEncoder,
    }
    if kind not in classes:
        raise ValueError(f"encoder kind: expected one of {', '.join(ENCODER_KINDS)}, got {kind!r}")
    return classes[kind](out_dim, **kwargs)
