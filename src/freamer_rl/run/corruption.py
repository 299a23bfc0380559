"""Modality corruption as TorchRL transforms: noise, token replacement, dropout, a stale sensor, a noisy TV.

Each transform corrupts one observation key of any TorchRL env, for any policy (FreamerV1, the baselines, a user's
own), so "does filtering before mixing keep a policy working when one modality is noisy?" can be asked on every env.
Recipes configure them (``env.corrupt: [{key: pixels, kind: gaussian, level: 1.0, when: eval}]``, checked with the
field named); :func:`corruption_transforms` builds the list a trainer (``when`` train) or an evaluator (eval) appends.

Kinds (``level`` means):

* ``gaussian`` -- ``x + level * s * N(0, 1)`` with ``s`` the key's running std (all entries of every env pooled,
  updated from the values this transform receives, from the first reset of the run on: an evaluation measures it on
  its own clean observations), so ``level`` means the same on pixels and on vectors (level 0 draws nothing); uint8 values are rounded and
  clipped to 0..255. Several entries on one key apply in order, each measuring what the previous one produced.
* ``salt`` -- integer keys (grid indices, mission tokens): each entry is replaced with probability ``level`` by a
  uniform random value of the key's spec range (salt-and-pepper / random-token replacement).
* ``dropout`` -- with probability ``level`` per env and step the whole key is zeroed; ``<key>_present`` (float
  ``[*B, 1]``, 1 = kept) is written beside it for a policy that wants to read it.
* ``dropout_episode`` -- the same, drawn once per env and episode (at its reset) and held to its end: a sensor that
  is dead for a whole episode, the case a per-step dropout never shows a policy (RME-style modality dropout).
* ``stale`` -- a frozen sensor: the value is refreshed every ``level`` steps and held in between (per env; an
  episode start refreshes it).
* ``noisy_tv`` -- a distractor inside the key: a share ``level`` of it (a top-left square of an image, the last
  entries of a vector) shows fresh noise every step (uniform over the range for integers, the running mean and std
  for floats).

``channels: [start, stop]`` (or ``key: "imu[0:12]"``) restricts an entry to that slice of the key's last dim: only
the slice changes, its running std is the slice's own, a dropout zeroes the slice only and writes
``<key>_<start>_<stop>_present`` (one sensor site of a concatenated vector, e.g. the health env's hand IMU).

Randomness comes from torch's global generator, so a seeded run corrupts the same way. Reset and step outputs are
corrupted alike; a partial reset changes only the state of the envs it resets.
"""

from __future__ import annotations

import logging
import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Unbounded
from torchrl.envs.transforms import Compose, Transform, TransformedEnv

from freamer_rl.config.sections import check_corruption_kind, clean_key, corruption_target
from freamer_rl.errors import ConfigError

__all__ = [
    "ModalityCorruption",
    "PresenceFlag",
    "SensorCopy",
    "corruption_transforms",
    "copy_transforms",
    "eval_entries",
    "env_corruption_state",
    "load_corruption_state",
    "presence_transforms",
]

logger = logging.getLogger(__name__)

_INTEGER_ONLY = {"salt"}
_FLOAT_OR_PIXELS = {"gaussian"}
_DROPOUTS = {"dropout", "dropout_episode"}


def _is_integer(dtype: torch.dtype) -> bool:
    return not dtype.is_floating_point and dtype != torch.bool


