"""Parameter tables of any model: trainable vs frozen parameters per component, a ``Total`` row, and their text or
Markdown rendering (``freamer-rl params``). Shared parameters are counted once, in the first row that holds them."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from torch import nn

__all__ = ["OFFLINE_NOTE", "count_parameters", "parameter_rows", "format_parameter_table"]

#: Printed under the table by ``freamer-rl params``.
OFFLINE_NOTE = "counted on a randomly initialised model of the same architecture: no weights were loaded or downloaded"


def count_parameters(module: nn.Module, seen: set[int]) -> tuple[int, int]:
    """``(trainable, frozen)`` parameters of ``module`` not yet in ``seen`` (ids; updated)."""
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


def parameter_rows(parts: Mapping[str, nn.Module | Iterable[nn.Module]], rest: nn.Module | None = None) -> list[dict]:
    """Rows ``{"component", "trainable", "frozen"}`` per named part (a module or several), in order; parameters of
    ``rest`` not counted yet go to an ``Other`` row; then a ``Total`` row."""
    seen: set[int] = set()
    rows = []
    for name, mods in parts.items():
        t = f = 0
        for m in [mods] if isinstance(mods, nn.Module) else mods:
            dt, df = count_parameters(m, seen)
            t, f = t + dt, f + df
        rows.append({"component": name, "trainable": t, "frozen": f})
    if rest is not None:
        t, f = count_parameters(rest, seen)
        if t or f:
            rows.append({"component": "Other (projections, stacking)", "trainable": t, "frozen": f})
    rows.append(
        {"component": "Total", "trainable": sum(r["trainable"] for r in rows), "frozen": sum(r["frozen"] for r in rows)}
    )
    return rows


def _fmt(n: int) -> str:
    return f"{n / 1e6:.3f}M" if n >= 1e5 else f"{n:,}"


def format_parameter_table(rows: list[dict], markdown: bool = False) -> str:
    total = rows[-1]["trainable"] + rows[-1]["frozen"]
    lines = []
    if markdown:
        lines += ["| Component | Trainable | Frozen | Total |", "|---|---:|---:|---:|"]
        for r in rows:
            lines.append(
                f"| {r['component']} | {_fmt(r['trainable'])} | {_fmt(r['frozen'])} | "
                f"{_fmt(r['trainable'] + r['frozen'])} |"
            )
    else:
        lines.append(f"{'Component':40s} {'Trainable':>12s} {'Frozen':>12s} {'Total':>12s}")
        for r in rows:
            lines.append(
                f"{r['component']:40s} {_fmt(r['trainable']):>12s} {_fmt(r['frozen']):>12s} "
                f"{_fmt(r['trainable'] + r['frozen']):>12s}"
            )
    share = rows[-1]["trainable"] / total if total else 0.0
    lines.append(f"trainable share: {100 * share:.2f}%")
    return "\n".join(lines)
