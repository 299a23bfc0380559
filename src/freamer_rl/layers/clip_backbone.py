"""Frozen open_clip image tower returning unprojected patch tokens (Section 3.2, Appendix E.1).

The paper's vision backbone is a frozen CLIP ViT-B/32: a 224x224 image gives 49 patch tokens (7x7 grid) of width 768,
taken after ``ln_post`` and before the image projection; :class:`~freamer_rl.layers.encoders.VisionEncoder` projects
them to d (``F_vision = W_proj F_patch + b_proj``).

``open_clip`` is an optional dependency (``pip install 'freamer_rl[clip]'``) imported only when a
:class:`ClipBackbone` is built. Weights come from, in this order:

1. ``checkpoint_path``: a local file (``.bin``/``.pt``/``.pth``/``.safetensors``) holding a full open_clip/OpenAI
   CLIP state dict, an image-tower-only state dict, or a saved ``ClipBackbone.state_dict()``;
2. ``pretrained``: an open_clip tag (e.g. ``"openai"``), resolved through open_clip's download/cache (the Hugging
   Face hub cache); a failed download (e.g. offline) is a one-line :class:`ClipWeightsError`;
3. random weights, only with ``pretrained=None, checkpoint_path=None, allow_random_weights=True`` (tests/benchmarks).

Nothing ever falls back silently to random weights.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from freamer_rl.errors import FreamerError
from freamer_rl.layers.encoders import pixels_to_unit
from freamer_rl.torchvision_compat import import_torchvision_safely

logger = logging.getLogger(__name__)

# CLIP image normalisation (OpenAI training statistics; open_clip.constants.OPENAI_DATASET_MEAN / _STD).
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)

_INSTALL_HINT = "pip install 'freamer_rl[clip]'"
_TV_HINT = (
    f"torchvision must be the build paired with torch {torch.__version__} (PyPI's Linux torchvision wheels are CUDA "
    f"builds; with CPU torch install torchvision from https://download.pytorch.org/whl/cpu)"
)


class ClipWeightsError(FreamerError, RuntimeError):
    """CLIP weights cannot be obtained or do not fit the requested model (one-line message for the CLI)."""


class ClipNotInstalledError(ClipWeightsError, ImportError):
    """``open_clip`` (or a dependency it imports, such as torchvision) is missing or cannot be imported."""


def _first_line(exc: BaseException, limit: int = 240) -> str:
    text = str(exc).strip().splitlines()
    line = text[0] if text else ""
    line = f"{type(exc).__name__}: {line}" if line else type(exc).__name__
    return line if len(line) <= limit else line[: limit - 3] + "..."


def import_open_clip():
    """Import ``open_clip`` lazily; raise :class:`ClipNotInstalledError` with one clear line when it is unusable.

    torchvision is imported first through :func:`freamer_rl.torchvision_compat.import_torchvision_safely`, which
    copes with a torchvision that cannot load its C++ operators (a CUDA build of torchvision next to a CPU torch, the
    only torchvision PyPI has for Linux) by declaring two operator schemas and logging a warning.

    Returns:
        The ``open_clip`` module.
    """
    try:
        import_torchvision_safely()
        import open_clip  # noqa: PLC0415  (optional dependency)
    except ModuleNotFoundError as exc:
        if exc.name == "open_clip":
            raise ClipNotInstalledError(f"open_clip is not installed: {_INSTALL_HINT}") from exc
        raise ClipNotInstalledError(
            f"open_clip is installed but its dependency {exc.name!r} is missing ({_INSTALL_HINT}; {_TV_HINT})"
        ) from exc
    except (ImportError, OSError, RuntimeError) as exc:
        raise ClipNotInstalledError(
            f"open_clip is installed but cannot be imported ({_first_line(exc)}); {_TV_HINT}"
        ) from exc
    return open_clip


class ClipBackbone(nn.Module):
    """Frozen open_clip image tower -> unprojected patch tokens.

    Args:
        model_name: open_clip architecture name (``"ViT-B-32"`` in the paper).
        pretrained: open_clip pretrained tag (``"openai"`` in the paper), a local weights file, or None. When
            ``checkpoint_path`` is also given, the file provides the weights and the tag only says which weights
            they are (it selects QuickGELU for the OpenAI/LAION-400M tags, matching how those weights were trained).
        checkpoint_path: local weights file (see module docstring); a missing file is a one-line error naming it.
        image_size: input resolution of the tower (224 for ViT-B/32; another size interpolates the position
            embedding, as open_clip does).
        allow_random_weights: required to build a randomly initialised tower (both weight sources None).
        cache_dir: open_clip/Hugging Face cache directory for tag downloads (None = the default HF cache).
        quick_gelu: force the activation (None = from the pretrained tag's metadata, False without a tag).
        max_batch: frames per tower call (bounds peak memory on large rollout batches).

    Attributes:
        token_dim (int): token width (768 for ViT-B/32).
        num_tokens (int): patch tokens per frame ((image_size / patch) ** 2 = 49).
        weights_source (str): where the weights came from (for logs/reports).

    forward(pixels ``[*B, H, W, 3]`` uint8, or float on the 0-255 scale, channels-last, any size) -> tokens
    ``[*B, num_tokens, token_dim]`` float32, computed under ``torch.no_grad()`` with the tower in eval mode:
    resize (shorter side to ``image_size``, bicubic, antialiased) + centre crop, CLIP mean/std normalisation.
    Float pixels holding NaN/Inf raise ``ValueError`` in eager mode; the forward has no host sync, so it also runs
    under ``torch.vmap``/``torch.compile`` (the check is then skipped; see :mod:`freamer_rl.layers.checks`).
    """

    def __init__(
        self,
        model_name: str = "ViT-B-32",
        pretrained: str | None = "openai",
        checkpoint_path: str | None = None,
        image_size: int = 224,
        allow_random_weights: bool = False,
        cache_dir: str | None = None,
        quick_gelu: bool | None = None,
        max_batch: int = 256,
    ) -> None:
        super().__init__()
        open_clip = import_open_clip()
        if model_name not in open_clip.list_models():
            raise ClipWeightsError(
                f"unknown open_clip model_name {model_name!r} (e.g. 'ViT-B-32', 'ViT-B-16'; see open_clip.list_models())"
            )
        tag_cfg: dict = {}
        if pretrained:
            tag_cfg = open_clip.get_pretrained_cfg(model_name, pretrained)
            if not tag_cfg and checkpoint_path is None and Path(pretrained).expanduser().is_file():
                checkpoint_path = pretrained  # open_clip also accepts a weights file in place of a tag
            elif not tag_cfg and checkpoint_path is None:
                tags = open_clip.list_pretrained_tags_by_model(model_name)
                raise ClipWeightsError(
                    f"unknown pretrained tag {pretrained!r} for CLIP {model_name} (known: {', '.join(tags) or 'none'}); "
                    f"or pass checkpoint_path=<local weights file>"
                )
        if quick_gelu is None:
            quick_gelu = bool(tag_cfg.get("quick_gelu", False))

        # 1) Resolve the weights file before building anything (fail fast, one line).
        weights_file = self._resolve_weights(
            open_clip, model_name, pretrained, checkpoint_path, tag_cfg, cache_dir, allow_random_weights
        )

        # Read the checkpoint before building the architecture, so an unreadable file fails fast.
        state = self._read_state(open_clip, weights_file) if weights_file is not None else None

        # 2) Build the architecture with random weights, keep only the image tower.
        force_size = image_size if image_size != self._config_image_size(open_clip, model_name) else None
        with _quiet_random_init_warning():  # open_clip says "initialized randomly" before we load the weights
            model = open_clip.create_model(
                model_name, pretrained=None, force_quick_gelu=quick_gelu, force_image_size=force_size, device="cpu"
            )
        visual = model.visual
        del model
        if not hasattr(visual, "output_tokens"):
            raise ClipWeightsError(f"open_clip {model_name} image tower has no token output (output_tokens)")
        visual.output_tokens = True  # forward returns (pooled, tokens)

        # 3) Load the weights into the tower.
        if state is not None:
            self._load_tower(visual, state, weights_file)

        visual.requires_grad_(False)
        visual.eval()
        self.visual = visual
        self.model_name = model_name
        self.image_size = int(image_size)
        self.max_batch = int(max_batch)
        patch = visual.conv1.kernel_size[0] if hasattr(visual, "conv1") else None
        grid = getattr(visual, "grid_size", None)
        self.num_tokens = int(grid[0] * grid[1]) if grid is not None else (self.image_size // patch) ** 2
        self.token_dim = int(
            visual.transformer.width if hasattr(visual, "transformer") else visual.ln_post.weight.shape[0]
        )
        self.out_dim = self.token_dim
        self.register_buffer("mean", torch.tensor(CLIP_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(CLIP_STD).view(1, 3, 1, 1), persistent=False)
        logger.info(
            "ClipBackbone %s ready (%s): %d tokens x %d, %.2fM frozen params, weights: %s",
            model_name,
            "QuickGELU" if quick_gelu else "GELU",
            self.num_tokens,
            self.token_dim,
            sum(p.numel() for p in visual.parameters()) / 1e6,
            self.weights_source,
        )

    # ------------------------------------------------------------------ weights
    def _resolve_weights(
        self,
        open_clip,
        model_name: str,
        pretrained: str | None,
        checkpoint_path: str | None,
        tag_cfg: dict,
        cache_dir: str | None,
        allow_random_weights: bool,
    ) -> Path | None:
        """The weights file to load (None: random weights, only when allowed); sets ``self.weights_source``."""
        weights_file: Path | None = None
        if checkpoint_path is not None:
            weights_file = Path(checkpoint_path).expanduser()
            if not weights_file.is_file():
                raise ClipWeightsError(f"CLIP checkpoint_path {str(weights_file)!r} does not exist or is not a file")
            self.weights_source = f"checkpoint {weights_file}"
        elif pretrained:
            weights_file = self._download(open_clip, model_name, pretrained, tag_cfg, cache_dir)
            self.weights_source = f"open_clip {model_name}/{pretrained} ({weights_file})"
        elif allow_random_weights:
            self.weights_source = "random (allow_random_weights=True)"
            logger.warning(
                "ClipBackbone %s uses RANDOM weights (allow_random_weights=True): for tests/benchmarks only", model_name
            )
        else:
            raise ClipWeightsError(
                f"no CLIP weights for {model_name}: pass pretrained=<open_clip tag, e.g. 'openai'> or "
                f"checkpoint_path=<local file>; random weights need allow_random_weights=True"
            )
        return weights_file

    @staticmethod
    def _config_image_size(open_clip, model_name: str) -> int:
        cfg = open_clip.get_model_config(model_name) or {}
        size = cfg.get("vision_cfg", {}).get("image_size", 224)
        return int(size[0] if isinstance(size, (tuple, list)) else size)

    @staticmethod
    def _download(open_clip, model_name: str, pretrained: str, tag_cfg: dict, cache_dir: str | None) -> Path:
        """Resolve an open_clip tag to a local file (cache hit or download). Any failure -> one-line ClipWeightsError."""
        hint = (
            f"provide the weights locally: checkpoint_path=<file> (e.g. open_clip_pytorch_model.bin of "
            f"{tag_cfg.get('hf_hub', '').rstrip('/') or 'the tag'}), or pre-fill the open_clip/Hugging Face cache "
            f"(HF_HOME / cache_dir) on a machine with internet"
        )
        cached = _cached_hub_file(tag_cfg, cache_dir)
        if cached is not None:  # no network round-trip (offline hub retries take ~45 s before failing)
            return cached
        try:
            path = open_clip.pretrained.download_pretrained(tag_cfg, cache_dir=cache_dir)
        except Exception as exc:  # noqa: BLE001 - network/hub errors come in many types; re-raised with the cause
            raise ClipWeightsError(
                f"cannot obtain CLIP weights {model_name}/{pretrained!r} (download failed: {_first_line(exc, 160)}); "
                f"{hint}"
            ) from exc
        if not path or not Path(path).is_file():
            raise ClipWeightsError(f"cannot obtain CLIP weights {model_name}/{pretrained!r} (no file resolved); {hint}")
        return Path(path)

    @staticmethod
    def _read_state(open_clip, path: Path) -> dict:
        """The image-tower state dict held by ``path`` (full CLIP, tower-only or ``ClipBackbone.state_dict()``)."""
        try:
            try:
                state = open_clip.factory.load_state_dict(str(path), weights_only=True)
            except RuntimeError as exc:
                if "TorchScript" not in str(exc):
                    raise
                # The original OpenAI release (e.g. ViT-B-32.pt) is a TorchScript archive: read its tensors only.
                state = dict(torch.jit.load(str(path), map_location="cpu").state_dict())
        except Exception as exc:  # noqa: BLE001 - torch.load/pickle/zip/safetensors errors; re-raised with the cause
            raise ClipWeightsError(f"cannot read CLIP checkpoint {str(path)!r}: {_first_line(exc, 160)}") from exc
        if not isinstance(state, dict) or not state:
            raise ClipWeightsError(f"CLIP checkpoint {str(path)!r} holds no state dict")
        if any(k.startswith("visual.") for k in state):
            state = {k[len("visual.") :]: v for k, v in state.items() if k.startswith("visual.")}
        return state

    @staticmethod
    def _load_tower(visual: nn.Module, state: dict, path: Path) -> None:
        """Strictly load ``state`` into the image tower; a mismatch is a one-line error naming ``path``."""
        # Interpolate the position-embedding grid when the tower's image size differs from the checkpoint's.
        pos = state.get("positional_embedding")
        own = getattr(visual, "positional_embedding", None)
        if pos is not None and own is not None and pos.shape != own.shape and pos.dim() == 2:
            state = {**state, "positional_embedding": _resize_pos_embed(pos, own.shape[0])}
        result = visual.load_state_dict(state, strict=False)
        if result.missing_keys or result.unexpected_keys:
            raise ClipWeightsError(
                f"CLIP checkpoint {str(path)!r} does not fit this image tower: {len(result.missing_keys)} missing "
                f"keys (e.g. {result.missing_keys[:3]}), {len(result.unexpected_keys)} unexpected "
                f"(e.g. {result.unexpected_keys[:3]})"
            )

    # ------------------------------------------------------------------ module
    def train(self, mode: bool = True) -> ClipBackbone:
        """The tower stays frozen in eval mode whatever the parent's mode."""
        super().train(mode)
        self.visual.eval()
        return self

    def preprocess(self, pixels: torch.Tensor) -> torch.Tensor:
        """``[b, H, W, 3]`` pixels (0-255 scale) -> normalised ``[b, 3, image_size, image_size]`` float32."""
        x = pixels_to_unit(pixels, 3, "ClipBackbone pixels").to(torch.float32)
        h, w = x.shape[-2:]
        s = self.image_size
        if (h, w) != (s, s):
            scale = s / min(h, w)
            nh, nw = max(s, round(h * scale)), max(s, round(w * scale))
            x = F.interpolate(x, size=(nh, nw), mode="bicubic", align_corners=False, antialias=True)
            top, left = (nh - s) // 2, (nw - s) // 2
            x = x[..., top : top + s, left : left + s].clamp(0.0, 1.0)
        return (x - self.mean) / self.std

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """``pixels [*B, H, W, 3]`` -> frozen patch tokens ``[*B, num_tokens, token_dim]``."""
        if pixels.dim() < 3:
            raise ValueError(f"ClipBackbone pixels: expected [*B, H, W, 3], got {tuple(pixels.shape)}")
        batch_shape = pixels.shape[:-3]
        flat = pixels.reshape(-1, *pixels.shape[-3:])
        param = next(self.visual.parameters())
        outs = []
        with torch.no_grad():
            for start in range(0, flat.shape[0], self.max_batch):
                x = self.preprocess(flat[start : start + self.max_batch]).to(param.dtype)
                _, tokens = self.visual(x)
                outs.append(tokens.float())
        tokens = torch.cat(outs, 0) if outs else flat.new_zeros(0, self.num_tokens, self.token_dim, dtype=torch.float32)
        return tokens.reshape(*batch_shape, self.num_tokens, self.token_dim)


class _DropRandomInitWarning(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "initialized randomly" not in record.getMessage()


@contextlib.contextmanager
def _quiet_random_init_warning():
    """Hide open_clip's root-logger "Model initialized randomly" while the architecture is built (weights follow)."""
    root = logging.getLogger()
    filt = _DropRandomInitWarning()
    root.addFilter(filt)
    try:
        yield
    finally:
        root.removeFilter(filt)


def _cached_hub_file(tag_cfg: dict, cache_dir: str | None) -> Path | None:
    """The tag's weights file if it is already in the Hugging Face cache (no network access), else None."""
    hub = tag_cfg.get("hf_hub", "")
    if not hub:
        return None
    try:
        from huggingface_hub import try_to_load_from_cache  # noqa: PLC0415  (open_clip dependency)
    except ImportError:
        return None
    repo_id, filename = os.path.split(hub)
    if filename:
        names = [filename[:-4] + ".safetensors", filename] if filename.endswith((".bin", ".pth")) else [filename]
    else:  # open_clip's defaults: safetensors first, then the pickle
        names = ["open_clip_model.safetensors", "open_clip_pytorch_model.bin"]
    for name in names:
        found = try_to_load_from_cache(repo_id, name, cache_dir=cache_dir)
        if isinstance(found, str) and os.path.isfile(found):
            return Path(found)
    return None


def _resize_pos_embed(pos: torch.Tensor, new_len: int) -> torch.Tensor:
    """Bicubic resize of a ``[1 + g*g, C]`` ViT position embedding (class token kept) to ``[new_len, C]``."""
    cls, grid = pos[:1], pos[1:]
    old = int(math.isqrt(grid.shape[0]))
    new = int(math.isqrt(new_len - 1))
    if old * old != grid.shape[0] or new * new != new_len - 1:
        raise ClipWeightsError(f"cannot resize a position embedding of {pos.shape[0]} tokens to {new_len}")
    g = grid.reshape(1, old, old, -1).permute(0, 3, 1, 2)
    g = F.interpolate(g, size=(new, new), mode="bicubic", align_corners=False, antialias=True)
    return torch.cat([cls, g.permute(0, 2, 3, 1).reshape(new * new, -1)], dim=0)
