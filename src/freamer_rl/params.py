"""Parameter table of a FreamerV1 model: trainable vs frozen per component (the paper's Table 4)."""

from __future__ import annotations

import copy
import logging

from torch import nn

from freamer_rl.factory import FreamerModules

#: Printed under the table by ``freamer-rl params``.
OFFLINE_NOTE = (
    "counted on a randomly initialised model of the same architecture: no weights were loaded or downloaded"
)


def _count(module: nn.Module, seen: set[int]) -> tuple[int, int]:
    trainable = frozen = 0
    for p in module.parameters():
        if id(p) in seen:
            continue
        seen.add(id(p))
        if p.requires_grad:
            trainable += p.numel()
        else:
            frozen += p.numel()
    return trainable, frozen


def parameter_table(modules: FreamerModules) -> list[dict]:
    """Rows ``{"component", "trainable", "frozen"}`` in the paper's order, then a ``Total`` row."""
    from freamer_rl.layers.dnc import DNCModule
    from freamer_rl.layers.encoders import CrossModalAttention, LanguageEncoder, RewardEncoder, VisionEncoder
    from freamer_rl.layers.flow_matching import FlowMatchingRefiner
    from freamer_rl.layers.fno import FNOFuser, StateFNOEncoder
    from freamer_rl.layers.vector import VectorEncoder

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
            add(f"Flow Matching (x{len(modules.refiners)} modalities)", m)
        elif isinstance(m, FNOFuser):
            add("FNO fusion", m)
        elif isinstance(m, DNCModule):
            add("DNC memory", m)
    add("Policy + Value heads", modules.actor)
    add("Policy + Value heads", modules.critic)
    seen: set[int] = set()
    rows = []
    # The backbone is counted before the vision encoder that contains it, so its weights land in its own row.
    order = ["Vision backbone"] + [g for g in groups if g != "Vision backbone"]
    for name in order:
        if name not in groups:
            continue
        t = f = 0
        for m in groups[name]:
            dt, df = _count(m, seen)
            t, f = t + dt, f + df
        rows.append({"component": name, "trainable": t, "frozen": f})
    t_rest, f_rest = _count(modules.actor_value, seen)
    if t_rest or f_rest:
        rows.append({"component": "Other (projections, stacking)", "trainable": t_rest, "frozen": f_rest})
    total_t = sum(r["trainable"] for r in rows)
    total_f = sum(r["frozen"] for r in rows)
    rows.append({"component": "Total", "trainable": total_t, "frozen": total_f})
    return rows


def offline_parameter_table(cfg) -> list[dict]:
    """:func:`parameter_table` of ``cfg``'s model built with random weights, so no CLIP weights are resolved.

    A pretrained tag or checkpoint changes the values of the weights, never their number; building the tower at
    random keeps ``freamer-rl params`` instant and offline (it used to try a 50 s download first).
    """
    from freamer_rl.train import build_modules

    cfg = copy.deepcopy(cfg)
    vision = cfg.model.vision
    vision.clip_pretrained, vision.clip_checkpoint, vision.allow_random_weights = None, None, True
    clip_log = logging.getLogger("freamer_rl.layers.clip_backbone")
    level = clip_log.level
    clip_log.setLevel(logging.ERROR)  # its "RANDOM weights" warning is the point here, not a problem
    try:
        return parameter_table(build_modules(cfg))
    finally:
        clip_log.setLevel(level)


def _fmt(n: int) -> str:
    return f"{n / 1e6:.3f}M" if n >= 1e5 else f"{n:,}"


def format_parameter_table(rows: list[dict], markdown: bool = False) -> str:
    total = rows[-1]["trainable"] + rows[-1]["frozen"]
    lines = []
    if markdown:
        lines += ["| Component | Trainable | Frozen | Total |", "|---|---:|---:|---:|"]
        for r in rows:
            lines.append(f"| {r['component']} | {_fmt(r['trainable'])} | {_fmt(r['frozen'])} | "
                         f"{_fmt(r['trainable'] + r['frozen'])} |")
    else:
        lines.append(f"{'Component':40s} {'Trainable':>12s} {'Frozen':>12s} {'Total':>12s}")
        for r in rows:
            lines.append(f"{r['component']:40s} {_fmt(r['trainable']):>12s} {_fmt(r['frozen']):>12s} "
                         f"{_fmt(r['trainable'] + r['frozen']):>12s}")
    share = rows[-1]["trainable"] / total if total else 0.0
    lines.append(f"trainable share: {100 * share:.2f}%")
    return "\n".join(lines)
