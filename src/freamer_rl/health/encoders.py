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
xyz, mag xyz`` (:data:`freamer_rl.data.IMU_FEATURE_NAMES`), viewed here as ``[*B, 3 sites, 12 channels]``;
``hr_features`` are the 16 heart-rate features (already scaled to O(1) by the loader). The IMU goes through
:func:`~freamer_rl.world_model.rssm.symlog` (``symlog_inputs``, default True) like the world model's default
encoder; the HR features are used as they are.

Common interface (all four): ``out_dim`` (= ``E``), ``obs_keys``, ``forward``, and the online *step* API used when
filtering a real env step by step: ``state_shapes()`` (``{name: per-element shape}``, empty for the stateless ones),
``initial_state(batch_shape)`` and ``step(obs, state, is_first) -> (embed [*B, E], new_state)``; plus
``make_aux_loss(lambda_fm=, lambda_smooth=)`` (``None`` except for the foundation encoder) and ``gates`` (``{}``
except for the foundation encoder). :class:`HealthEncoder` is that interface as a typed ``Protocol``: the pipeline
calls it without probing what an encoder can do.

The foundation encoder is the MiniGrid trunk's Layers 2-4 (:func:`freamer_rl.model.factory.build_filter_mix_memory`)
behind a health Stage 1, as one ``TensorDictSequential`` (:attr:`FoundationHealthEncoder.trunk`); its auxiliary
losses are :class:`~freamer_rl.model.losses.FreamerAuxLoss` read from the tensordict the trunk wrote. It is recurrent (the
DNC memory) and follows TorchRL's stateful pattern: inside :meth:`WorldModel.loss` it runs under
``set_recurrent_mode(True)`` on a TensorDict of batch ``[*B, T+1]`` holding the observations and ``"is_init"``
(``[*B, T+1, 1]``, True where a sequence starts), looping the DNC over time and zeroing the memory wherever
``is_init`` is True; online it is driven with :meth:`FoundationHealthEncoder.step` (step mode). Looping over a
sequence equals stepping through it (tested).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import set_recurrent_mode

from freamer_rl.layers.dnc import DNCModule
from freamer_rl.layers.encoders import CrossModalAttention
from freamer_rl.layers.fno import FNOFuser
from freamer_rl.layers.tdmodule import KeyedModule
from freamer_rl.model.factory import build_filter_mix_memory
from freamer_rl.model.losses import FreamerAuxLoss
from freamer_rl.world_model.encoder import StatelessStepMixin, StepEncoder
from freamer_rl.world_model.functional import mlp, symlog

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
    "FoundationStage1",
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


def _check_pair(owner: str, imu_name: str, imu: torch.Tensor, hr_name: str, hr: torch.Tensor) -> None:
    """``imu [*B, 36]`` and ``hr [*B, 16]`` with the same batch dims, else ``ValueError`` naming the keys."""
    _check(imu_name, imu, IMU_DIM)
    _check(hr_name, hr, HR_DIM)
    if imu.shape[:-1] != hr.shape[:-1]:
        raise ValueError(
            f"{owner}: batch dims differ: {imu_name!r} {tuple(imu.shape)} vs {hr_name!r} {tuple(hr.shape)}"
        )


