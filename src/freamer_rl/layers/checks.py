"""When the layers may inspect tensor *values* (host syncs), and the shared non-finite input check.

Every layer's forward must run unchanged under ``torch.vmap`` (TorchRL's ``GAE(value_network=...)`` vmaps the value
network by default), the other ``torch.func`` transforms (``grad``, ``jacrev``) and ``torch.compile``. Inside those,
reading a tensor's value on the host (``.item()``, ``int(t.min())``, ``bool(t.all())``, Python ``if`` on a tensor)
raises ("vmap: It looks like you're calling .item() on a Tensor") or breaks the graph. So the layers split their
guards in two:

- shape/dtype checks (Python on ``.shape`` / ``.dtype``, no sync) always run;
- value checks (index ranges, non-finite inputs), fallback/clamp counting, and data-dependent shortcuts (row
  deduplication, inference caches) run only when :func:`value_checks_active` is True. The maths is identical
  either way: under a transform invalid values are simply not detected and counters are not updated.

In plain eager mode these value checks do read values on the host (a few small syncs per forward: cheap on a CPU,
a pipeline stall per layer on a GPU). :func:`set_value_checks` switches them off globally; the trainer does so when
``run.device`` is not the CPU.
"""

from __future__ import annotations

import torch

__all__ = ["check_finite", "is_transformed", "set_value_checks", "value_checks_active"]

_enabled = True


def set_value_checks(enabled: bool) -> bool:
    """Switch the eager-mode value checks, counters and caches on or off for every layer; returns the old setting."""
    global _enabled
    old, _enabled = _enabled, bool(enabled)
    return old


def is_transformed(*tensors: torch.Tensor) -> bool:
    """True under ``torch.compile`` tracing, or when any of ``tensors`` is a functorch-wrapped tensor (inside
    ``torch.vmap`` / ``torch.func.grad`` / ... ), where host-side reads of tensor values are impossible."""
    if torch.compiler.is_compiling():
        return True
    is_wrapped = torch._C._functorch.is_functorch_wrapped_tensor
    return any(isinstance(t, torch.Tensor) and bool(is_wrapped(t)) for t in tensors)


def value_checks_active(*tensors: torch.Tensor) -> bool:
    """True when value checks, counting and caching may read ``tensors`` on the host (plain eager execution, and
    not switched off by :func:`set_value_checks`)."""
    return _enabled and not is_transformed(*tensors)


def check_finite(x: torch.Tensor, label: str) -> None:
    """Raise ``ValueError`` if the floating tensor ``x`` holds NaN/Inf (eager only; a no-op under transforms).

    One host sync on the clean path (``isfinite(x).all()``); the count is computed only for the error message.
    Integer/bool tensors are always finite and are skipped without a sync.

    Args:
        x: any shape.
        label: ``"<Layer> <input>"`` for the message, e.g. ``"RewardEncoder reward_history"`` (the layer's class
            name and the TensorDict key the input usually comes from).
    """
    if not (x.is_floating_point() or x.is_complex()) or x.numel() == 0 or not value_checks_active(x):
        return
    finite = torch.isfinite(x)
    if bool(finite.all()):
        return
    n_bad = int((~finite).sum())
    raise ValueError(
        f"{label}: {n_bad} non-finite values (NaN/Inf) in the input of shape {tuple(x.shape)}; clean the "
        "observation before the policy (e.g. torchrl's UnaryTransform(in_keys, out_keys, fn=torch.nan_to_num); "
        "FiniteTensorDictCheck() finds the env step that produces it) or fix the layer that wrote this input"
    )
