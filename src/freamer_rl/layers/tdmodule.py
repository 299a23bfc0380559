"""``KeyedModule``: tensordict's ``TensorDictModule`` without a per-call import probe on its outputs.

``TensorDictModule`` passes every output through ``TensorDict.from_any``, which for a plain tensor asks
``importlib.util.find_spec("pandas")`` on each call (tensordict 0.14): about 50 us per output, 11 outputs per policy
step here, several percent of a collection step. :class:`KeyedModule` writes plain tensors straight into the
tensordict and leaves everything else (tensor collections, ``inplace=False``, ``tensordict_out``) to the parent
class, so it is a drop-in ``TensorDictModule`` (same constructor, keys, state dict and ``isinstance``).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey

__all__ = ["KeyedModule"]


class KeyedModule(TensorDictModule):
    """A ``TensorDictModule`` whose plain-tensor outputs are set directly (see the module docstring)."""

    def _write_to_tensordict(
        self,
        tensordict: TensorDictBase,
        tensors: list[torch.Tensor],
        tensordict_out: TensorDictBase | None = None,
        out_keys: Iterable[NestedKey] | None = None,
    ) -> TensorDictBase:
        keys = list(self.out_keys_source if out_keys is None else out_keys)
        if (
            tensordict_out is not None
            or self.inplace is not True
            or len(keys) != len(tensors)
            or not all(type(t) is torch.Tensor or isinstance(t, torch.nn.Parameter) for t in tensors)
        ):
            return super()._write_to_tensordict(tensordict, tensors, tensordict_out, out_keys)
        for key, tensor in zip(keys, tensors):
            if key != "_":
                tensordict.set(key, tensor)
        return tensordict
