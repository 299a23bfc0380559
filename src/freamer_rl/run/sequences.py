"""Whole ``[B, T]`` sequences for stateful layers (the DNC), the way TorchRL's recurrent losses need them.

Every TorchRL ``LossModule.forward`` switches recurrent mode on, and in recurrent mode a stateful layer reads time as
the last batch dim. TorchRL's PPO tutorial flattens and shuffles the collected batch (``rb.extend(data.reshape(-1))``):
its 1-D minibatches would thread the DNC memory through unrelated steps (the importance ratio of the first
minibatch, before any update, was 1.023 instead of 1.000), so :class:`~freamer_rl.layers.dnc.DNCModule` refuses a
1-D batch in recurrent mode. Cut the collected ``[envs, T]`` batch into length-``L`` sequences instead and sample
whole sequences::

    rb = sequence_replay_buffer(num_sequences=frames_per_batch // L, sequences_per_minibatch=minibatch_frames // L)
    for data in collector:                       # [envs, T], T a multiple of L
        data = gae(data)
        rb.empty(); rb.extend(split_sequences(data, L))
        for _ in range(len(rb) // rb.batch_size):   # one epoch, each sequence once
            mb = rb.sample()                     # [n, L]: the DNC starts from the memory stored at t = 0
            loss_td = loss(mb)

A sequence may cross an episode boundary: ``is_init`` (``InitTracker``) resets the memory there, exactly as during
collection. TorchRL's ``SliceSampler`` is the alternative when the storage holds whole trajectories; its flat samples
must be reshaped to ``[num_slices, slice_len]`` before the loss (``sample.reshape(-1, slice_len)``) and it needs
``strict_length=True`` so every slice has the same length.
"""

from __future__ import annotations

from tensordict import NonTensorData, NonTensorStack, TensorDictBase, is_non_tensor, is_tensor_collection
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement

__all__ = ["split_sequences", "sequence_replay_buffer"]


def split_sequences(data: TensorDictBase, seq_len: int) -> TensorDictBase:
    """``[*lead, T]`` collected batch (time last) -> ``[N, seq_len]`` whole sequences, ``N = prod(lead) * T / seq_len``.

    Leading dims (envs, or workers x envs from a multi-process collector) are flattened. Non-tensor entries (e.g. a
    raw mission string) are dropped: a tensor storage cannot hold them.

    Raises:
        ValueError: the batch has no leading dim besides time, or ``T`` is not a multiple of ``seq_len``.
    """
    if seq_len < 1:
        raise ValueError(f"split_sequences: seq_len must be >= 1, got {seq_len}")
    if data.ndim < 2 or data.batch_size[-1] % seq_len:
        raise ValueError(
            f"split_sequences: expected a collected batch [..., envs, T] with T a multiple of {seq_len}; got batch "
            f"size {tuple(data.batch_size)} (collect with frames_per_batch = envs * k * {seq_len})"
        )
    non_tensor = [k for k, v in data.items(True, True, is_leaf=_is_leaf) if is_non_tensor(v)]
    if non_tensor:
        data = data.exclude(*non_tensor)
    T = data.batch_size[-1]
    return data.reshape(-1, T).reshape(-1, T // seq_len, seq_len).reshape(-1, seq_len)


def _is_leaf(cls: type) -> bool:
    return issubclass(cls, NonTensorData) or issubclass(cls, NonTensorStack) or not is_tensor_collection(cls)


def sequence_replay_buffer(num_sequences: int, sequences_per_minibatch: int, device="cpu") -> ReplayBuffer:
    """A replay buffer of ``[L]`` sequences sampled without replacement, ``sequences_per_minibatch`` at a time.

    ``device``: where the storage (and so every sampled minibatch) lives; the device the loss runs on.

    Build it once and refill it every batch (``rb.empty(); rb.extend(split_sequences(data, L))``): one sample is a
    ``[n, L]`` minibatch of whole sequences; ``len(rb) // rb.batch_size`` samples make one epoch.
    """
    if num_sequences < 1 or sequences_per_minibatch < 1:
        raise ValueError(
            f"sequence_replay_buffer: num_sequences ({num_sequences}) and sequences_per_minibatch "
            f"({sequences_per_minibatch}) must be >= 1"
        )
    return ReplayBuffer(
        storage=LazyTensorStorage(num_sequences, device=device),
        sampler=SamplerWithoutReplacement(),
        batch_size=sequences_per_minibatch,
    )
