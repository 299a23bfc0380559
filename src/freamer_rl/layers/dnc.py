"""Layer 4: content-addressed DNC memory (paper Section 3.5, Appendix F.1) and its TorchRL stateful wrapper.

Maths (content-based addressing only -- no usage/allocation/temporal links; one write head, one read head):

    interface(x) -> k_w [W], beta_w = 1 + softplus(.), e = sigmoid(.) [W], a = tanh(.) [W], g = sigmoid(.) scalar,
                    k_r [W], beta_r = 1 + softplus(.)
    w(i)  = softmax_i(beta * cos(k, M[i]))                          (content weights, Appendix F.1)
    write "additive" (Appendix F.1 as printed; the layer's default, so a caller that chooses nothing keeps it):
    M'    = M * (1 - g w_w e^T) + g w_w a^T                          (erase + write; then clamped, see below)
    write "bounded" (the written value scaled by the erase gate; ``model.dnc.write: bounded``, e.g. gym/cartpole):
    M'    = M * (1 - g w_w e^T) + g w_w (e * a)^T  =  M + g w_w(i) e_j (a_j - M_ij)
    r     = sum_i w_r(i) M'[i]                                       (read from the *written* memory)
    e_aug = GELU(W_out [x; r] + b)                                   (Appendix F.1, input to the policy head Eq. 5)
    e_aug = LayerNorm(e_aug)                                         (only with output_norm=True)

Why "bounded": with lambda_ij = g w_w(i) e_j in [0, 1] each bounded entry is the convex combination ``M'_ij = (1 -
lambda_ij) M_ij + lambda_ij a_j``, so ``|M'| <= max(|M|, |a|) <= max(|M|, 1)`` and, from the zero memory of an episode
start, ``|M| <= 1`` at every step of any episode, however long. The additive write is not convex: repeated writes to
one slot move ``M_ij`` towards the fixed point ``a_j / e_j``, which is beyond the clamp (10) whenever ``e_j < 0.1``:
with it a trained CartPole policy (seed 0, 100k frames) had 34% of its memory entries at the clamp at steps 400 and
1,000 of a 1,421-step episode, and 68 million clamp events in its training run. The bounded write differs from the
paper's printed update only in scaling ``a`` by ``e`` (a gate that erases nothing writes nothing).

Numerical safety:
``cos`` divides by ``sqrt(||v||^2 + eps^2)`` (eps = 1e-6), which is finite with finite gradients even for an all-zero
memory (that gives uniform weights). The write vector is ``a = tanh(.)`` in ``[-1, 1]``; the additive update is *not* a
convex combination (``(1 - g w e) + g w`` can exceed 1 when ``e < 1``), so repeated writes to one slot without erasing
grow it by up to ``g w(i)`` per step. The new memory is therefore clamped to ``[-memory_clip, memory_clip]`` (default
10) with either write (the bounded one never reaches a clip >= 1: the clamp and its count stay as the guard, and a
count above 0 with ``bounded`` and the default clip would be a bug). Each clamped entry is counted in ``clip_events``
and logged (rate-limited ``logger.warning``); counting is skipped inside ``torch.func`` transforms / ``torch.compile``
(the clamp still applies). A non-finite input ``x`` raises ``ValueError`` in eager mode (it is a bug upstream, and the
memory would carry the NaN into every later step of the episode); under transforms the check is skipped and the maths
is unchanged (see :mod:`freamer_rl.layers.checks`).

Checkpoints: the write is recorded in the state dict (buffer ``write_code``: 0 additive, 1 bounded). A state dict
without it predates the choice and was trained with the additive write, so loading one sets the additive write; a
state dict that records the other write than the module was built with sets the recorded one. Either change logs a
warning naming ``model.dnc.write``: the weights only mean what they were trained to mean with their own write.
"""

from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Unbounded
from torchrl.envs.transforms import TensorDictPrimer
from torchrl.modules import recurrent_mode

from freamer_rl.layers.checks import check_finite, is_transformed, value_checks_active
from freamer_rl.layers.compiled import CompileOrEager

