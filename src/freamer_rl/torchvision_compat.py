"""Import torchvision beside a CPU torch when the installed torchvision is a CUDA build.

PyPI's only Linux torchvision wheels for a given torch are CUDA builds; beside a CPU torch their C++ extension
cannot load (it needs ``libtorch_cuda.so``). torchvision is written to run without its C++ operators, except that
two fake-kernel registrations in ``torchvision/_meta_registrations.py`` are not guarded by ``_has_ops()``, so
``import torchvision`` fails with ``RuntimeError: operator torchvision::nms does not exist``. Libraries that import
torchvision only for its Python parts (open_clip's transforms, transformers' model modules) then fail to import.

:func:`import_torchvision_safely` imports torchvision and, on exactly that error, declares the schemas of the two
operators (no kernels) and imports again, logging a warning once. Calling ``torchvision.ops.nms`` afterwards still
raises: the declared operators have no implementation.
"""

from __future__ import annotations

import logging
import sys
from types import ModuleType

import torch

logger = logging.getLogger(__name__)

# torchvision's C++ operators whose fake (meta) kernels torchvision registers at import time even when its C++
# extension failed to load (torchvision/_meta_registrations.py guards the other registrations with _has_ops(), not
# these two). Schemas as in torchvision/csrc/ops/nms.cpp and quantized/cpu/qnms_kernel.cpp.
_TORCHVISION_UNGUARDED_OPS = {
    "nms": "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms": "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
}
_torchvision_schema_lib = None  # keeps the declared schemas alive for the process


def _first_line(exc: BaseException, limit: int = 240) -> str:
    """Return ``"ExcType: first line of the message"``, cut to ``limit`` characters."""
    text = str(exc).strip().splitlines()
    line = text[0] if text else ""
    line = f"{type(exc).__name__}: {line}" if line else type(exc).__name__
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _declare_torchvision_schemas() -> None:
    """Declare the schemas of torchvision's unguarded ops so that ``import torchvision`` completes. Returns None.

    Only used after ``import torchvision`` failed with ``operator torchvision::nms does not exist``. open_clip and
    transformers use torchvision's Python parts, never these ops; a call to ``torchvision.ops.nms`` still fails
    loudly (the schema has no kernel).
    """
    global _torchvision_schema_lib
    if _torchvision_schema_lib is not None:
        return
    lib = torch.library.Library("torchvision", "FRAGMENT")
    for name, schema in _TORCHVISION_UNGUARDED_OPS.items():
        if not hasattr(torch.ops.torchvision, name):
            lib.define(schema)
    _torchvision_schema_lib = lib


def _forget_modules(*packages: str) -> None:
    """Drop partially imported packages from ``sys.modules`` so that a second import starts clean. Returns None."""
    for name in [m for m in sys.modules if m.split(".")[0] in packages]:
        del sys.modules[name]


def is_torchvision_missing_op(exc: BaseException) -> bool:
    """Return True when ``exc`` is torchvision's ``operator torchvision::<op> does not exist`` import failure."""
    text = str(exc)
    return isinstance(exc, RuntimeError) and "operator torchvision::" in text and "does not exist" in text


def import_torchvision_safely() -> ModuleType | None:
    """Import torchvision, declaring its two unguarded operator schemas first when its C++ operators cannot load.

    Returns:
        The ``torchvision`` module, or ``None`` when torchvision is not installed (callers that need it report
        that themselves).

    Raises:
        The original import error for any failure other than the missing-operator one (or when the retry fails).
    """
    try:
        import torchvision  # noqa: PLC0415  (optional dependency)
    except ModuleNotFoundError as exc:
        if exc.name == "torchvision":
            return None
        raise
    except RuntimeError as exc:
        if not is_torchvision_missing_op(exc):
            raise
        logger.warning(
            "torchvision's C++ operators could not load (%s; likely a CUDA torchvision build beside torch %s): "
            "declaring the schemas of torchvision::nms/qnms so that torchvision's Python parts import; open_clip "
            "and transformers do not use those operators, and calling them raises",
            _first_line(exc),
            torch.__version__,
        )
        _forget_modules("torchvision")
        _declare_torchvision_schemas()
        import torchvision  # noqa: PLC0415
    return torchvision