class _HealthEncoderMixin(StatelessStepMixin):
    """Input handling and the stateless step API shared by the four encoders."""

    imu_key: NestedKey
    hr_key: NestedKey
    symlog_inputs: bool

    @property
    def obs_keys(self) -> tuple[NestedKey, NestedKey]:
        return (self.imu_key, self.hr_key)

    def _raw_inputs(self, obs: Mapping | TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``obs`` mapping -> ``(imu [*B, 36], hr [*B, 16])`` as given; checks keys, sizes and batch dims."""
        try:
            imu, hr = obs[self.imu_key], obs[self.hr_key]
        except KeyError as err:
            raise KeyError(
                f"{type(self).__name__}: observation key {err.args[0]!r} missing (needs {self.imu_key!r} [*B, "
                f"{IMU_DIM}] and {self.hr_key!r} [*B, {HR_DIM}])"
            ) from None
        _check_pair(type(self).__name__, str(self.imu_key), imu, str(self.hr_key), hr)
        return imu, hr

    def _inputs(self, obs: Mapping | TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``obs`` mapping -> ``(imu [*B, 36], hr [*B, 16])`` float, IMU symlog-squashed; batch dims must agree."""
        imu, hr = self._raw_inputs(obs)
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

    def __init__(
        self,
        out_dim: int = 128,
        hidden: int = 256,
        layers: int = 2,
        *,
        imu_key: NestedKey = "imu",
        hr_key: NestedKey = "hr_features",
        symlog_inputs: bool = True,
    ) -> None:
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

    def __init__(
        self,
        out_dim: int = 128,
        channels: int = 32,
        hidden: int = 128,
        *,
        imu_key: NestedKey = "imu",
        hr_key: NestedKey = "hr_features",
        symlog_inputs: bool = True,
    ) -> None:
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

    def __init__(
        self,
        out_dim: int = 128,
        dim: int = 64,
        heads: int = 4,
        hr_tokens: int = 4,
        hidden: int = 128,
        *,
        imu_key: NestedKey = "imu",
        hr_key: NestedKey = "hr_features",
        symlog_inputs: bool = True,
    ) -> None:
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


class FoundationStage1(nn.Module):
    """Stage 1 of the foundation encoder on raw observations, for its ``TensorDictModule``.

    ``forward(imu [*B, 36], hr [*B, 16]) -> (e_imu [*B, d], e_hr [*B, d])``: checks the shapes, squashes the IMU with
    symlog (``symlog_inputs``) and runs :class:`HealthStage1` (Eq. A26). The outputs are the Layer-1 embeddings
    ``("embed", "imu")`` and ``("embed", "heart_rate")`` of the trunk.
    """

    def __init__(self, stage1: HealthStage1, symlog_inputs: bool = True) -> None:
        super().__init__()
        self.stage1 = stage1
        self.symlog_inputs = symlog_inputs

    def forward(self, imu: torch.Tensor, hr: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _check_pair(type(self).__name__, "imu", imu, "hr_features", hr)
        imu = imu.float()
        return self.stage1(symlog(imu) if self.symlog_inputs else imu, hr.float())


class FoundationHealthEncoder(_HealthEncoderMixin, TensorDictModuleBase):
    """The FreamerV1 foundation encoder of the health domain (Appendix J.2, Stages 1-4).

    Per step::

        e_imu, e_hr = Stage1(symlog(imu), hr)                      Eq. A26 (HealthStage1)        [*B, d] each
        ê_m = e_m + sigmoid(alpha_m) (Euler_N(v_m; e_m) - e_m)    Eq. 1-3, m in (imu, heart_rate) [*B, d] each
        fused, E_out = FNOFuser([ê_imu; ê_hr])                    Eq. A14-A15                    [*B, d], [*B, 2, d]
        o_embed, M_t = DNC(fused, M_{t-1})                        Appendix F.1                   [*B, E], [*B, N, W]

    Stages 2-4 are the MiniGrid trunk's own layers, built by :func:`freamer_rl.model.factory.build_filter_mix_memory`;
    :attr:`trunk` is ``TensorDictSequential(Stage 1, refiners, StackModalities, FNOFuser, DNCModule)`` writing
    ``("embed", m)``, ``("refined", m)`` ``[*B, d]``, ``"modal_stack"`` / ``"fused_modalities"`` ``[*B, 2, d]``,
    ``"fused"`` ``[*B, d]``, ``out_key`` ``[*B, E]`` and ``("next", *memory_key)`` ``[*B, N, W]``. The auxiliary
    losses are :class:`~freamer_rl.model.losses.FreamerAuxLoss` (:meth:`make_aux_loss`) on the tensordict the trunk wrote.

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

    TensorDict forward -- the mode is chosen only by ``torchrl.modules.set_recurrent_mode`` (TorchRL's pattern):
        * step mode (default): every leading dim is batch, ``is_init [*B, 1]`` zeroes the memory, one DNC step.
        * recurrent mode (``set_recurrent_mode(True)``; :meth:`WorldModel.loss` sets it): batch ``[B, T]`` (at least
          two batch dims, time last); the DNC loops over ``T`` from ``memory_key[..., 0, :, :]`` and zeroes its
          memory wherever ``is_init[..., t]`` is True.
        ``is_init`` is required; a missing ``memory_key`` is written as zeros first (what the primer gives at reset).

    Tensor API: :meth:`step` (online filtering, step mode) and :meth:`encode_sequence` (recurrent mode).
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
        stage1 = KeyedModule(
            FoundationStage1(HealthStage1(dim, heads, hr_tokens, hidden), symlog_inputs),
            in_keys=[self.imu_key, self.hr_key],
            out_keys=[("embed", "imu"), ("embed", "heart_rate")],
        )
        layers, refiners, fuser, dnc = build_filter_mix_memory(
            MODALITIES,
            dim,
            flow_hidden=fm_hidden,
            flow_steps=fm_steps,
            gate_init=gates,
            fno_modes=min(fno_modes, dim // 2 + 1),
            fno_residual_scale=fno_residual_scale,
            memory_slots=memory_slots,
            memory_width=memory_width,
            output_dim=out_dim,
            out_key=self.out_key,
            memory_key=self.memory_key,
            is_init_key=self.is_init_key,
        )
        self.trunk = TensorDictSequential(stage1, *layers)
        # references into the trunk (a tuple is not registered: the parameters live once, under ``trunk``)
        self._parts = (stage1.module.stage1, refiners, fuser, dnc)
        self._register_load_state_dict_pre_hook(self._rename_legacy_keys)

    def _rename_legacy_keys(self, state_dict: dict, prefix: str, *args) -> None:
        """Load hook: map the names of the former hand-wired encoder (``stage1.*``, ``refiners.<m>.*``, ``fuser.*``,
        ``dnc.*``) onto the trunk's, so checkpoints written before the shared trunk still load."""
        step = {id(getattr(m, "module", m)): i for i, m in enumerate(self.trunk.module)}
        old = {
            "stage1.": f"trunk.module.{step[id(self.trunk.module[0].module)]}.module.stage1.",
            "fuser.": f"trunk.module.{step[id(self.fuser)]}.module.",
            "dnc.": f"trunk.module.{step[id(self.dnc)]}.dnc.",
        }
        old.update({f"refiners.{m}.": f"trunk.module.{step[id(r)]}.module." for m, r in self.refiners.items()})
        for key in [k for k in state_dict if k.startswith(prefix)]:
            for before, after in old.items():
                if key.startswith(prefix + before):
                    state_dict[prefix + after + key[len(prefix + before) :]] = state_dict.pop(key)
                    break

    @property
    def stage1(self) -> HealthStage1:
        """Stage 1 (Eq. A26)."""
        return self._parts[0]

    @property
    def refiners(self) -> nn.ModuleDict:
        """``{m: FlowMatchingRefiner}`` for ``m`` in ``("imu", "heart_rate")`` (Stage 2, Eq. 1-3)."""
        return self._parts[1]

    @property
    def fuser(self) -> FNOFuser:
        """The FNO fuser (Stage 3, Eq. A14-A15)."""
        return self._parts[2]

    @property
    def dnc(self) -> DNCModule:
        """The DNC memory module (Stage 4, Appendix F.1)."""
        return self._parts[3]

    @property
    def gates(self) -> dict[str, float]:
        """Current FM gates ``sigmoid(alpha_m)`` per modality (Eq. 3)."""
        return {m: float(r.gate.detach()) for m, r in self.refiners.items()}

    def state_shapes(self) -> dict[str, tuple[int, ...]]:
        return {"memory": self.dnc.dnc.memory_shape}

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Run the trunk (step or recurrent mode, see the class docstring); writes ``out_key`` ``[*B, E]`` and
        ``("next", *memory_key)`` ``[*B, N, W]`` (plus the intermediate keys) into ``tensordict`` and returns it."""
        if self.memory_key not in tensordict.keys(include_nested=True):
            ref = tensordict.get(self.imu_key)
            zeros = torch.zeros(*tensordict.batch_size, *self.dnc.dnc.memory_shape, device=ref.device)
            tensordict.set(self.memory_key, zeros)
        return self.trunk(tensordict)

    def _tensordict(self, obs: Mapping, is_init: torch.Tensor, memory: torch.Tensor | None) -> TensorDictBase:
        """``obs {key: [*L, d]}``, ``is_init`` bool ``[*L]`` (or ``[*L, 1]``), ``memory [*L, N, W]`` or None -> the
        trunk's input tensordict of batch ``[*L]``."""
        imu, hr = self._raw_inputs(obs)
        lead = imu.shape[:-1]
        if is_init.shape == (*lead, 1):
            is_init = is_init.squeeze(-1)
        if is_init.shape != lead:
            raise ValueError(
                f"is_init: expected shape {tuple(lead)} (or with a trailing 1), got {tuple(is_init.shape)}"
            )
        td = TensorDict(
            {self.imu_key: imu, self.hr_key: hr, self.is_init_key: is_init.bool().unsqueeze(-1)},
            batch_size=lead,
            device=imu.device,
        )
        if memory is not None:
            if tuple(memory.shape) != (*lead, *self.dnc.dnc.memory_shape):
                raise ValueError(
                    f"memory: expected shape {(*lead, *self.dnc.dnc.memory_shape)}, got {tuple(memory.shape)}"
                )
            td.set(self.memory_key, memory)
        return td

    def step(
        self, obs: Mapping, state: Mapping[str, torch.Tensor] | None = None, is_first: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One online step (step mode). ``obs {key: [*B, d]}``, ``state {"memory": [*B, N, W]}`` (zeros when
        omitted), ``is_first`` bool ``[*B]`` (memory zeroed there; False when omitted) ->
        ``(embed [*B, E], {"memory": [*B, N, W]})``."""
        imu = self._raw_inputs(obs)[0]
        lead = imu.shape[:-1]
        if is_first is None:
            is_first = torch.zeros(lead, dtype=torch.bool, device=imu.device)
        memory = None if state is None else state.get("memory")
        td = self._tensordict(obs, is_first.reshape(lead), memory)
        with set_recurrent_mode(False):
            td = self(td)
        return td.get(self.out_key), {"memory": td.get(self.next_memory_key)}

    def encode_sequence(
        self, obs: Mapping, is_init: torch.Tensor, memory: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Recurrent mode on tensors: ``obs {key: [*B, T, d]}``, ``is_init`` bool ``[*B, T]`` (or ``[*B, T, 1]``),
        ``memory [*B, N, W]`` before step 0 (zeros when omitted) -> ``(embed [*B, T, E], memories [*B, T, N, W])``
        where ``memories[..., t]`` is the memory after step ``t``. A single sequence ``[T]`` is run as ``[1, T]``."""
        lead = self._raw_inputs(obs)[0].shape[:-1]
        if len(lead) < 1:
            raise ValueError(f"encode_sequence: expected observations [*B, T, d], got batch dims {tuple(lead)}")
        if memory is not None:
            if tuple(memory.shape) != (*lead[:-1], *self.dnc.dnc.memory_shape):
                raise ValueError(
                    f"memory: expected shape {(*lead[:-1], *self.dnc.dnc.memory_shape)}, got {tuple(memory.shape)}"
                )
            memory = memory.unsqueeze(-3).expand(*lead, *self.dnc.dnc.memory_shape)  # only t = 0 is read
        td = self._tensordict(obs, is_init, memory)
        single = td.batch_dims == 1
        with set_recurrent_mode(True):
            td = self(td.unsqueeze(0) if single else td)
        out, mems = td.get(self.out_key), td.get(self.next_memory_key)
        return (out[0], mems[0]) if single else (out, mems)

    def make_tensordict_primer(self):
        """A ``TensorDictPrimer`` declaring ``memory_key`` ``[N, W]`` (zeros at reset) for TorchRL envs."""
        return self.dnc.make_tensordict_primer()

    def make_aux_loss(self, *, lambda_fm: float = 0.1, lambda_smooth: float = 1e-3) -> FreamerAuxLoss:
        """The auxiliary losses (the MiniGrid trunk's :class:`~freamer_rl.model.losses.FreamerAuxLoss`) on a tensordict
        this encoder wrote: ``loss_fm = lambda_fm * mean_m CFM_m(("embed", m))`` (Eq. A13, noise ``fm_noise_std``;
        the embeddings are detached inside, only the velocity fields learn) and ``loss_smooth = lambda_smooth *
        L_smooth("fused_modalities")`` (Eq. A16 on ``E_out [*B, 2, d]``, gradient into every stage: the literal
        Eq. 6), plus detached ``fm_imu``, ``fm_heart_rate``."""
        return FreamerAuxLoss(
            self.refiners,
            lambda_fm=lambda_fm,
            lambda_cl=0.0,
            lambda_smooth=lambda_smooth,
            noise_std=self.fm_noise_std,
            smooth_fuser=None,
        )


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