def _spec_range(spec, where: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Element-wise (low, high) of an integer spec (broadcastable to its shape): Categorical ``n``, Bounded ``low`` /
    ``high`` (MiniGrid's grid has other bounds per channel), uint8 0..255."""
    space = getattr(spec, "space", None)
    n = getattr(space, "n", None)
    if n is not None:
        return torch.tensor(0), torch.tensor(int(n) - 1)
    low, high = getattr(space, "low", None), getattr(space, "high", None)
    if low is not None and high is not None:
        return torch.as_tensor(low).long(), torch.as_tensor(high).long()
    if spec.dtype == torch.uint8:
        return torch.tensor(0), torch.tensor(255)
    raise ConfigError(f"{where}.key: {spec.dtype} observation without bounds: no range to draw replacement values from")


def _draw(low: torch.Tensor, high: torch.Tensor, shape: torch.Size, like: torch.Tensor) -> torch.Tensor:
    """Uniform integers in [low, high] element-wise, of ``shape`` (bounds broadcast from the right)."""
    low, high = low.to(like.device), high.to(like.device)
    u = torch.rand(shape, device=like.device)
    return (low + torch.floor(u * (high - low + 1)).long().clamp(max=high - low)).to(like.dtype)


class ModalityCorruption(Transform):
    """Corrupt observation ``key`` with ``kind`` at ``level`` (see the module docstring); ``where`` names the recipe
    entry in errors (``env.corrupt[0]``)."""

    def __init__(
        self,
        key: NestedKey,
        kind: str,
        level: float,
        where: str = "env.corrupt",
        channels: tuple[int, int] | None = None,
    ) -> None:
        check_corruption_kind(kind, level, where)
        super().__init__(in_keys=[key], out_keys=[key])
        self.key, self.kind, self.level, self.where = key, kind, float(level), where
        # [start, stop) of the last dim: only that slice is corrupted (and measured); None: the whole key
        self.channels = None if channels is None else (int(channels[0]), int(channels[1]))
        tail = "" if self.channels is None else f"_{self.channels[0]}_{self.channels[1]}"
        name = key if isinstance(key, str) else key[-1]
        present = f"{name}{tail}_present"
        self.present_key = present if isinstance(key, str) else (*key[:-1], present)
        self._range: tuple[torch.Tensor, torch.Tensor] | None = None
        self._stats = torch.zeros(3, dtype=torch.float64)  # count, mean, M2 of the clean values (Welford)
        self._held: torch.Tensor | None = None
        self._age: torch.Tensor | None = None
        self._keep: torch.Tensor | None = None  # dropout_episode: [*B] bool, this episode's draw per env

    # -- specs ---------------------------------------------------------------------------------------------------
    def transform_observation_spec(self, observation_spec):
        if self.key not in observation_spec.keys(True):
            known = ", ".join(str(k) for k in observation_spec.keys(True, True))
            raise ConfigError(f"{self.where}.key: the env has no observation {self.key!r} (it has {known})")
        spec = observation_spec[self.key]
        if self.channels is not None:
            width = spec.shape[-1] if len(spec.shape) > len(observation_spec.shape) else 0
            if self.channels[1] > width:
                raise ConfigError(
                    f"{self.where}.channels: [{self.channels[0]}, {self.channels[1]}] does not fit {self.key!r}, "
                    f"whose last dim has {width} entries (shape {tuple(spec.shape)})"
                )
        if self.kind in _INTEGER_ONLY and not _is_integer(spec.dtype):
            raise ConfigError(
                f"{self.where}.kind: {self.kind} replaces integer entries, but {self.key!r} is "
                f"{spec.dtype}; use gaussian for float keys"
            )
        if self.kind in _FLOAT_OR_PIXELS and _is_integer(spec.dtype) and spec.dtype != torch.uint8:
            raise ConfigError(
                f"{self.where}.kind: {self.kind} adds noise to float or uint8 pixel keys, but "
                f"{self.key!r} holds {spec.dtype} indices; use salt"
            )
        if _is_integer(spec.dtype):
            low, high = _spec_range(spec, self.where)
            if self.channels is not None:  # per-entry bounds of the full last dim: keep the slice's
                low, high = (self._slice(b) if b.ndim and b.shape[-1] == spec.shape[-1] else b for b in (low, high))
            self._range = (low, high)
        if self.kind in _DROPOUTS:
            observation_spec[self.present_key] = Unbounded(
                (*spec.shape[: len(observation_spec.shape)], 1), device=spec.device, dtype=torch.float32
            )
        return observation_spec

    # -- statistics ----------------------------------------------------------------------------------------------
    def _update_stats(self, x: torch.Tensor) -> None:
        x = x.detach().double().reshape(-1)
        n, mean, m2 = self._stats.tolist()
        k = x.numel()
        if not k:
            return
        bm, bv = float(x.mean()), float(x.var(unbiased=False))
        tot = n + k
        delta = bm - mean
        self._stats = torch.tensor(
            [tot, mean + delta * k / tot, m2 + bv * k + delta**2 * n * k / tot], dtype=torch.float64
        )

    def stats_state(self) -> dict:
        """The running statistic as checkpoint data (plain tensors and strings: ``torch.load(weights_only=True)``)."""
        return {"key": str(self.key), "kind": self.kind, "channels": list(self.channels or []), "stats": self._stats}

    def load_stats_state(self, state: dict) -> None:
        """Restore :meth:`stats_state` (a resumed run keeps measuring from where the checkpoint left off)."""
        stats = torch.as_tensor(state["stats"], dtype=torch.float64)
        if stats.shape != (3,):
            raise ValueError(f"{self.where}: corruption statistic of shape {tuple(stats.shape)}, expected (3,)")
        self._stats = stats.clone()

    @property
    def running_std(self) -> float:
        n, _, m2 = self._stats.tolist()
        return math.sqrt(m2 / n) if n > 0 else 0.0

    # -- corruption ----------------------------------------------------------------------------------------------
    def _corrupt(self, td: TensorDictBase, update: torch.Tensor | None, *, at_reset: bool = True) -> TensorDictBase:
        """Corrupt ``td[key]``; ``update`` [*B] marks the envs whose per-env state may change (None: all);
        ``at_reset``: those envs start an episode (a step output continues one)."""
        full = td.get(self.key, None)
        if full is None:
            raise KeyError(f"{self.where}: observation {self.key!r} missing from the env's output")
        x = full if self.channels is None else self._slice(full)
        batch = td.batch_size
        if update is None:
            update = torch.ones(batch, dtype=torch.bool, device=x.device)
        self._update_stats(x[update])
        if self.kind in _DROPOUTS:
            if self.kind == "dropout":
                keep = torch.rand(batch, device=x.device) >= self.level
            else:
                keep = self._episode_keep(batch, x.device, update if at_reset else torch.zeros_like(update))
            td.set(self.present_key, keep.to(torch.float32).unsqueeze(-1))
            out = x * keep.reshape((*batch, *([1] * (x.ndim - len(batch))))).to(x.dtype)
        elif self.kind == "stale":
            out = self._stale(x, update, len(batch))
        else:
            out = getattr(self, f"_{self.kind}")(x, len(batch))
        if self.channels is not None:  # the rest of the key passes through untouched
            out = torch.cat([full[..., : self.channels[0]], out, full[..., self.channels[1] :]], dim=-1)
        td.set(self.key, out)
        return td

    def _slice(self, x: torch.Tensor) -> torch.Tensor:
        return x[..., self.channels[0] : self.channels[1]]

    def _gaussian(self, x: torch.Tensor, nb: int) -> torch.Tensor:
        if self.level == 0:  # a config value, not a tensor: level 0 draws nothing, so it equals a clean run exactly
            return x
        noisy = x.float() + self.level * self.running_std * torch.randn(x.shape, device=x.device)
        return noisy.round().clamp(0, 255).to(x.dtype) if x.dtype == torch.uint8 else noisy.to(x.dtype)

    def _salt(self, x: torch.Tensor, nb: int) -> torch.Tensor:
        draw = _draw(*self._range, x.shape, x)
        return torch.where(torch.rand(x.shape, device=x.device) < self.level, draw, x)

    def _noisy_tv(self, x: torch.Tensor, nb: int) -> torch.Tensor:
        out = x.clone()
        if self._range is not None:
            noise = _draw(*self._range, x.shape, x)
        else:
            n, mean, m2 = self._stats.tolist()
            noise = (mean + math.sqrt(m2 / n) * torch.randn(x.shape, device=x.device)).to(x.dtype)
        event = x.shape[nb:]
        if len(event) == 3:  # an image [H, W, C]: a top-left square covering `level` of its area
            h, w = max(1, round(math.sqrt(self.level) * event[0])), max(1, round(math.sqrt(self.level) * event[1]))
            out[..., :h, :w, :] = noise[..., :h, :w, :]
        else:  # a vector: its last ceil(level * n) entries
            flat, nflat = out.reshape((*x.shape[:nb], -1)), noise.reshape((*x.shape[:nb], -1))
            k = math.ceil(self.level * flat.shape[-1])
            flat[..., -k:] = nflat[..., -k:]
            out = flat.reshape(x.shape)
        return out

    def _episode_keep(self, batch: torch.Size, device: torch.device, start: torch.Tensor) -> torch.Tensor:
        """dropout_episode: the per-env keep flag [*B], drawn anew where ``start`` [*B] (an episode begins; every env
        the first time) and held elsewhere."""
        draw = torch.rand(batch, device=device) >= self.level
        fresh = self._keep is None or self._keep.shape != draw.shape
        self._keep = draw if fresh else torch.where(start, draw, self._keep)
        return self._keep

    def _stale(self, x: torch.Tensor, update: torch.Tensor, nb: int) -> torch.Tensor:
        if self._held is None or self._held.shape != x.shape:
            self._held, self._age = x.clone(), torch.zeros(x.shape[:nb], dtype=torch.long, device=x.device)
        refresh = update & (self._age % int(self.level) == 0)
        expand = refresh.reshape((*refresh.shape, *([1] * (x.ndim - nb))))
        self._held = torch.where(expand, x, self._held)
        self._age = torch.where(update, self._age + 1, self._age)
        return self._held.clone()

    # -- TorchRL hooks ---------------------------------------------------------------------------------------------
    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._corrupt(next_tensordict, None, at_reset=False)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        update = None if mask is None else mask.reshape(tuple(tensordict_reset.batch_size))
        if self._age is not None:  # an episode start refreshes a stale sensor
            self._age = torch.where(
                update if update is not None else torch.ones_like(self._age, dtype=torch.bool),
                torch.zeros_like(self._age),
                self._age,
            )
        return self._corrupt(tensordict_reset, update)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._corrupt(tensordict, None)


class SensorCopy(Transform):
    """A second sensor of one observation, written on reset and step before any corruption, so the two views can be
    corrupted one at a time: ``new_key`` = ``source_key`` as float32 (``env.copies: {new: source}``), or with
    ``same_spec`` the value itself under the source's own spec (``env.clean_copies``: ``<key>_clean``, the clean
    target of the refiners' paired denoising, ``model.flow.targets=paired``)."""

    def __init__(self, new_key: str, source_key: str, *, same_spec: bool = False, field: str = "env.copies") -> None:
        super().__init__(in_keys=[source_key], out_keys=[new_key])
        self.new_key, self.source_key, self.same_spec = new_key, source_key, same_spec
        self.field = f"{field}.{new_key}" if not same_spec else f"{field}[{source_key}]"

    def transform_observation_spec(self, observation_spec):
        keys = observation_spec.keys(True)
        if self.source_key not in keys:
            known = ", ".join(str(k) for k in observation_spec.keys(True, True))
            raise ConfigError(f"{self.field}: the env has no observation {self.source_key!r} ({known})")
        if self.new_key in keys:
            raise ConfigError(f"{self.field}: the env already has an observation {self.new_key!r}")
        spec = observation_spec[self.source_key]
        observation_spec[self.new_key] = (
            spec.clone() if self.same_spec else Unbounded(spec.shape, device=spec.device, dtype=torch.float32)
        )
        return observation_spec

    def _apply_transform(self, x: torch.Tensor) -> torch.Tensor:
        return x.clone() if self.same_spec else x.to(torch.float32)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)


class PresenceFlag(Transform):
    """``<key>_present`` (float ``[*B, 1]``) in every phase, 1 where nothing wrote it (``env.presence: [key]``).

    A ``dropout`` (or ``dropout_episode``) corruption of ``key`` writes the flag itself (0 where it dropped the key)
    and this transform, placed after the corruptions, leaves that value alone; without one (a clean evaluation, a
    Gaussian or salt corruption) the flag reads 1. So a policy that reads the flag (FreamerV1's
    ``model.presence_keys``, a baseline's ``network.observation_keys``) finds it in every env of the run, trained
    with dropout or not."""

    def __init__(self, key: str) -> None:
        self.key, self.flag = key, f"{key}_present"
        super().__init__(in_keys=[], out_keys=[self.flag])

    def transform_observation_spec(self, observation_spec):
        keys = observation_spec.keys(True)
        if self.key not in keys:
            known = ", ".join(str(k) for k in observation_spec.keys(True, True))
            raise ConfigError(f"env.presence: the env has no observation {self.key!r} (it has {known})")
        if self.flag not in keys:
            batch = observation_spec.shape
            observation_spec[self.flag] = Unbounded((*batch, 1), device=observation_spec.device, dtype=torch.float32)
        return observation_spec

    def _flag(self, td: TensorDictBase) -> TensorDictBase:
        if td.get(self.flag, None) is None:
            td.set(self.flag, torch.ones((*td.batch_size, 1), dtype=torch.float32, device=td.device))
        return td

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._flag(next_tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._flag(tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._flag(tensordict)


def presence_transforms(keys) -> list[PresenceFlag]:
    """The ``env.presence`` flags, to be placed after every corruption of the env."""
    return [PresenceFlag(k) for k in keys]


def copy_transforms(copies: dict[str, str], clean_copies: list[str] | tuple[str, ...] = ()) -> list[SensorCopy]:
    """The ``env.copies`` entries, then the ``env.clean_copies`` ones, as transforms, in order."""
    out = [SensorCopy(new, source) for new, source in copies.items()]
    return out + [SensorCopy(clean_key(k), k, same_spec=True, field="env.clean_copies") for k in clean_copies]


def eval_entries(config_entries: list, override: list | None) -> list:
    """The corruption of an evaluation: ``override`` (``--corrupt``) when given, else the recipe's ``env.corrupt``
    entries whose ``when`` is eval or both."""
    return [c for c in config_entries if c.when in ("eval", "both")] if override is None else list(override)


def corruption_transforms(entries: list, phase: str | None) -> list[ModalityCorruption]:
    """The ``env.corrupt`` entries that apply in ``phase`` (``train`` or ``eval``; None: every entry, already chosen)
    as transforms, in order."""
    out = []
    for i, e in enumerate(entries):
        if phase is None or e.when in (phase, "both"):
            where = f"env.corrupt[{i}]"
            key, channels = corruption_target(e, where)
            out.append(ModalityCorruption(key, e.kind, e.level, where=where, channels=channels))
    return out


def _corruptions(env) -> list[ModalityCorruption]:
    """The :class:`ModalityCorruption` transforms of a TorchRL env, outermost wrapper last, in order."""
    found: list[ModalityCorruption] = []
    while isinstance(env, TransformedEnv):  # no getattr on other envs: wrappers forward unknown names to their env
        transform = env.transform
        parts = list(transform) if isinstance(transform, Compose) else [transform]
        found = [t for t in parts if isinstance(t, ModalityCorruption)] + found
        env = env.base_env
    return found


def env_corruption_state(env) -> list[dict]:
    """The running statistics of ``env``'s corruption transforms (:meth:`ModalityCorruption.stats_state`, in order),
    for a run's checkpoint (issue 20): a resumed run that corrupts during training keeps its ``s``."""
    return [t.stats_state() for t in _corruptions(env)]


def load_corruption_state(transforms: list, state: list[dict] | None, source: str) -> None:
    """Restore ``state`` (:func:`env_corruption_state` of a checkpoint ``source``) into the ``ModalityCorruption``
    entries of ``transforms`` before the envs are built from them (the env's clones start from it). ``None`` (a
    checkpoint written before the statistic was saved) leaves them fresh, with one logged line; entries that no longer
    match (key, kind, slice) are refused with one CheckpointError-worthy ValueError naming the entry."""
    own = [t for t in transforms if isinstance(t, ModalityCorruption)]
    if not own:
        return
    if state is None:
        logger.info(
            "%s holds no corruption statistics (an older checkpoint): they restart from the first reset", source
        )
        return
    if len(state) != len(own):
        raise ValueError(f"{source}: {len(state)} corruption statistics saved for {len(own)} training corruptions")
    for t, saved in zip(own, state):
        if (saved["key"], saved["kind"], list(saved["channels"])) != (str(t.key), t.kind, list(t.channels or [])):
            raise ValueError(
                f"{t.where}: the checkpoint's corruption statistic is of {saved['key']}:{saved['kind']} "
                f"{list(saved['channels'])}, not {t.key}:{t.kind} {list(t.channels or [])}"
            )
        t.load_stats_state(saved)
