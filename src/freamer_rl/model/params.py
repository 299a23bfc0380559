"""Parameter table of a FreamerV1 model: trainable vs frozen per component (the paper's Table 4)."""

from __future__ import annotations

from torch import nn

from freamer_rl.layers.dnc import DNCModule
from freamer_rl.layers.encoders import CrossModalAttention, LanguageEncoder, RewardEncoder, VisionEncoder
from freamer_rl.layers.flow_matching import FlowMatchingRefiner
from freamer_rl.layers.fno import FNOFuser, StateFNOEncoder
from freamer_rl.layers.fusion import ConcatFuser, MeanFuser
from freamer_rl.layers.vector import VectorEncoder
from freamer_rl.model.factory import FreamerModules
from freamer_rl.run.params import parameter_rows

__all__ = ["parameter_table"]


def parameter_table(modules: FreamerModules) -> list[dict]:
    """Rows ``{"component", "trainable", "frozen"}`` in the paper's order, then a ``Total`` row."""
    groups: dict[str, list[nn.Module]] = {}

    def add(name: str, m: nn.Module) -> None:
        groups.setdefault(name, []).append(m)

    for m in modules.trunk.modules():
        if isinstance(m, VisionEncoder):
            add("Vision backbone", m.backbone)
            add("Slot Attention + Cross-Modal Attn", m)
        elif isinstance(m, (LanguageEncoder, CrossModalAttention)):
            add("Slot Attention + Cross-Modal Attn", m)
        elif isinstance(m, StateFNOEncoder):
            add("State encoder (FNO)", m)
        elif isinstance(m, VectorEncoder):
            add("Vector encoder (MLP)", m)
        elif isinstance(m, RewardEncoder):
            add("Reward encoder (Conv1D)", m)
        elif isinstance(m, FlowMatchingRefiner):
            where = "fused vector" if "fused" in modules.refiners else f"x{len(modules.refiners)} modalities"
            add(f"Flow Matching ({where})", m)
        elif isinstance(m, FNOFuser):
            add("FNO fusion", m)
        elif isinstance(m, (ConcatFuser, MeanFuser)):
            add(f"{type(m).__name__[:-5]} fusion", m)
        elif isinstance(m, DNCModule):
            add("DNC memory", m)
    add("Policy + Value heads", modules.actor)
    add("Policy + Value heads", modules.critic)
    # The backbone is counted before the vision encoder that contains it, so its weights land in its own row.
    order = ["Vision backbone"] + [g for g in groups if g != "Vision backbone"]
    return parameter_rows({name: groups[name] for name in order if name in groups}, rest=modules.actor_value)
