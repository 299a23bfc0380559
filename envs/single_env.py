"""What our unbatched env adapters (MiniGrid, Crafter) share: building the output TensorDict without TensorDict's
per-key validation, and answering a reset call that resets nothing."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

EMPTY_SIZE = torch.Size([])
# TensorDict._new_unsafe skips the per-key checks (shape, device) of the constructor; fall back to the constructor on
# tensordict versions without it
_new_td = getattr(TensorDict, "_new_unsafe", TensorDict)


def finish_td(out: dict[str, Any], device: torch.device) -> TensorDictBase:
    """An unbatched TensorDict of ``out`` on ``device``. On the CPU every value was built by the adapter with the
    right shape, so TensorDict's per-key validation (about as costly as the rest of an adapter's step) is skipped;
    created on the env device so that ``EnvBase.step`` does not run a ``.to(device)`` over it either."""
    if device.type == "cpu":
        return _new_td(out, batch_size=EMPTY_SIZE, device=device)
    return TensorDict(out, batch_size=()).to(device)


def unchanged_reset(env, tensordict: TensorDictBase | None, last_obs: TensorDictBase | None) -> TensorDictBase | None:
    """The current observation when a reset call resets nothing (a ``"_reset"`` mask that is all False; transforms
    may have added keys to it), else None: the caller resets."""
    if tensordict is None or last_obs is None:
        return None
    mask = tensordict.get("_reset", None)
    if mask is None or mask.any():
        return None
    keys = [*env.observation_spec.keys(), *env.done_spec.keys()]
    return last_obs.select(*keys, strict=False).clone()
