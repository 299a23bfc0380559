"""Exploration bonuses for the shaped reward (paper Appendix G.1): novelty counts, curiosity, vision-language match.

Three independent pieces, each producing one bonus term that :class:`~freamer_rl.machinery.reward_mixer.RewardMixer` mixes
into ``("next", "shaped_reward")`` (G.2) while the env reward ``("next", "reward")`` stays untouched:

- :class:`NoveltyBonus`: a TorchRL env transform, a count-based bonus of the NovelD family for discrete
  observations. It writes ``("next", "novelty_bonus")`` while the env steps, for any TorchRL env.
- :class:`CuriosityModel`: prediction-error curiosity (G.1's ``R_intrinsic``, Pathak et al., paper ref. [41]) on the
  policy's detached features of a collected ``[*B, T]`` batch.
- :func:`vision_language_similarity`: G.1's ``R_VL``, the cosine similarity of two embeddings.

Example (a flat env; our MiniGrid env hashes ``in_keys=["grid", "direction"]``)::

    env = TransformedEnv(base_env, Compose(InitTracker(), StepCounter(), RewardSum(),
                                           NoveltyBonus(in_keys=["observation"])))
    data = collector_batch                                # [*B, T]: ("next", "novelty_bonus") [*B, T, 1]
    RewardMixer({"novelty": (("next", "novelty_bonus"), 0.1)})(data, success_rate=0.3)
    gae.set_keys(reward="shaped_reward")
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Composite, Unbounded
from torchrl.envs import Transform

from freamer_rl.layers.moments import merge_moments

logger = logging.getLogger(__name__)

__all__ = ["CuriosityModel", "NoveltyBonus", "next_step_valid", "vision_language_similarity"]


# ----------------------------------------------------------------------------------------------------------------
# Count-based novelty (NovelD family)
# ----------------------------------------------------------------------------------------------------------------
class NoveltyBonus(Transform):
    """Count-based NovelD bonus for discrete observations, as a TorchRL env transform.

    For each env row and step ``s -> s'`` (``s'`` the NEW state)::

        count(s') += 1                     (over the whole run, all rows share the table)
        N(x) = 1 / sqrt(count(x))
        bonus = max(N(s') - alpha * N(s), 0)   if s' is visited for the first time in this episode of this row
                0                               otherwise (NovelD's episodic restriction)

    A state is the exact bytes of the row's ``in_keys`` entries, concatenated in ``in_keys`` order (int or float
    tensors; no binning). Within one step every row's visit is counted first, then the novelties are read, so the
    rows of a batched env are treated alike whatever their order. A reset counts the reset state as a visit and
    starts the row's episodic set with it (so returning to the start state earns 0); the bonus at reset is 0.
    ``N(s)`` is read from the counts after the step's update.

    Writes ``("next", out_key)`` float32 ``[*B, 1]`` in ``_step`` and ``out_key`` = 0 at reset (declared in the
    observation spec, so ``check_env_specs`` passes and collectors keep it). Works on unbatched envs and batched envs
    (batch ``[*B]``, partial resets through the ``"_reset"`` mask), placed after ``InitTracker``, ``StepCounter``
    and ``RewardSum`` in a ``Compose``. It is an online transform: it cannot be applied to stored data.

    Not checkpointed: the counts and episodic sets live in Python dicts outside ``state_dict``; a resumed run
    restarts them from zero (so the bonus is briefly larger again). Each env copy (each ``ParallelEnv`` worker,
    each collector) keeps its own counts. Memory: one dict entry per distinct state holding its key (for MiniGrid's
    int64 ``grid`` + ``direction`` about 1.2 kB); ``digest_size`` bounds it.

    Args:
        in_keys: observation entries that identify a state, e.g. ``["grid", "direction"]`` for our MiniGrid env
            or ``["observation"]`` for a flat env.
        out_key: the bonus entry (default ``"novelty_bonus"``).
        alpha: NovelD's ``alpha`` (0.5 in the NovelD paper).
        digest_size: ``None`` (default): the key is the exact bytes. An int in ``[1, 64]``: a BLAKE2b digest of that
            many bytes (16 gives a 128-bit key; a collision between n states has probability ~``n^2 / 2^129``).
    """

    def __init__(
        self,
        in_keys: Sequence[NestedKey],
        out_key: NestedKey = "novelty_bonus",
        *,
        alpha: float = 0.5,
        digest_size: int | None = None,
    ) -> None:
        if isinstance(in_keys, (str, tuple)):
            in_keys = [in_keys]
        if not in_keys:
            raise ValueError("NoveltyBonus: in_keys must name at least one observation entry")
        if not (math.isfinite(alpha) and alpha >= 0):
            raise ValueError(f"NoveltyBonus: alpha must be a finite number >= 0, got {alpha!r}")
        if digest_size is not None and not 1 <= digest_size <= 64:
            raise ValueError(f"NoveltyBonus: digest_size must be None or in [1, 64], got {digest_size!r}")
        super().__init__(in_keys=list(in_keys), out_keys=[out_key])
        self.out_key = self.out_keys[0]
        self.alpha = float(alpha)
        self.digest_size = digest_size
        self._counts: dict[bytes, int] = {}
        self._total_visits = 0
        self._episodic: list[set[bytes]] = []  # per row: states seen in the current episode
        self._last: list[bytes | None] = []  # per row: the current state s

    # -- state keys -----------------------------------------------------------------------------------------------
    def _row_keys(self, td: TensorDictBase, rows: int) -> list[bytes]:
        """One hashable key per flattened batch row (``rows`` = number of env rows)."""
        parts = []
        for key in self.in_keys:
            value = td.get(key, None)
            if value is None:
                raise KeyError(
                    f"NoveltyBonus: observation entry {key!r} is missing (in_keys={self.in_keys}); "
                    f"the env provides {list(td.keys(True, True))}"
                )
            parts.append(value.detach().reshape(rows, -1).cpu().contiguous().numpy())
        keys = [b"".join(p[i].tobytes() for p in parts) for i in range(rows)]
        if self.digest_size is not None:
            keys = [hashlib.blake2b(k, digest_size=self.digest_size).digest() for k in keys]
        return keys

    def _visit(self, keys: list[bytes]) -> None:
        for k in keys:
            self._counts[k] = self._counts.get(k, 0) + 1
        self._total_visits += len(keys)

    def _novelty(self, key: bytes | None) -> float:
        count = self._counts.get(key, 0) if key is not None else 0
        return 1.0 / math.sqrt(count) if count else 0.0

    def _ensure_rows(self, rows: int) -> None:
        if len(self._last) != rows:  # first use, or the batch size changed: start every row afresh
            if self._last:
                logger.warning(
                    "NoveltyBonus: the env batch changed from %d to %d rows; episodic sets restarted "
                    "(the counts are kept)",
                    len(self._last),
                    rows,
                )
            self._episodic = [set() for _ in range(rows)]
            self._last = [None] * rows

    # -- TorchRL hooks --------------------------------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        rows = batch.numel()
        self._ensure_rows(rows)
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        which = range(rows) if mask is None else mask.reshape(rows, -1).any(-1).nonzero().flatten().tolist()
        if which:
            keys = self._row_keys(tensordict_reset, rows)
            self._visit([keys[i] for i in which])
            for i in which:
                self._episodic[i] = {keys[i]}
                self._last[i] = keys[i]
        tensordict_reset.set(self.out_key, torch.zeros(*batch, 1, dtype=torch.float32, device=tensordict_reset.device))
        return tensordict_reset

    def _reset_on_native_autoreset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        batch = next_tensordict.batch_size
        rows = batch.numel()
        self._ensure_rows(rows)
        keys = self._row_keys(next_tensordict, rows)
        self._visit(keys)
        bonus = [0.0] * rows
        for i, key in enumerate(keys):
            if key not in self._episodic[i]:
                self._episodic[i].add(key)
                bonus[i] = max(self._novelty(key) - self.alpha * self._novelty(self._last[i]), 0.0)
            self._last[i] = key
        out = torch.tensor(bonus, dtype=torch.float32, device=next_tensordict.device).reshape(*batch, 1)
        next_tensordict.set(self.out_key, out)
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec[self.out_key] = Unbounded(
            shape=(*observation_spec.shape, 1), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(
            "NoveltyBonus is an online env transform (it counts visits as the env steps): append it "
            "to a TransformedEnv; it cannot be applied to stored data"
        )

    # -- logging --------------------------------------------------------------------------------------------------
    def counts_summary(self) -> dict[str, int]:
        """``{"distinct_states": ..., "total_visits": ...}`` over the run so far (for logging; not checkpointed)."""
        return {"distinct_states": len(self._counts), "total_visits": self._total_visits}

    def reset_counts(self) -> None:
        """Forget every count and episodic set (as a fresh or resumed run starts)."""
        self._counts.clear()
        self._total_visits = 0
        self._episodic = []
        self._last = []

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(in_keys={self.in_keys}, out_key={self.out_key!r}, alpha={self.alpha}, "
            f"distinct_states={len(self._counts)})"
        )


# ----------------------------------------------------------------------------------------------------------------
# Prediction-error curiosity
# ----------------------------------------------------------------------------------------------------------------
def next_step_valid(done: torch.Tensor) -> torch.Tensor:
    """The ``valid`` mask of :class:`CuriosityModel` from a collected batch's ``("next", "done")`` ``[*B, T, 1]``.

    Step ``t`` is valid when the row's step ``t + 1`` continues the same episode: the episode did not end at ``t``
    (``done`` covers terminated and truncated) and ``t`` is not the row's last step. Returns bool ``[*B, T]``.
    """
    valid = ~done.reshape(done.shape[:-1]) if done.shape[-1:] == (1,) else ~done
    valid = valid.clone()
    valid[..., -1] = False
    return valid


class CuriosityModel(nn.Module):
    """Prediction-error curiosity (G.1's ``R_intrinsic``; Pathak et al. 2017, paper ref. [41]) on detached features.

    A forward model ``f([phi_t, onehot(a_t)]) -> phi_{t+1}`` (an MLP with one hidden layer of ``hidden`` units)
    predicts the next step's feature. The features are the policy's ``"fused"`` embedding of the collected batch
    (``[*B, T, d]``, time last), always detached: only the forward model learns from this module, the policy's
    encoders are not pulled towards predictable features (the inverse model of ICM is left out).

    Contract of ``phi, action, valid`` (every method):
        phi: ``[*B, T, d]`` features of the root states, time last; ``phi[..., t + 1, :]`` is the state after step
            ``t`` when ``valid[..., t]``.
        action: ``[*B, T]`` int64 indices in ``[0, n_actions)`` (``[*B, T, 1]`` is accepted), or a float
            ``[*B, T, n_actions]`` (one-hot or a continuous action, used as given).
        valid: bool ``[*B, T]`` (or ``[*B, T, 1]``): True where step ``t`` has a successor in the same row and episode,
            i.e. ``~done[..., t]`` and ``t < T - 1``; build it with :meth:`valid_mask` (:func:`next_step_valid`) from
            ``("next", "done")``.
            The last step of each row is treated as invalid whatever ``valid`` says.

    Intrinsic reward (per step ``t``, ``[*B, T, 1]``, 0 where invalid)::

        e_t = mean_j (f(phi_t, a_t)_j - phi_{t+1, j})^2          (squared error per feature dim)
        r_t = e_t / sqrt(running_var(e) + eps)                 (normalised by a running std)

    The running statistics (buffers, so in ``state_dict``) are updated by :meth:`update_stats` or by
    ``intrinsic_reward(..., update_stats=True)``; every computation is tensor-only (no ``.item()``, no Python branch
    on a tensor value), so it runs under ``torch.func.vmap`` and on an accelerator without host syncs.

    Args:
        feature_dim: ``d``.
        n_actions: number of discrete actions (or the action dim of a float action).
        hidden: hidden width of the forward model.
        eps: added to the running variance.
    """

    def __init__(self, feature_dim: int, n_actions: int, *, hidden: int = 128, eps: float = 1e-8) -> None:
        super().__init__()
        self.feature_dim = int(feature_dim)
        self.n_actions = int(n_actions)
        self.eps = float(eps)
        self.forward_model = nn.Sequential(
            nn.Linear(self.feature_dim + self.n_actions, hidden), nn.ReLU(), nn.Linear(hidden, self.feature_dim)
        )
        self.register_buffer("err_mean", torch.zeros(()))
        self.register_buffer("err_var", torch.ones(()))
        self.register_buffer("err_count", torch.full((), 1e-4))

    #: the ``valid`` mask from ``("next", "done")`` ``[*B, T, 1]`` (see :func:`next_step_valid`)
    valid_mask = staticmethod(next_step_valid)

    def _action_features(self, action: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """``[*B, T]`` / ``[*B, T, 1]`` indices -> one-hot ``[*B, T, n_actions]``; a float action is used as given."""
        if action.is_floating_point():
            return action.to(like.dtype)
        if action.shape == (*like.shape[:-1], 1):
            action = action.squeeze(-1)
        return F.one_hot(action.long(), self.n_actions).to(like.dtype)

    def forward(self, phi: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Predicted next features ``[*B, T, d]`` for every step (``phi`` is detached here)."""
        phi = phi.detach()
        return self.forward_model(torch.cat([phi, self._action_features(action, phi)], dim=-1))

    def prediction_error(self, phi: torch.Tensor, action: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Raw squared error per feature dim ``e_t`` ``[*B, T, 1]``, 0 where invalid (differentiable in ``f``)."""
        phi = phi.detach()
        inputs = torch.cat([phi, self._action_features(action, phi)], dim=-1)[..., :-1, :]
        pred = self.forward_model(inputs)  # [*B, T-1, d]: phi_{t+1} predicted for t < T - 1
        err = (pred - phi[..., 1:, :]).pow(2).mean(-1, keepdim=True)  # [*B, T-1, 1]
        err = torch.cat([err, torch.zeros_like(err[..., :1, :])], dim=-2)  # the last step has no successor
        return err * self._mask(valid, err)

    @staticmethod
    def _mask(valid: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """``valid`` ``[*B, T]`` or ``[*B, T, 1]`` -> float ``[*B, T, 1]`` like ``like``, the last step set to 0."""
        if valid.dim() < like.dim():
            valid = valid.unsqueeze(-1)
        mask = valid.to(like.dtype).expand_as(like).clone()
        mask[..., -1, :] = 0.0
        return mask

    @torch.no_grad()
    def update_stats(self, err: torch.Tensor, valid: torch.Tensor) -> None:
        """Merge the valid entries of ``err`` ``[*B, T, 1]`` into the running mean/variance (Chan et al.'s parallel
        update; an all-invalid batch leaves them unchanged)."""
        mask = self._mask(valid, err)
        n = mask.sum()
        batch_mean = (err * mask).sum() / n.clamp_min(1.0)
        batch_var = ((err - batch_mean).pow(2) * mask).sum() / n.clamp_min(1.0)
        count, mean, var = merge_moments(self.err_count, self.err_mean, self.err_var, n, batch_mean, batch_var)
        self.err_mean.copy_(mean)
        self.err_var.copy_(var)
        self.err_count.copy_(count)

    def intrinsic_reward(
        self, phi: torch.Tensor, action: torch.Tensor, valid: torch.Tensor, *, update_stats: bool = True
    ) -> torch.Tensor:
        """Normalised curiosity ``r_t = (e_t - mean_batch(e)) / std(e)`` ``[*B, T, 1]`` (the mean over this batch's
        valid steps, the running std; no gradient), 0 where invalid.

        ``update_stats=True`` first merges this batch's errors into the running statistics (once per collected
        batch); pass False to read the reward without changing them (e.g. under ``vmap``).
        """
        with torch.no_grad():
            err = self.prediction_error(phi, action, valid)
            if update_stats:
                self.update_stats(err, valid)
            # centred on this batch's mean as well as scaled: an always-positive bonus would pay the agent for long
            # episodes, and a running mean lags behind a forward model that keeps learning (a standing penalty)
            mask = self._mask(valid, err)
            batch_mean = (err * mask).sum() / mask.sum().clamp_min(1.0)
            return (err - batch_mean) / (self.err_var + self.eps).sqrt() * mask

    def loss(self, phi: torch.Tensor, action: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Forward-model MSE over the valid steps (a scalar; 0 when none is valid): the trainer's ``loss_curiosity``."""
        err = self.prediction_error(phi, action, valid)
        return err.sum() / self._mask(valid, err).sum().clamp_min(1.0)


# ----------------------------------------------------------------------------------------------------------------
# Vision-language similarity
# ----------------------------------------------------------------------------------------------------------------
def vision_language_similarity(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """G.1's ``R_VL``: cosine similarity of two embeddings ``[*, d]`` -> ``[*, 1]`` in ``[-1, 1]``.

    In the trainer: ``a`` = the refined vision embedding ``("refined", "vision")`` (or ``("refined", "state")`` when the
    env has no pixels, e.g. MiniGrid's symbolic grid), ``b`` = the refined mission embedding ``("refined",
    "language")``; both ``[*B, T, d]`` on a collected batch, so the term is ``[*B, T, 1]``. Computed on the root
    (current) state of each step; detach the inputs when it is used as a reward.
    """
    return F.cosine_similarity(a, b, dim=-1, eps=eps).unsqueeze(-1)