logger = logging.getLogger(__name__)

__all__ = ["WRITES", "DNCMemory", "DNCModule"]

_EPS = 1e-6

#: ``model.dnc.write`` choices, in the order of the ``write_code`` buffer (0 additive, 1 bounded)
WRITES = ("additive", "bounded")


def _safe_norm(v: torch.Tensor) -> torch.Tensor:
    """``sqrt(||v||^2 + eps^2)`` over the last dim: >= eps, smooth at 0."""
    return torch.sqrt(v.pow(2).sum(-1) + _EPS**2)


class DNCMemory(nn.Module):
    """Content-addressed DNC memory step (Appendix F.1). Plain ``nn.Module``; state is passed explicitly.

    Args:
        input_dim: size ``D_in`` of the input ``x`` (the fused representation ``e_fused``).
        memory_slots: ``N`` (Table A20: 32).
        memory_width: ``W`` (Table A20: 64).
        output_dim: size ``D_out`` of ``e_aug`` (default ``input_dim``).
        memory_clip: bound on ``|M'|`` entries (``None`` disables the clamp). Clamped entries are counted in
            :attr:`clip_events` and logged.
        write: ``"additive"`` (Appendix F.1 as printed, the default; earlier checkpoints) or ``"bounded"`` (convex,
            ``|M| <= 1`` in any episode), see the module docstring.
        output_norm: LayerNorm (with affine weights) on ``e_aug``, so the heads see unit-scale features.

    Shapes:
        step / forward: ``x [*B, D_in]``, ``memory [*B, N, W]`` -> ``(e_aug [*B, D_out], new_memory [*B, N, W])``.
    """

    def __init__(
        self,
        input_dim: int,
        memory_slots: int = 32,
        memory_width: int = 64,
        output_dim: int | None = None,
        *,
        memory_clip: float | None = 10.0,
        write: str = "additive",
        output_norm: bool = False,
    ) -> None:
        super().__init__()
        if write not in WRITES:
            raise ValueError(f"write must be one of {', '.join(WRITES)}; got {write!r}")
        if min(input_dim, memory_slots, memory_width) < 1:
            raise ValueError(
                f"input_dim, memory_slots and memory_width must be positive; got {input_dim}, {memory_slots}, "
                f"{memory_width}"
            )
        self.input_dim = input_dim
        self.memory_slots = memory_slots
        self.memory_width = memory_width
        self.output_dim = input_dim if output_dim is None else output_dim
        w = memory_width
        # [k_w (W), beta_w (1), erase (W), write vector (W), gate (1), k_r (W), beta_r (1)]
        self._split = (w, 1, w, w, 1, w, 1)
        self.interface = nn.Linear(input_dim, sum(self._split))
        self.out = nn.Linear(input_dim + w, self.output_dim)
        if memory_clip is not None and not memory_clip > 0:
            raise ValueError(f"memory_clip must be positive or None; got {memory_clip}")
        self.memory_clip = memory_clip
        self.clip_events = 0  # number of memory entries clamped so far (numerical fallback, see module docstring)
        self._clip_warnings = 0
        self.out_norm = nn.LayerNorm(self.output_dim) if output_norm else None
        # a Python string, so the step branches at trace time, not on a tensor (no host sync, compile-friendly);
        # the buffer only carries it through checkpoints (see the module docstring, "Checkpoints")
        self.write_mode = write
        self.register_buffer("write_code", torch.tensor(WRITES.index(write), dtype=torch.uint8))

    @property
    def memory_shape(self) -> tuple[int, int]:
        """``(N, W)``."""
        return (self.memory_slots, self.memory_width)

    @staticmethod
    def content_weights(key: torch.Tensor, memory: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
        """Content addressing ``w(i) = softmax_i(beta * cos(key, memory[i]))`` (Appendix F.1).

        Args:
            key: ``[*B, W]``.
            memory: ``[*B, N, W]``.
            beta: strength ``[*B]`` (or broadcastable, e.g. a float tensor).

        Returns:
            ``[*B, N]`` (sums to 1 over ``N``).
        """
        dot = (memory @ key.unsqueeze(-1)).squeeze(-1)  # [*B, N]
        cos = dot / (_safe_norm(memory) * _safe_norm(key).unsqueeze(-1))
        return torch.softmax(torch.as_tensor(beta, dtype=cos.dtype).unsqueeze(-1) * cos, dim=-1)

    @staticmethod
    def write(
        memory: torch.Tensor, weights: torch.Tensor, erase: torch.Tensor, add: torch.Tensor, gate: torch.Tensor
    ) -> torch.Tensor:
        """Gated erase/write ``M' = M * (1 - g w e^T) + g w a^T`` (Appendix F.1).

        Args:
            memory: ``[*B, N, W]``; weights: ``[*B, N]``; erase: ``[*B, W]`` in ``[0, 1]``; add: ``[*B, W]``;
            gate: ``[*B]`` in ``[0, 1]``.

        Returns:
            ``[*B, N, W]``.
        """
        gw = (gate.unsqueeze(-1) * weights).unsqueeze(-1)  # [*B, N, 1]
        return memory * (1.0 - gw * erase.unsqueeze(-2)) + gw * add.unsqueeze(-2)

    @staticmethod
    def write_bounded(
        memory: torch.Tensor, weights: torch.Tensor, erase: torch.Tensor, add: torch.Tensor, gate: torch.Tensor
    ) -> torch.Tensor:
        """Convex erase/write ``M' = M * (1 - g w e^T) + g w (e * a)^T``: every entry moves towards ``a_j`` by the
        fraction ``lambda_ij = g w(i) e_j`` in ``[0, 1]``, so ``|M'| <= max(|M|, |a|)``.

        Same arguments and shapes as :meth:`write`.
        """
        lam = (gate.unsqueeze(-1) * weights).unsqueeze(-1) * erase.unsqueeze(-2)  # [*B, N, W]
        return memory * (1.0 - lam) + lam * add.unsqueeze(-2)

    @staticmethod
    def read(memory: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Read ``r = sum_i w(i) M[i]``: ``memory [*B, N, W]``, ``weights [*B, N]`` -> ``[*B, W]``."""
        return (weights.unsqueeze(-2) @ memory).squeeze(-2)

    def interface_vectors(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """Split the interface projection of ``x [*B, D_in]`` into the activated DNC controls.

        Returns a dict with ``write_key [*B, W]``, ``write_strength [*B]`` (>= 1), ``erase [*B, W]`` (0..1),
        ``write_vector [*B, W]`` (-1..1), ``write_gate [*B]`` (0..1), ``read_key [*B, W]``, ``read_strength [*B]``.
        """
        k_w, b_w, e, a, g, k_r, b_r = self.interface(x).split(self._split, dim=-1)
        return {
            "write_key": k_w,
            "write_strength": 1.0 + F.softplus(b_w.squeeze(-1)),
            "erase": torch.sigmoid(e),
            "write_vector": torch.tanh(a),
            "write_gate": torch.sigmoid(g.squeeze(-1)),
            "read_key": k_r,
            "read_strength": 1.0 + F.softplus(b_r.squeeze(-1)),
        }

    def step(self, x: torch.Tensor, memory: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One write-then-read step.

        ``x [*B, D_in]``, ``memory [*B, N, W]`` -> ``(e_aug [*B, D_out], M' [*B, N, W])``.
        """
        if x.shape[-1] != self.input_dim:
            raise ValueError(f"DNC input must have last dim input_dim={self.input_dim}; got shape {tuple(x.shape)}")
        if memory.ndim < 2 or tuple(memory.shape[-2:]) != self.memory_shape:
            raise ValueError(
                f"DNC memory must have shape [*B, N={self.memory_slots}, W={self.memory_width}]; "
                f"got {tuple(memory.shape)}"
            )
        if memory.shape[:-2] != x.shape[:-1]:
            raise ValueError(
                f"DNC input batch dims {tuple(x.shape[:-1])} and memory batch dims {tuple(memory.shape[:-2])} differ"
            )
        check_finite(x, "DNCMemory input")
        r, new_memory = self.memory_step(self.interface_vectors(x), memory)
        return self.output(x, r), new_memory

    def memory_step(self, controls: dict[str, torch.Tensor], memory: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The memory-dependent part of a step: write then read (Appendix F.1); clamped entries are counted.

        ``controls`` from :meth:`interface_vectors` (``[*B, ...]``), ``memory [*B, N, W]`` ->
        ``(read vector r [*B, W], M' [*B, N, W])``. Split out so a sequence can project all its interface vectors
        (and outputs) in one batched matmul and loop over time only here.
        """
        r, new_memory, clamped = self.write_read(controls, memory)
        self.note_clamped(clamped)
        return r, new_memory

    def write_read(
        self, controls: dict[str, torch.Tensor], memory: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`memory_step` without the host-side count: ``(r, M', clamped)`` with ``clamped`` the number of
        entries the clamp changed, a 0-d tensor (free of host syncs: compilable; sum it over a loop and pass the
        total to :meth:`note_clamped` once)."""
        c = controls
        w_w = self.content_weights(c["write_key"], memory, c["write_strength"])
        write = self.write_bounded if self.write_mode == "bounded" else self.write
        written = write(memory, w_w, c["erase"], c["write_vector"], c["write_gate"])
        clip = self.memory_clip
        if clip is None:
            new_memory, clamped = written, torch.zeros((), dtype=torch.long, device=written.device)
        else:
            new_memory, clamped = written.clamp(-clip, clip), (written.detach().abs() > clip).sum()
        w_r = self.content_weights(c["read_key"], new_memory, c["read_strength"])
        return self.read(new_memory, w_r), new_memory, clamped

    def output(self, x: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        """``e_aug = GELU(W_out [x; r] + b)`` (then LayerNorm with ``output_norm``) for ``x [*B, D_in]``,
        ``r [*B, W]`` -> ``[*B, D_out]``."""
        e_aug = F.gelu(self.out(torch.cat([x, r], dim=-1)))
        return e_aug if self.out_norm is None else self.out_norm(e_aug)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing, unexpected, errors):
        """Take the write the state dict was trained with (``write_code``; absent: ``additive``, the only write of
        earlier releases) and warn when it is not the one this module was built with."""
        key = prefix + "write_code"
        legacy = key not in state_dict
        if legacy:
            state_dict[key] = torch.tensor(WRITES.index("additive"), dtype=torch.uint8)
        code = state_dict[key]
        if isinstance(code, torch.Tensor) and code.numel() == 1 and int(code) in range(len(WRITES)):
            trained = WRITES[int(code)]
            if trained != self.write_mode:
                logger.warning(
                    "DNCMemory: the checkpoint was trained with model.dnc.write=%s%s, this module was built with %s: "
                    "loading it with the %s write it was trained with",
                    trained,
                    " (its state predates the choice)" if legacy else "",
                    self.write_mode,
                    trained,
                )
                self.write_mode = trained
        else:
            errors.append(f"{key}: expected a 0-d code in 0..{len(WRITES) - 1} (one of {WRITES}); got {code!r}")
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing, unexpected, errors)

    def note_clamped(self, clamped: torch.Tensor) -> None:
        """Add a clamp count from :meth:`write_read` to :attr:`clip_events` (and log it). One host sync; skipped
        under ``torch.vmap``/``torch.func``/``torch.compile`` and with value checks off."""
        if self.memory_clip is not None and value_checks_active(clamped):
            self._note_clamped(int(clamped))

    def _note_clamped(self, n: int) -> None:
        if not n:
            return
        self.clip_events += n
        self._clip_warnings += 1
        if self._clip_warnings <= 10 or self._clip_warnings % 1000 == 0:
            logger.warning(
                "DNCMemory: clamped %d memory entries to |M| <= %g (total clamped entries: %d, warning %d; only the "
                "first 10 and every 1000th are logged)",
                n,
                self.memory_clip,
                self.clip_events,
                self._clip_warnings,
            )

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Alias of :meth:`step`."""
        return self.step(x, memory)

    def initial_memory(self, batch_shape: tuple[int, ...] = (), **kwargs) -> torch.Tensor:
        """Zero memory ``[*batch_shape, N, W]`` (``kwargs`` go to ``torch.zeros``: dtype, device)."""
        return torch.zeros(*batch_shape, *self.memory_shape, **kwargs)


def _as_key(key: NestedKey) -> tuple[str, ...]:
    key = unravel_key(key)
    return key if isinstance(key, tuple) else (key,)


class DNCModule(TensorDictModuleBase):
    """TensorDict wrapper of :class:`DNCMemory` following TorchRL's ``LSTMModule`` stateful pattern.

    Reads ``in_key [*B, D_in]``, the stored memory ``memory_key [*B, N, W]`` (state *before* the step) and
    ``is_init_key`` (bool ``[*B, 1]`` as written by ``InitTracker``, or ``[*B]``); writes
    ``out_key [*B, D_out]`` (``e_aug``) and ``("next", *memory_key) [*B, N, W]`` (state *after* the step), which
    ``step_mdp`` moves back to the root for the next step.

    Modes (see :func:`torchrl.modules.set_recurrent_mode`; every ``LossModule.forward`` enables it):

    - step mode (default): every leading dim is batch; the memory is zeroed where ``is_init`` is True, then one
      step is taken.
    - recurrent mode: the tensordict has batch ``[*B, T]`` with at least two batch dims (time = last batch dim;
      a 1-D tensordict raises ``ValueError``, since a flattened shuffled minibatch looks the same). Starting from
      ``memory[..., 0, :, :]`` the module loops over ``T``, zeroing the running memory wherever ``is_init[..., t]``
      is True, and writes ``out_key`` and ``("next", *memory_key)`` for every ``t``. Gradients flow through time.

    Both modes are free of host syncs under ``torch.vmap`` (TorchRL's ``GAE(value_network=...)`` default) and
    ``torch.compile``; in eager mode a NaN/Inf in ``in_key`` raises ``ValueError`` and memory clamps are counted.

    ``make_tensordict_primer()`` declares the memory to the environment (``TransformedEnv(env,
    Compose(InitTracker(), module.make_tensordict_primer()))``, or ``Collector(...,
    auto_register_policy_transforms=True)``).

    Args:
        input_dim, memory_slots, memory_width, output_dim: see :class:`DNCMemory`.
        in_key: input key (default ``"fused"``).
        out_key: output key (default ``"hidden"``).
        memory_key: memory state key (default ``("dnc", "memory")``).
        is_init_key: episode-start marker (default ``"is_init"``).
        default_recurrent_mode: mode used when no ``set_recurrent_mode`` context is active (default step mode).
        memory_clip, write, output_norm: see :class:`DNCMemory`.
        compile: run the per-step memory update of recurrent mode (the training loop over ``T``) through
            ``torch.compile`` (:class:`~freamer_rl.layers.compiled.CompileOrEager`: a failed compilation warns,
            is counted in ``compile_fallbacks`` and runs eagerly). Same maths; about 2x faster forward and backward
            on CPU for ``[32, 16]`` sequences; step mode (collection, the value pass) is compiled with dynamic
            shapes (its batch sizes vary), about 2-3x faster. Under ``torch.vmap``/``torch.func`` it runs eagerly.
    """

    def __init__(
        self,
        input_dim: int,
        memory_slots: int = 32,
        memory_width: int = 64,
        output_dim: int | None = None,
        *,
        in_key: NestedKey = "fused",
        out_key: NestedKey = "hidden",
        memory_key: NestedKey = ("dnc", "memory"),
        is_init_key: NestedKey = "is_init",
        default_recurrent_mode: bool | None = None,
        memory_clip: float | None = 10.0,
        write: str = "additive",
        output_norm: bool = False,
        compile: bool = False,
    ) -> None:
        super().__init__()
        self.dnc = DNCMemory(
            input_dim,
            memory_slots,
            memory_width,
            output_dim,
            memory_clip=memory_clip,
            write=write,
            output_norm=output_norm,
        )
        # plain attributes (not Modules): the state dict and parameters stay those of ``self.dnc``. Recurrent mode
        # sees one minibatch shape (static); step mode sees 16 envs, the 2048-step value pass, varying subsets.
        self._sequence_step = (
            CompileOrEager(self.dnc.write_read, "DNCModule recurrent step", dynamic=False) if compile else None
        )
        self._compiled_step = CompileOrEager(self._step, "DNCModule step", dynamic=True) if compile else None
        self.in_key = unravel_key(in_key)
        self.out_key = unravel_key(out_key)
        self.memory_key = unravel_key(memory_key)
        self.is_init_key = unravel_key(is_init_key)
        self.next_memory_key = ("next", *_as_key(self.memory_key))
        self.in_keys = [self.in_key, self.memory_key, self.is_init_key]
        self.out_keys = [self.out_key, self.next_memory_key]
        self._recurrent_mode = default_recurrent_mode

    @property
    def compile_fallbacks(self) -> int:
        """How often ``compile=True`` fell back to eager execution (0 to 2: step mode, recurrent mode)."""
        return sum(f.fallbacks for f in (self._sequence_step, self._compiled_step) if f is not None)

    @property
    def recurrent_mode(self) -> bool:
        """``torchrl.modules.recurrent_mode()`` if a context set it, else ``default_recurrent_mode``."""
        rm = recurrent_mode()
        if rm is None:
            return bool(self._recurrent_mode)
        return bool(rm)

    def make_tensordict_primer(self):
        """A ``TensorDictPrimer`` declaring ``memory_key`` as ``Unbounded([N, W])`` float32 (zeros at reset).

        ``expand_specs=True`` lets the primer follow the env's batch size (as ``LSTMModule`` does).
        """
        return TensorDictPrimer(
            {self.memory_key: Unbounded(shape=self.dnc.memory_shape, dtype=torch.float32)},
            expand_specs=True,
        )

    def _get_inputs(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        keys = tensordict.keys(include_nested=True)
        if self.in_key not in keys:
            raise KeyError(f"DNCModule: input key {self.in_key!r} is missing from the tensordict")
        if self.memory_key not in keys:
            raise KeyError(
                f"DNCModule: memory key {self.memory_key!r} is missing from the tensordict. The environment must "
                "declare the DNC state: append `module.make_tensordict_primer()` to the env (e.g. "
                "TransformedEnv(env, Compose(InitTracker(), module.make_tensordict_primer()))), or build the "
                "collector with `Collector(..., auto_register_policy_transforms=True)`, which adds it."
            )
        if self.is_init_key not in keys:
            raise KeyError(
                f"DNCModule: episode-start key {self.is_init_key!r} is missing from the tensordict; add "
                "torchrl.envs.InitTracker() to the environment so memory is reset at episode boundaries."
            )
        x = tensordict.get(self.in_key)
        memory = tensordict.get(self.memory_key)
        is_init = tensordict.get(self.is_init_key)
        lead = x.shape[:-1]
        if is_init.shape == (*lead, 1):
            is_init = is_init.squeeze(-1)
        if is_init.shape != lead:
            raise ValueError(
                f"DNCModule: {self.is_init_key!r} must have shape [*B, 1] or [*B] with *B={tuple(lead)} (the batch "
                f"dims of {self.in_key!r} {tuple(x.shape)}); got {tuple(is_init.shape)}"
            )
        if tuple(memory.shape) != (*lead, *self.dnc.memory_shape):
            raise ValueError(
                f"DNCModule: {self.memory_key!r} must have shape {(*lead, *self.dnc.memory_shape)}; "
                f"got {tuple(memory.shape)}"
            )
        return x, memory, is_init.to(torch.bool)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Run one step (step mode) or a ``[*B, T]`` sequence (recurrent mode); writes ``out_key`` and
        ``("next", *memory_key)`` into ``tensordict`` and returns it."""
        x, memory, is_init = self._get_inputs(tensordict)
        if not self.recurrent_mode:
            check_finite(x, f"DNCModule {self.in_key!r}")
            eager = self._compiled_step is None or is_transformed(x, memory)  # vmap/grad: no compiled code inside
            out, new_memory, clamped = (self._step if eager else self._compiled_step)(x, memory, is_init)
            self.dnc.note_clamped(clamped)
        else:
            out, new_memory = self._forward_sequence(tensordict, x, memory, is_init)
        tensordict.set(self.out_key, out)
        tensordict.set(self.next_memory_key, new_memory)
        return tensordict

    def _step(
        self, x: torch.Tensor, memory: torch.Tensor, is_init: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Step mode on plain tensors (compiled with ``compile=True``): ``x [*B, D_in]``, ``memory [*B, N, W]``,
        ``is_init [*B]`` -> ``(e_aug [*B, D_out], M' [*B, N, W], clamped)``; the memory is zeroed where
        ``is_init``. The caller counts the clamps (outside compiled code)."""
        memory = torch.where(is_init[..., None, None], torch.zeros_like(memory), memory)
        r, new_memory, clamped = self.dnc.write_read(self.dnc.interface_vectors(x), memory)
        return self.dnc.output(x, r), new_memory, clamped

    def _forward_sequence(
        self, tensordict: TensorDictBase, x: torch.Tensor, memory: torch.Tensor, is_init: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Recurrent mode: ``x [*B, T, D_in]``, ``memory [*B, T, N, W]`` (only ``t = 0`` is read), ``is_init [*B, T]``
        -> ``(e_aug [*B, T, D_out], M' [*B, T, N, W])``, looping over ``T`` from the stored state at ``t = 0``."""
        if tensordict.batch_dims < 2:
            # A 1-D batch is either one trajectory or a flattened (often shuffled) minibatch of unrelated steps;
            # threading memory through the latter is silently wrong, so refuse to guess.
            raise ValueError(
                f"DNCModule in recurrent mode needs [B, T] sequences (time = last batch dim); got a tensordict with "
                f"batch size {tuple(tensordict.batch_size)}: a 1-D batch cannot be told apart from shuffled steps. "
                "Sample whole sequences (e.g. freamer_rl.run.sequences.split_sequences(data, seq_len), or a TorchRL "
                "replay buffer with a SliceSampler; README section 'Sequences for stateful layers'), or call it on "
                "td.unsqueeze(0) for one trajectory"
            )
        tdim = tensordict.batch_dims - 1
        if x.shape[:-1] != tensordict.batch_size:
            raise ValueError(
                f"DNCModule in recurrent mode expects {self.in_key!r} of shape [*B, T, D_in] with [*B, T] the "
                f"tensordict batch size {tuple(tensordict.batch_size)}; got {tuple(x.shape)}"
            )
        check_finite(x, f"DNCModule {self.in_key!r}")
        m = memory.select(tdim, 0)
        # Interface vectors and outputs do not depend on the memory: compute them for all T at once and
        # loop over time only for addressing, write and read.
        controls = self.dnc.interface_vectors(x)
        eager = self._sequence_step is None or is_transformed(x, m)
        step = self.dnc.write_read if eager else self._sequence_step
        reads, mems, clamped = [], [], []
        for t in range(x.shape[tdim]):
            # the reset stays outside the compiled step: inside it, forward + backward measured ~30% slower
            reset = is_init.select(tdim, t)[..., None, None]
            m = torch.where(reset, torch.zeros_like(m), m)
            r, m, n = step({k: v.select(tdim, t) for k, v in controls.items()}, m)
            reads.append(r)
            mems.append(m)
            clamped.append(n)
        out = self.dnc.output(x, torch.stack(reads, dim=tdim))
        self.dnc.note_clamped(torch.stack(clamped).sum())  # one host sync per sequence, not one per step
        return out, torch.stack(mems, dim=tdim)
