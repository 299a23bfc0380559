"""``torch.compile`` with a working fallback: the eager function takes over, loudly, when compilation fails.

Compilation can fail for reasons outside the model (no C++ compiler for the CPU backend, an unsupported
platform, a torch bug). :class:`CompileOrEager` then logs one warning naming the function and the error, counts
the fallback in :attr:`CompileOrEager.fallbacks`, and runs the eager function from then on. An error that the
eager function raises as well (bad input) is the eager function's own: it propagates unchanged and compiling stays
on. An error caused by a Ctrl-C / SIGTERM during compilation is raised as that interrupt, never taken for a failed
compilation (the run must stop, not go on eagerly).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

from freamer_rl.errors import interrupt_in_chain

logger = logging.getLogger(__name__)

__all__ = ["CompileOrEager"]


class CompileOrEager:
    """Call ``torch.compile(fn, **options)``, or ``fn`` after a failed compilation (warned and counted).

    The compiled function is built on the first call (compiling costs seconds; a model that never takes this path
    never pays). Not pickled: a copy starts uncompiled and compiles on its own first call.
    """

    def __init__(self, fn: Callable[..., Any], name: str, **options: Any) -> None:
        self.fn = fn
        self.name = name
        self.options = options
        self.fallbacks = 0
        self._compiled: Callable[..., Any] | None = None
        self._failed = False

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self._failed:
            return self.fn(*args, **kwargs)
        if self._compiled is None:
            self._compiled = torch.compile(self.fn, **self.options)
        try:
            return self._compiled(*args, **kwargs)
        except Exception as err:  # noqa: BLE001 -- decided below: the compiler's failure or the input's
            interrupt = interrupt_in_chain(err)
            if interrupt is not None:  # Ctrl-C / SIGTERM while compiling, wrapped by the compiler: not a failure
                raise interrupt from err
            compile_error = err
        result = self.fn(*args, **kwargs)  # raises the input's own error (compiling stays on) if eager fails too
        self._failed = True
        self._compiled = None
        self.fallbacks += 1
        first = (str(compile_error).strip().splitlines() or [type(compile_error).__name__])[0][:300]
        logger.warning(
            "%s: torch.compile failed (%s: %s); running it eagerly from now on (set model.compile=false "
            "to skip compiling)",
            self.name,
            type(compile_error).__name__,
            first,
        )
        return result

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_compiled"] = None  # compiled artefacts are process-local
        return state
