"""Layer 1 modality encoders other than the state encoder (Section 3.2, Appendix E).

Every module works on plain tensors with arbitrary leading batch dims ``[*B, ...]`` and takes its inputs in a fixed
positional order, so the factory can wrap it in ``TensorDictModule(module, in_keys=..., out_keys=...)``.

========================  =========================================  ===========================
module                    inputs                                     output
========================  =========================================  ===========================
RewardEncoder             reward history ``[*B, H]``                 ``[*B, d]``
LanguageEncoder           token ids ``[*B, L]`` (0 = padding)        slots ``[*B, K_lang, d]``
CNNBackbone               pixels ``[*B, H, W, C]`` (uint8/float)     tokens ``[*B, N_tok, C_out]``
VisionEncoder             pixels ``[*B, H, W, C]``                   slots ``[*B, K, d]``
CrossModalAttention       vision ``[*B, K, d]``, language slots      (vision', language')
SlotPool                  slots ``[*B, K, d]``                       ``[*B, d]``
========================  =========================================  ===========================

Every forward is free of host syncs under ``torch.vmap``/``torch.func``/``torch.compile`` (TorchRL's ``GAE`` vmaps
the value network): value checks (id ranges, NaN/Inf inputs) and data-dependent shortcuts (deduplication, caches) run
in eager mode only, and the maths is the same either way (see :mod:`freamer_rl.layers.checks`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn
from torchrl.modules.functional import symlog

from freamer_rl.layers.checks import check_finite, value_checks_active
from freamer_rl.layers.dedup import dedup_rows, distinct_rows
from freamer_rl.layers.slot_attention import SlotAttention

__all__ = [
    "CNNBackbone",
    "CrossModalAttention",
    "LanguageEncoder",
    "RewardEncoder",
    "SlotPool",
    "VisionEncoder",
    "pixels_to_unit",
    "sinusoidal_positions",
]


def pixels_to_unit(pixels: torch.Tensor, in_channels: int = 3, name: str = "pixels") -> torch.Tensor:
    """Channels-last pixels ``[b, H, W, C]`` on the 0-255 scale -> float ``[b, C, H, W]`` in ``[0, 1]``.

    uint8 and floating inputs are both divided by 255 (environments give uint8; a float copy of the same frames keeps
    the 0-255 scale). Raises ``ValueError`` when the channel axis is not last, and (eager mode only) when float
    pixels hold NaN/Inf.
    """
    if pixels.dim() != 4 or pixels.shape[-1] != in_channels:
        raise ValueError(
            f"{name}: expected channels-last [*B, H, W, {in_channels}] (flattened to 4-D), got {tuple(pixels.shape)}"
        )
    if not (pixels.dtype == torch.uint8 or pixels.is_floating_point()):
        raise TypeError(f"{name}: expected uint8 or floating pixels, got dtype {pixels.dtype}")
    check_finite(pixels, name)
    x = pixels.permute(0, 3, 1, 2)  # a view with channels_last strides, the layout the CPU convolutions prefer
    if pixels.dtype == torch.uint8:
        # the float copy is ours: one pass to convert and one in-place divide, no second full-size tensor
        return x.to(torch.float32).div_(255.0)
    return x / 255.0


def sinusoidal_positions(length: int, dim: int) -> torch.Tensor:
    """Fixed sinusoidal positional encoding ``[length, dim]`` (Vaswani et al. 2017), used as PE in Appendix E.2."""
    pos = torch.arange(length, dtype=torch.float32).unsqueeze(1)
    div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    pe = torch.zeros(length, dim)
    pe[:, 0::2] = torch.sin(pos * div)
    pe[:, 1::2] = torch.cos(pos * div[: dim // 2])
    return pe


class RewardEncoder(nn.Module):
    """Temporal Conv1D reward encoder (Appendix E.2: ``e_reward = ReLU(Conv1D(r_{t-H:t}))``, then a linear map to d).

    ``[*B, H]`` reward history (most recent last) -> Conv1d(1 -> channels, kernel, 'same' padding) -> ReLU ->
    flatten ``[*B, channels * H]`` -> Linear -> ``[*B, out_dim]``. With ``symlog``, the rewards first pass through
    ``sign(r) log(1 + |r|)`` (DreamerV3's squashing; not in the paper): an env's raw reward scale (Pendulum's -16..0)
    otherwise sets the size of this embedding against the other modalities' normalised ones.

    A NaN/Inf reward raises ``ValueError`` in eager mode (skipped, same maths, under vmap/compile).
    """

    def __init__(self, history: int, out_dim: int, channels: int = 16, kernel: int = 3, symlog: bool = False) -> None:
        super().__init__()
        if history < 1:
            raise ValueError(f"history must be >= 1, got {history}")
        if kernel < 1:
            raise ValueError(f"kernel must be >= 1, got {kernel}")
        self.history = history
        self.out_dim = out_dim
        self.symlog = bool(symlog)
        self.conv = nn.Conv1d(1, channels, kernel_size=kernel, padding="same")
        self.proj = nn.Linear(channels * history, out_dim)

    def forward(self, rewards: torch.Tensor) -> torch.Tensor:
        """``rewards [*B, H]`` -> ``[*B, out_dim]``."""
        if rewards.dim() < 1 or rewards.shape[-1] != self.history:
            raise ValueError(f"RewardEncoder reward_history: expected [*B, {self.history}], got {tuple(rewards.shape)}")
        check_finite(rewards, "RewardEncoder reward_history")
        batch_shape = rewards.shape[:-1]
        x = rewards.reshape(-1, self.history).to(self.proj.weight.dtype)
        # sparse rewards repeat the same (mostly all-zero) history: encode each distinct row once (eager only)
        return dedup_rows(self._encode, x).reshape(*batch_shape, self.out_dim)

    def _encode(self, x: torch.Tensor) -> torch.Tensor:
        """``x [b, H]`` -> ``[b, out_dim]``."""
        if self.symlog:
            x = symlog(x)
        h = F.relu(self.conv(x.unsqueeze(1))).flatten(1)
        return self.proj(h)


class LanguageEncoder(nn.Module):
    """Mission-text encoder (Appendix E.2): ``H = TransformerEnc(Embed(T) + PE)`` then Slot Attention over H.

    Token ids ``[*B, L]`` (int, 0 = padding, ``L <= max_len``) -> slots ``[*B, num_slots, out_dim]``.
    The transformer uses a key-padding mask and the Slot Attention ignores padded positions, so trailing padding does
    not change the output. A row that is all padding yields finite slots (they depend only on the slot
    initialisation); dropout is 0 so the encoder is deterministic in eval mode.
    With ``deduplicate`` (default) identical token rows in a batch are encoded once: missions are constant within
    an episode, so a PPO minibatch holds only a few distinct rows. The slot initialisation must then be
    deterministic for identical rows to get identical slots (true in eval mode, which training uses).

    Eager mode only: ids outside ``[0, vocab_size)`` raise ``ValueError``, and the deduplication and the inference
    cache are used. Under ``torch.vmap``/``torch.func``/``torch.compile`` (data-dependent shapes and host syncs are
    impossible there) every row is encoded directly and ids are not range-checked; the slots are the same.
    """

    def __init__(
        self,
        vocab_size: int,
        out_dim: int = 128,
        num_slots: int = 4,
        layers: int = 1,
        heads: int = 4,
        max_len: int = 32,
        slot_iters: int = 3,
        ff_mult: int = 2,
        deduplicate: bool = True,
        cache_inference: bool = True,
    ) -> None:
        super().__init__()
        self.deduplicate = deduplicate
        self.cache_inference = cache_inference
        self._cache: dict = {}
        self._cache_version: tuple | None = None
        if vocab_size < 2:
            raise ValueError(f"vocab_size must be >= 2 (0 is padding), got {vocab_size}")
        if out_dim % heads:
            raise ValueError(f"out_dim ({out_dim}) must be divisible by heads ({heads})")
        self.vocab_size = vocab_size
        self.out_dim = out_dim
        self.slot_dim = out_dim
        self.num_slots = num_slots
        self.max_len = max_len
        self.embed = nn.Embedding(vocab_size, out_dim, padding_idx=0)
        self.register_buffer("pos", sinusoidal_positions(max_len, out_dim), persistent=False)
        layer = nn.TransformerEncoderLayer(
            out_dim, heads, dim_feedforward=ff_mult * out_dim, dropout=0.0, batch_first=True, norm_first=True
        )
        self.transformer = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(out_dim)
        self.slot_attention = SlotAttention(num_slots, out_dim, input_dim=out_dim, iters=slot_iters)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """``tokens [*B, L]`` -> slots ``[*B, num_slots, out_dim]``."""
        if tokens.dim() < 1 or tokens.shape[-1] > self.max_len:
            raise ValueError(
                f"LanguageEncoder mission_tokens: expected [*B, L] with L <= max_len={self.max_len}, "
                f"got {tuple(tokens.shape)}"
            )
        if tokens.is_floating_point() or tokens.is_complex() or tokens.dtype == torch.bool:
            raise TypeError(f"LanguageEncoder mission_tokens: expected an integer dtype, got {tokens.dtype}")
        batch_shape = tokens.shape[:-1]
        length = tokens.shape[-1]
        ids = tokens.reshape(-1, length).long()
        # Parameters count too: vmapping over stacked parameters alone must not fill the cache with batched rows.
        if not value_checks_active(ids, *self.parameters()):
            return self._encode(ids).reshape(*batch_shape, self.num_slots, self.out_dim)
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= self.vocab_size):
            raise ValueError(
                f"LanguageEncoder mission_tokens: ids must lie in [0, {self.vocab_size}), "
                f"got min {int(ids.min())} max {int(ids.max())}"
            )
        if self.deduplicate and ids.shape[0] > 1:
            # Missions repeat across envs and steps (constant within an episode): encode each distinct row once
            # and gather. Gradients flow through the gather, so training is unchanged. (Hashed rows, verified
            # exactly: torch.unique(dim=0) compares rows one select at a time on the CPU, ~0.5 ms per 512 rows.)
            found = distinct_rows(ids, max_fraction=1.0)
            if found is not None and found[0].shape[0] < ids.shape[0]:
                first, inverse = found
                slots = self._encode_cached(ids[first])[inverse]
                return slots.reshape(*batch_shape, self.num_slots, self.out_dim)
        return self._encode_cached(ids).reshape(*batch_shape, self.num_slots, self.out_dim)

    def _encode_cached(self, ids: torch.Tensor) -> torch.Tensor:
        """Inference-time memo of encoded rows (collection calls this every env step with the same missions).

        Used only when gradients are off and the slot initialisation is deterministic (eval mode). The cache is
        keyed by the parameters' in-place version counters, so any optimiser step or ``load_state_dict`` clears it.
        """
        if torch.is_grad_enabled() or self.training or not self.cache_inference:
            return self._encode(ids)
        version = (ids.device, ids.dtype, ids.shape[-1], *(p._version for p in self.parameters()))
        if version != self._cache_version or len(self._cache) > 4096:
            self._cache = {}
            self._cache_version = version
        keys = [row.numpy().tobytes() if ids.device.type == "cpu" else tuple(row.tolist()) for row in ids]
        missing = [i for i, k in enumerate(keys) if k not in self._cache]
        if missing:
            encoded = self._encode(ids[missing])
            for j, i in enumerate(missing):
                self._cache[keys[i]] = encoded[j]
        return torch.stack([self._cache[k] for k in keys])

    def _encode(self, ids: torch.Tensor) -> torch.Tensor:
        """``ids [b, L]`` (validated) -> slots ``[b, num_slots, out_dim]``."""
        length = ids.shape[-1]
        valid = ids != 0  # [b, L]
        # An all-padding row would make every key masked (softmax of all -inf = NaN inside the transformer):
        # let such rows attend to their first (padding) position; the slot attention below still ignores it.
        empty = ~valid.any(dim=-1, keepdim=True)
        key_padding = ~valid
        if length:
            first = torch.zeros_like(key_padding)
            first[:, 0] = True
            key_padding = key_padding & ~(empty & first)
        h = self.embed(ids) + self.pos[:length]
        h = self.transformer(h, src_key_padding_mask=key_padding)
        h = self.norm(h)
        return self.slot_attention(h, valid)


class CNNBackbone(nn.Module):
    """Small trainable conv stack producing patch tokens (the paper's "-CLIP" ablation; works offline).

    Pixels ``[*B, H, W, C]`` (uint8 or float on the 0-255 scale, channels-last as environments give) -> /255 ->
    3 x (Conv 3x3, stride 2) with ReLU between -> + soft position embedding (Locatello et al. 2020) -> tokens
    ``[*B, ceil(H/8) * ceil(W/8), out_dim]``; a 56x56 frame gives 7x7 = 49 tokens.

    The position embedding is a linear map of the 4-channel grid (y, x, 1-y, 1-x), so any input size works; it gives
    the permutation-invariant Slot Attention access to token positions (CLIP tokens already carry them).
    """

    def __init__(self, in_channels: int = 3, out_dim: int = 64, hidden: int = 32) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_dim = out_dim
        self.token_dim = out_dim
        # In-place ReLUs (same values and gradients): each conv output is read only by its ReLU (a convolution's
        # backward needs its input, not its output), so overwriting it saves a full-size tensor per layer and
        # ~10% of the stack's forward+backward at a [512, 56, 56, 3] batch (benchmarks/throughput_pixels.py).
        self.net = nn.Sequential(
            nn.Conv2d(in_channels, hidden, 3, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, 2 * hidden, 3, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(2 * hidden, out_dim, 3, stride=2, padding=1),
        )
        self.pos_proj = nn.Linear(4, out_dim)

    @staticmethod
    def _grid(h: int, w: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        ys = torch.linspace(0.0, 1.0, h, device=device, dtype=dtype)
        xs = torch.linspace(0.0, 1.0, w, device=device, dtype=dtype)
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        return torch.stack([gy, gx, 1.0 - gy, 1.0 - gx], dim=-1).reshape(h * w, 4)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """``pixels [*B, H, W, C]`` -> tokens ``[*B, N_tok, out_dim]``."""
        if pixels.dim() < 3:
            raise ValueError(f"CNNBackbone pixels: expected [*B, H, W, {self.in_channels}], got {tuple(pixels.shape)}")
        batch_shape = pixels.shape[:-3]
        x = pixels_to_unit(pixels.reshape(-1, *pixels.shape[-3:]), self.in_channels, "CNNBackbone pixels")
        feats = self.net(x.to(self.pos_proj.weight.dtype))  # [b, C_out, h, w]
        h, w = feats.shape[-2:]
        tokens = feats.flatten(2).transpose(1, 2)  # [b, h*w, C_out]
        tokens = tokens + self.pos_proj(self._grid(h, w, tokens.device, tokens.dtype))
        return tokens.reshape(*batch_shape, h * w, self.out_dim)


#: ``VisionEncoder(pooling=...)``: the paper's Slot Attention, or the token grid flattened into one Linear
VISION_POOLINGS = ("slots", "flatten")


class VisionEncoder(nn.Module):
    """Vision encoder (Appendix E.1): backbone patch tokens -> ``F_vision = W_proj F_patch + b_proj`` -> Slot Attention.

    ``pixels [*B, H, W, C]`` -> backbone tokens ``[*B, N, token_dim]`` (CLIP ViT-B/32: N = 49, token_dim = 768) ->
    Linear(token_dim, out_dim) -> SlotAttention (Eq. A19-A20) -> slots ``[*B, num_slots, out_dim]``.
    ``pooling="flatten"`` (an ablation, not the paper's) replaces the last two steps by one Linear on the flattened
    tokens ``[*B, N * token_dim] -> [*B, 1, out_dim]``: the token grid kept in place, no slot competition.

    ``backbone`` is any module mapping ``[b, H, W, C]`` pixels to ``[b, N, token_dim]`` tokens and exposing
    ``token_dim`` (:class:`CNNBackbone` or :class:`~freamer_rl.layers.clip_backbone.ClipBackbone`).

    Non-finite tokens raise ``ValueError`` in eager mode (Slot Attention would otherwise turn one NaN token into NaN
    slots for the whole sample); the check is skipped (same maths) under vmap/compile.
    """

    def __init__(
        self,
        backbone: nn.Module,
        out_dim: int = 128,
        num_slots: int = 8,
        slot_iters: int = 3,
        pooling: str = "slots",
        num_tokens: int | None = None,
    ) -> None:
        super().__init__()
        token_dim = getattr(backbone, "token_dim", None)
        if not isinstance(token_dim, int):
            raise TypeError(
                f"VisionEncoder backbone {type(backbone).__name__} must expose an int attribute 'token_dim', "
                f"got {token_dim!r}"
            )
        if pooling not in VISION_POOLINGS:
            raise ValueError(f"VisionEncoder pooling: expected one of {', '.join(VISION_POOLINGS)}, got {pooling!r}")
        if pooling == "flatten" and not (isinstance(num_tokens, int) and num_tokens > 0):
            raise ValueError(f"VisionEncoder pooling 'flatten' needs the backbone's token count, got {num_tokens!r}")
        self.backbone = backbone
        self.token_dim = token_dim
        self.out_dim = out_dim
        self.slot_dim = out_dim
        self.pooling = pooling
        if pooling == "slots":
            self.num_slots = num_slots
            self.proj = nn.Linear(token_dim, out_dim)
            self.slot_attention = SlotAttention(num_slots, out_dim, input_dim=out_dim, iters=slot_iters)
        else:
            # one "slot": every token in its grid place, as a PPO-CNN's flatten + Linear reads its conv map
            self.num_slots = 1
            self.num_tokens = num_tokens
            self.flat = nn.Linear(num_tokens * token_dim, out_dim)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """``pixels [*B, H, W, C]`` -> slots ``[*B, num_slots, out_dim]`` (``num_slots`` is 1 for ``flatten``)."""
        if pixels.dim() < 3:
            raise ValueError(f"VisionEncoder pixels: expected [*B, H, W, C], got {tuple(pixels.shape)}")
        batch_shape = pixels.shape[:-3]
        tokens = self.backbone(pixels.reshape(-1, *pixels.shape[-3:]))  # [b, N, token_dim]
        if tokens.dim() != 3 or tokens.shape[-1] != self.token_dim:
            raise ValueError(
                f"VisionEncoder: backbone {type(self.backbone).__name__} returned {tuple(tokens.shape)}, "
                f"expected [b, N, {self.token_dim}]"
            )
        check_finite(tokens, f"VisionEncoder tokens (from {type(self.backbone).__name__})")
        if self.pooling == "flatten":
            if tokens.shape[1] != self.num_tokens:
                raise ValueError(
                    f"VisionEncoder pooling 'flatten': built for {self.num_tokens} tokens, the backbone gave "
                    f"{tokens.shape[1]} (pixels {tuple(pixels.shape[-3:])})"
                )
            slots = self.flat(tokens.to(self.flat.weight.dtype).flatten(1)).unsqueeze(1)
        else:
            slots = self.slot_attention(self.proj(tokens.to(self.proj.weight.dtype)))
        return slots.reshape(*batch_shape, self.num_slots, self.out_dim)


class CrossModalAttention(nn.Module):
    """Bidirectional cross-modal multi-head attention with residuals (Appendix E.3, Eq. A21-A22)::

        S'_vis  = S_vis  + MHA(S_vis,  S_lang, S_lang)     (A21)
        S'_lang = S_lang + MHA(S_lang, S_vis,  S_vis)      (A22)

    Both directions read the *input* slots (they are computed in parallel).
    forward(vision ``[*B, K_v, d]``, language ``[*B, K_l, d]``) -> (vision' ``[*B, K_v, d]``, language' ``[*B, K_l, d]``).
    """

    def __init__(self, dim: int, heads: int = 4) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim ({dim}) must be divisible by heads ({heads})")
        self.dim = dim
        self.out_dim = dim
        self.vis_from_lang = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.lang_from_vis = nn.MultiheadAttention(dim, heads, batch_first=True)

    def forward(self, vision: torch.Tensor, language: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(vision ``[*B, K_v, d]``, language ``[*B, K_l, d]``) -> (vision', language'), same shapes."""
        if vision.dim() < 2 or vision.shape[-1] != self.dim or language.dim() < 2 or language.shape[-1] != self.dim:
            raise ValueError(
                f"CrossModalAttention: expected [*B, K, {self.dim}] inputs, got vision {tuple(vision.shape)} "
                f"and language {tuple(language.shape)}"
            )
        if vision.shape[:-2] != language.shape[:-2]:
            raise ValueError(
                f"CrossModalAttention: batch dims differ: vision {tuple(vision.shape)} vs language {tuple(language.shape)}"
            )
        batch_shape = vision.shape[:-2]
        v = vision.reshape(-1, *vision.shape[-2:])
        lang = language.reshape(-1, *language.shape[-2:])
        v_new = v + self.vis_from_lang(v, lang, lang, need_weights=False)[0]  # Eq. A21
        l_new = lang + self.lang_from_vis(lang, v, v, need_weights=False)[0]  # Eq. A22
        return v_new.reshape(*batch_shape, *v_new.shape[-2:]), l_new.reshape(*batch_shape, *l_new.shape[-2:])


class SlotPool(nn.Module):
    """Mean over the slot axis (Section 3.2): slots ``[*B, K, d]`` -> modality embedding ``e_m`` ``[*B, d]``."""

    def forward(self, slots: torch.Tensor) -> torch.Tensor:
        if slots.dim() < 2:
            raise ValueError(f"SlotPool: expected [*B, K, d], got {tuple(slots.shape)}")
        return slots.mean(dim=-2)
