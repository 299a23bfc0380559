"""Layer 2: per-modality Flow Matching refinement (paper Section 3.3, Eq. 1-3; Appendix D.1, Eq. A12-A13).

Each modality embedding ``e`` (shape ``[*B, d]``) is refined by Euler-integrating a learned velocity field
``v_theta(x, t)`` from ``t = 0`` to ``t = 1`` starting at the encoder output, then mixed back through a learnable
residual gate:

    x_0 = e                                                   (Eq. 1)
    x_{i+1} = x_i + (1/N) v_theta(x_i, i/N),  i = 0..N-1      (Eq. 2)
    e_hat = e + sigmoid(alpha) * (x_N - e)                     (Eq. 3)

Training objective (Eq. A13) -- *denoising* conditional flow matching with paired endpoints
------------------------------------------------------------------------------------------
The paper writes ``L_CFM = E_{t,z,x_0} ||v_theta(x_t, t) - (z - x_0)||^2`` without fixing the coupling. We use the
following exact formulation (see :meth:`FlowMatchingRefiner.cfm_loss`):

    x_1 = stopgrad(e)                       clean target (detached: the loss trains only the velocity field,
                                             never the encoder that produced ``e``)
    x_0 = x_1 + noise_std * eps,  eps ~ N(0, I)      paired noisy start point
    t ~ U[0, 1]                              one draw per sample (per element of ``*B``)
    x_t = t * x_1 + (1 - t) * x_0            straight-line interpolant (:func:`cfm_interpolant`)
    u   = x_1 - x_0  (= -noise_std * eps)    conditional target velocity
    L   = mean_{*B} [ (1/d) * sum_j (v_theta(x_t, t)_j - u_j)^2 ]

i.e. the squared error is **averaged** over the embedding dimension (and the batch), which keeps the loss O(1)
independent of ``d`` (``noise_std**2`` for a zero velocity field) so that ``lambda_FM`` in Eq. 6 is comparable
across embedding sizes. Multiply by ``d`` to get the summed-over-dim norm of Eq. A13.

Why this coupling: at inference the refinement starts from the encoder output itself (``x_0 = e``, Eq. 1), not
from pure noise. The flow therefore has to map a *perturbed* embedding back onto the manifold of clean
embeddings, which is exactly what training on (noisy, clean) pairs ``(x_1 + sigma*eps, x_1)`` teaches: the optimal
field is ``v*(x, t) = E[x_1 - x_0 | x_t = x]``, whose flow transports the noisy distribution onto the clean one.
We use plain (independent-pair) CFM rather than OT-CFM: OT-CFM re-samples the (x_0, x_1) coupling through a
mini-batch optimal-transport plan, which would re-pair a noisy point with a *different* sample's clean embedding
and destroy the denoising target.

Score-based adaptive complexity (Appendix G.4, optional: ``adaptive_steps``)
---------------------------------------------------------------------------
"Complexity = E_t[||s_theta(x, t, c)||^2] determines the number of FM steps via Gumbel-Softmax selection from
{1, 2, 3, 5, 7, 10}". The velocity field plays the role of the score ``s_theta``; per row (see
:meth:`FlowMatchingRefiner.complexity` and :meth:`FlowMatchingRefiner.step_selection`)

    c(x)   = (1/3) sum_{t in {1/4, 1/2, 3/4}} ||v_theta(x, t)||^2 / d       (detached: a difficulty feature)
    logits = Linear(1 -> K)(log(c(x) + 1e-6))                             K = len(choices)
    y      = onehot(argmax(logits + g)) + p - stopgrad(p),  p = softmax((logits + g) / tau)
    x_N    = sum_k y_k * Euler(x, n_k)                                    (Eq. 2 with n_k steps)

``y`` is a hard one-hot in the forward pass (every row takes exactly one step count) with the straight-through
Gumbel-Softmax gradient. The Gumbel noise ``g`` is drawn only in train mode (``module.training``); in eval mode
``g = 0`` and the choice is the deterministic argmax. The PPO trainer keeps the policy in eval mode for both
collection and update, so the step count chosen at collection is the one recomputed at the update and the stored
log-probabilities match. All K integrations are computed for every row and mixed by ``y`` (no host syncs and no
Python branches on values: ``torch.vmap``/``torch.compile`` keep working), so the cost is that of
``sum(choices) + 3`` velocity evaluations.

Score-based reliability (optional: ``reliability``; issue "filter before mixing", not in the paper)
--------------------------------------------------------------------------------------------------
Trained as above, the velocity field is ``E[x_1 - x_0 | x_t]``: small where ``x`` lies on the manifold of the
embeddings it was trained on, large off it. Its score ``c(e)`` at the encoder output therefore says how unusual an
embedding is, per row and at test time. With ``reliability`` on, the refiner keeps running statistics (EMA mean and
variance, buffer ``score_stats = [count, mean, var]``) of ``log c(e)`` over the clean targets of every
:meth:`FlowMatchingRefiner.cfm_loss` call (the training embeddings) and standardises the score,
``z = (log c(e) - mean) / std`` (0 before any statistics exist), then

    gate:    e_hat = e + sigmoid(alpha + softplus(beta) z) (x_N - e)     the filter opens on unusual inputs
    weight:  e_hat <- w e_hat,  w = exp(-relu(z - margin))               an unusual modality weighs less in the mix

(``both``: the two together). ``beta`` is learned (``softplus(beta) = 1`` at initialisation); the weight has no
parameters, so it reacts at test time to a corruption training never showed.

Paired targets (``paired_loss``; ``model.flow.targets=paired``, not in the paper)
---------------------------------------------------------------------------------
Trained on synthetic pairs alone the flow learns to undo isotropic Gaussian noise of one fixed size, which is not
what a corrupted sensor does to an embedding (issue 20 measured ~20-30% of the noise removed with the gate open and
~1% through the trained gate). Where a run corrupts an observation itself it also holds the clean value, so the
refiner can be trained on the pair it will meet: ``x_0`` the embedding of the corrupted observation, ``x_1`` that of
the clean copy, the same straight-line CFM term, plus ``||e_hat(x_0) - x_1||^2``, so that the residual gate learns
how much of the flow to let through (it is otherwise trained only by the policy loss and stays where it started).

Noise scale (``cfm_loss(..., relative=True)``): ``x_0 = x_1 + noise_std * std_row(x_1) * eps``, the perturbation
measured in each row's own std across its ``d`` entries (the scale of the paper's Table 13 protocol), so a modality
with small embeddings is not trained on noise ten times its own size.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from freamer_rl.layers.checks import check_finite, is_transformed
from freamer_rl.layers.dedup import dedup_rows

__all__ = ["FlowMatchingRefiner", "RELIABILITY_MODES", "cfm_interpolant"]

#: ``reliability`` choices of :class:`FlowMatchingRefiner` (see the module docstring)
RELIABILITY_MODES = ("off", "gate", "weight", "both")
#: EMA rate of the score statistics (the first update sets them)
SCORE_STATS_RATE = 0.05

#: Times at which the complexity E_t ||v_theta(x, t)||^2 / d is evaluated (Appendix G.4).
COMPLEXITY_TIMES = (0.25, 0.5, 0.75)


def _time_column(t: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Broadcast a time value to a column ``[*B, 1]`` matching ``like`` of shape ``[*B, d]``."""
    batch_shape = like.shape[:-1]
    if not isinstance(t, torch.Tensor):
        t = torch.tensor(float(t), dtype=like.dtype, device=like.device)
    t = t.to(dtype=like.dtype, device=like.device)
    if t.ndim == like.ndim - 1 and t.shape == batch_shape:
        t = t.unsqueeze(-1)
    elif t.ndim == 0:
        t = t.reshape((1,) * like.ndim)
    elif not (t.ndim == like.ndim and t.shape[-1] == 1):
        raise ValueError(
            f"t must be a float, a scalar tensor, or a tensor of shape [*B] or [*B, 1] with *B={tuple(batch_shape)}; "
            f"got shape {tuple(t.shape)}"
        )
    return t.expand(*batch_shape, 1)


def cfm_interpolant(x0: torch.Tensor, x1: torch.Tensor, t: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Straight-line conditional path and its velocity (Eq. A13's ``x_t`` and ``z - x_0``).

    Args:
        x0: start points ``[*B, d]`` (noisy embeddings).
        x1: end points ``[*B, d]`` (clean embeddings), paired element-wise with ``x0``.
        t: time in ``[0, 1]``: a float, or a tensor ``[*B]`` / ``[*B, 1]``.

    Returns:
        ``(x_t, u)`` with ``x_t = t * x1 + (1 - t) * x0`` and ``u = x1 - x0``, both ``[*B, d]``.
    """
    if x0.shape != x1.shape:
        raise ValueError(f"x0 and x1 must have the same shape; got x0 {tuple(x0.shape)} and x1 {tuple(x1.shape)}")
    tc = _time_column(t, x0)
    x_t = tc * x1 + (1.0 - tc) * x0
    return x_t, x1 - x0


class FlowMatchingRefiner(nn.Module):
    """Per-modality Flow Matching refiner ``phi^m`` (Section 3.3, Eq. 1-3; loss Eq. A13).

    Args:
        dim: embedding size ``d``.
        hidden: width of the velocity MLP (Table A20: 128).
        steps: number of Euler steps ``N`` (Table A20: 4).
        gate_init: initial value of the gate logit ``alpha`` (Table A20: -3.0, ``sigmoid(-3) ~ 0.047``).
        num_hidden_layers: hidden layers of the velocity MLP (default 2).
        last_layer_scale: the last velocity layer's default init is multiplied by this factor (bias zeroed), so
            ``v ~ 0`` and the refiner is near identity at initialisation.
        deduplicate: in eager mode, integrate each distinct input row once when at least half the rows repeat
            (a constant mission or an all-zero reward history; :mod:`freamer_rl.layers.dedup`). Same maths.
        adaptive_steps: step-count choices ``n_k`` for the score-based adaptive complexity (Appendix G.4, e.g.
            ``(1, 2, 3, 5, 7, 10)``); ``None`` or empty: off (always ``steps``; no selector, same state_dict).
        tau: Gumbel-Softmax temperature of the straight-through gradient (the forward choice is hard).
        reliability: ``off`` | ``gate`` | ``weight`` | ``both``: the score-based input gate and/or mixing weight
            (module docstring). Off: no extra parameter or buffer (same state_dict as before).
        reliability_margin: ``margin`` of the weight, in standard deviations of the training scores.

    The velocity field is ``v_theta(x, t) = MLP([x; t])`` (time concatenated as an extra input, SiLU activations).
    The gate logit is the scalar parameter ``alpha`` (named so optimisers/OGM-GE can single it out).

    With ``adaptive_steps`` the module also has ``selector`` (``Linear(1, K)``: weight 0 and a +1 bias on the choice
    nearest ``steps`` at initialisation, so an untrained eval-mode refiner takes about ``steps`` steps) and two
    detached 0-d buffers for logging, written by every eager forward: ``last_steps`` (mean chosen step count)
    and ``expected_steps`` (mean of ``sum_k softmax(logits / tau)_k n_k``, without the Gumbel noise).

    Shapes:
        forward: ``e [*B, d] -> e_hat [*B, d]``.
    """

    def __init__(
        self,
        dim: int,
        hidden: int = 128,
        steps: int = 4,
        gate_init: float = -3.0,
        *,
        num_hidden_layers: int = 2,
        last_layer_scale: float = 1e-2,
        deduplicate: bool = True,
        adaptive_steps: Sequence[int] | None = None,
        tau: float = 1.0,
        reliability: str = "off",
        reliability_margin: float = 2.0,
    ) -> None:
        super().__init__()
        if dim <= 0 or hidden <= 0:
            raise ValueError(f"dim and hidden must be positive; got dim={dim}, hidden={hidden}")
        if steps < 1:
            raise ValueError(f"steps must be >= 1; got steps={steps}")
        if num_hidden_layers < 1:
            raise ValueError(f"num_hidden_layers must be >= 1; got {num_hidden_layers}")
        self.dim = dim
        self.steps = steps
        self.deduplicate = deduplicate
        layers: list[nn.Module] = []
        in_features = dim + 1
        for _ in range(num_hidden_layers):
            layers += [nn.Linear(in_features, hidden), nn.SiLU()]
            in_features = hidden
        last = nn.Linear(in_features, dim)
        with torch.no_grad():
            last.weight.mul_(last_layer_scale)
            last.bias.zero_()
        layers.append(last)
        self.net = nn.Sequential(*layers)
        self.alpha = nn.Parameter(torch.tensor(float(gate_init)))
        if not (math.isfinite(tau) and tau > 0):
            raise ValueError(f"tau must be a finite positive float; got {tau}")
        self.tau = float(tau)
        self.adaptive_steps: tuple[int, ...] | None = None
        self.selector: nn.Linear | None = None
        if adaptive_steps:
            self._init_adaptive(tuple(int(n) for n in adaptive_steps))
        if reliability not in RELIABILITY_MODES:
            raise ValueError(f"reliability must be one of {RELIABILITY_MODES}; got {reliability!r}")
        self.reliability = reliability
        self.reliability_margin = float(reliability_margin)
        if reliability != "off":
            self.register_buffer("score_stats", torch.tensor([0.0, 0.0, 1.0]))  # count, mean, var of log c(e)
        if reliability in ("gate", "both"):
            self.beta = nn.Parameter(torch.tensor(math.log(math.e - 1.0)))  # softplus(beta) = 1

    def _init_adaptive(self, choices: tuple[int, ...]) -> None:
        """Build the step selector and the logging buffers (Appendix G.4); see the class docstring."""
        if min(choices) < 1 or len(set(choices)) != len(choices):
            raise ValueError(f"adaptive_steps must be distinct integers >= 1; got {choices}")
        self.adaptive_steps = choices
        self.selector = nn.Linear(1, len(choices))
        nearest = min(range(len(choices)), key=lambda k: (abs(choices[k] - self.steps), choices[k]))
        with torch.no_grad():
            self.selector.weight.zero_()
            self.selector.bias.zero_()
            self.selector.bias[nearest] = 1.0
        self.register_buffer("choice_steps", torch.tensor(choices, dtype=torch.get_default_dtype()), persistent=False)
        self.register_buffer("last_steps", torch.zeros(()), persistent=False)
        self.register_buffer("expected_steps", torch.zeros(()), persistent=False)

    @property
    def gate(self) -> torch.Tensor:
        """Residual gate ``sigmoid(alpha)`` (Eq. 3), a 0-d tensor (differentiable)."""
        return torch.sigmoid(self.alpha)

    def velocity(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """Velocity field ``v_theta(x, t)``.

        Args:
            x: ``[*B, d]``.
            t: float, 0-d tensor, or ``[*B]`` / ``[*B, 1]`` tensor of times in ``[0, 1]``.

        Returns:
            ``[*B, d]``.
        """
        if x.shape[-1] != self.dim:
            raise ValueError(f"x must have last dim {self.dim} (the refiner's dim); got shape {tuple(x.shape)}")
        first = self.net[0]
        if isinstance(first, nn.Linear) and not isinstance(t, torch.Tensor):
            # Same maths as net(cat[x, t]) for a scalar time (every Euler step): fold t into the first bias,
            # W [x; t] + b = W_x x + (b + t W_t), which saves building and concatenating a time column.
            bias = first.weight[:, self.dim] * float(t)
            if first.bias is not None:
                bias = bias + first.bias
            h = F.linear(x, first.weight[:, : self.dim], bias)
            for layer in list(self.net)[1:]:  # not self.net[1:]: that builds a new Sequential on every call
                h = layer(h)
            return h
        return self.net(torch.cat([x, _time_column(t, x)], dim=-1))

    def integrate(self, e: torch.Tensor, steps: int | None = None) -> torch.Tensor:
        """Euler-integrate the flow from ``x_0 = e`` for ``steps`` steps (Eq. 1-2); returns ``x_N [*B, d]``."""
        n = self.steps if steps is None else int(steps)
        if n < 1:
            raise ValueError(f"steps must be >= 1; got {n}")
        x = e
        for i in range(n):
            x = x + self.velocity(x, i / n) / n
        return x

    def complexity(self, x: torch.Tensor) -> torch.Tensor:
        """Score-based complexity (Appendix G.4) ``c(x) = mean_t ||v_theta(x, t)||^2 / d`` over
        :data:`COMPLEXITY_TIMES`, per row: ``x [*B, d] -> [*B]``. Computed without gradients (a feature of the
        step selector, not a quantity to optimise)."""
        with torch.no_grad():
            return torch.stack([self.velocity(x, t).pow(2).mean(-1) for t in COMPLEXITY_TIMES]).mean(0)

    def step_selection(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Straight-through Gumbel-Softmax choice of the step count per row (Appendix G.4).

        Args:
            x: ``[*B, d]`` flow start points (the embeddings).

        Returns:
            ``(y, probs)``, both ``[*B, K]``: ``y`` is an exact one-hot in the forward pass with the gradient of
            ``softmax((logits + g) / tau)`` (``g`` Gumbel noise in train mode only, 0 in eval mode); ``probs =
            softmax(logits / tau)`` (noise-free, for logging).

        Train mode draws random numbers: under ``torch.vmap`` it needs ``randomness="different"`` (eval mode does
        not draw, so TorchRL's default vmap works).
        """
        if self.selector is None:
            raise RuntimeError("step_selection needs a refiner built with adaptive_steps")
        logits = self.selector(torch.log(self.complexity(x) + 1e-6).unsqueeze(-1))
        noisy = logits
        if self.training:  # Gumbel(0, 1) = -log(Exp(1)); eval mode: deterministic argmax
            noisy = logits - torch.empty_like(logits).exponential_().clamp_min(1e-20).log()
        soft = torch.softmax(noisy / self.tau, dim=-1)
        index = noisy.argmax(dim=-1, keepdim=True)
        hard = (torch.arange(logits.shape[-1], device=logits.device) == index).to(soft.dtype)
        return hard + (soft - soft.detach()), torch.softmax(logits.detach() / self.tau, dim=-1)

    def score_z(self, e: torch.Tensor) -> torch.Tensor:
        """Standardised score ``z = (log c(e) - mean) / std`` against the training statistics: ``e [*B, d] -> [*B]``
        (0 while no statistics exist). Needs ``reliability`` on."""
        log_c = torch.log(self.complexity(e) + 1e-8)
        count, mean, var = self.score_stats.unbind()
        z = (log_c - mean) / var.clamp_min(1e-6).sqrt()
        return torch.where(count > 0, z, torch.zeros_like(z))

    def _observe_scores(self, e: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """EMA update of ``score_stats`` from the training embeddings ``e [*B, d]``, only the rows where ``mask
        [*B]`` is 1 if given (in place, no host sync; a batch without such rows leaves them as they were; skipped
        under ``torch.vmap``/``torch.func`` as :meth:`_record_steps` is)."""
        rows = e.detach().reshape(-1, self.dim)
        if rows.shape[0] == 0:
            return
        log_c = torch.log(self.complexity(rows) + 1e-8)
        if is_transformed(log_c) and not torch.compiler.is_compiling():
            return
        w = torch.ones_like(log_c) if mask is None else mask.detach().reshape(-1).to(log_c.dtype)
        with torch.no_grad():
            count, mean, var = self.score_stats.unbind()
            rate = torch.where(count > 0, torch.full_like(count, SCORE_STATS_RATE), torch.ones_like(count))
            rate = torch.where(w.sum() > 0, rate, torch.zeros_like(rate))  # nothing observed: keep the statistics
            n = w.sum().clamp_min(1.0)
            b_mean = (w * log_c).sum() / n
            b_var = (w * (log_c - b_mean) ** 2).sum() / n
            delta = b_mean - mean
            new_var = (1 - rate) * (var + rate * delta**2) + rate * b_var
            observed = (w.sum() > 0).to(count.dtype)
            self.score_stats.copy_(torch.stack([count + observed, mean + rate * delta, new_var]))

    def reliability_terms(self, e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(gate [*B, 1], weight [*B, 1])`` for ``e [*B, d]``: the residual gate of Eq. 3 (input-dependent with
        ``reliability`` gate/both) and the mixing weight (1 unless weight/both)."""
        gate_logit = self.alpha.to(e.dtype).expand(e.shape[:-1]).unsqueeze(-1)
        weight = torch.ones_like(gate_logit)
        if self.reliability == "off":
            return torch.sigmoid(gate_logit), weight
        z = self.score_z(e).unsqueeze(-1).to(e.dtype)
        if self.reliability in ("gate", "both"):
            gate_logit = gate_logit + F.softplus(self.beta).to(e.dtype) * z
        if self.reliability in ("weight", "both"):
            weight = torch.exp(-torch.relu(z - self.reliability_margin))
        return torch.sigmoid(gate_logit), weight

    def _adaptive_integrate(self, e: torch.Tensor) -> torch.Tensor:
        """``[*B, d] -> [*B, d + 2]``: ``cat[x_N, n_chosen, n_expected]`` with ``x_N = sum_k y_k Euler(e, n_k)``.

        The two step-count columns travel with ``x_N`` so that :func:`dedup_rows` gathers them back per row.
        """
        y, probs = self.step_selection(e)
        x_n = sum(y[..., k : k + 1] * self.integrate(e, n) for k, n in enumerate(self.adaptive_steps))
        n = self.choice_steps.to(e.dtype)
        chosen = (y.detach() * n).sum(-1, keepdim=True)
        expected = (probs * n).sum(-1, keepdim=True)
        return torch.cat([x_n, chosen, expected], dim=-1)

    def _record_steps(self, counts: torch.Tensor) -> None:
        """Write the batch means of ``counts [*B, 2]`` (chosen, expected) into ``last_steps``/``expected_steps``.

        In-place copies (no ``.item()``, fine under ``torch.compile``); skipped under ``torch.vmap``/``torch.func``,
        whose per-sample values must not leak into the module.
        """
        if counts.numel() == 0:  # an empty batch chose nothing
            return
        means = counts.detach().reshape(-1, 2).mean(0)
        if is_transformed(means) and not torch.compiler.is_compiling():
            return
        with torch.no_grad():
            self.last_steps.copy_(means[0])
            self.expected_steps.copy_(means[1])

    def forward(self, e: torch.Tensor, steps: int | None = None) -> torch.Tensor:
        """Refine ``e [*B, d]`` into ``e_hat = e + sigmoid(alpha) (x_N - e)`` (Eq. 3), shape ``[*B, d]``.

        ``steps`` overrides the number of Euler steps for this call (and the adaptive choice, if any). With
        ``adaptive_steps`` and ``steps=None``, ``x_N`` is the per-row adaptive integration (Appendix G.4).
        A NaN/Inf in ``e`` raises ``ValueError`` in eager mode; under ``torch.vmap``/``torch.func``/``torch.compile``
        the forward is sync-free and the check is skipped (same maths; see :mod:`freamer_rl.layers.checks`).
        """
        if e.shape[-1] != self.dim:
            raise ValueError(f"e must have last dim {self.dim} (the refiner's dim); got shape {tuple(e.shape)}")
        check_finite(e, "FlowMatchingRefiner input")
        adaptive = self.adaptive_steps is not None and steps is None
        flow = self._adaptive_integrate if adaptive else (lambda rows: self.integrate(rows, steps))
        if self.deduplicate and e.ndim > 1:
            # duplicates share one selection (and, in train mode, one Gumbel draw)
            width = self.dim + 2 if adaptive else self.dim
            out = dedup_rows(flow, e.reshape(-1, self.dim)).reshape(*e.shape[:-1], width)
        else:
            out = flow(e)
        if adaptive:
            self._record_steps(out[..., self.dim :])
            out = out[..., : self.dim]
        if self.reliability == "off":
            return e + self.gate.to(e.dtype) * (out - e)
        gate, weight = self.reliability_terms(e)
        return weight * (e + gate * (out - e))

    def cfm_loss(
        self, e: torch.Tensor, noise_std: float = 1.0, *, relative: bool = False, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Denoising conditional flow matching loss (Eq. A13); see the module docstring for the exact formulation.
        With ``reliability`` on, the clean targets also update the score statistics.

        Args:
            e: encoder embeddings ``[*B, d]`` (detached inside: only the velocity field receives gradients).
            noise_std: std ``sigma`` of the Gaussian perturbation that defines the noisy start ``x_0``.
            relative: ``sigma`` in units of each row's own std across ``d`` (module docstring, "Noise scale").
            mask: ``[*B]`` (or ``[*B, 1]``) 1 for the rows to train on, 0 for rows to leave out (a dropped sensor's
                embedding, ``model.presence_keys``): the loss and the score statistics see only the kept rows.

        Returns:
            0-d tensor: ``mean over *B and d of (v_theta(x_t, t) - (x_1 - x_0))^2`` (over the kept rows; 0 if none).
        """
        if e.shape[-1] != self.dim:
            raise ValueError(f"e must have last dim {self.dim} (the refiner's dim); got shape {tuple(e.shape)}")
        if not math.isfinite(noise_std) or noise_std < 0:
            raise ValueError(f"noise_std must be a finite non-negative float; got {noise_std}")
        x1 = e.detach()
        if mask is not None:
            mask = mask.detach().reshape(x1.shape[:-1]).to(x1.dtype)
        if self.reliability != "off":
            self._observe_scores(x1, mask)
        scale = noise_std * x1.std(dim=-1, keepdim=True) if relative else noise_std
        x0 = x1 + scale * torch.randn_like(x1)
        t = torch.rand(x1.shape[:-1], dtype=x1.dtype, device=x1.device)
        x_t, u = cfm_interpolant(x0, x1, t)
        err = (self.velocity(x_t, t) - u).pow(2)
        if mask is None:
            return err.mean()
        return (err.mean(-1) * mask).sum() / mask.sum().clamp_min(1.0)

    def paired_loss(
        self, noisy: torch.Tensor, clean: torch.Tensor, *, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Denoising on observed pairs (``model.flow.targets=paired``; module docstring, "Paired targets").

        Args:
            noisy: embeddings of corrupted observations ``[*B, d]``.
            clean: embeddings of the same observations uncorrupted ``[*B, d]`` (both detached inside: neither
                encoder pass is trained here).
            mask: ``[*B]`` (or ``[*B, 1]``) 1 for the rows to train on, 0 for rows to leave out (a dropped sensor's
                embedding, ``model.presence_keys``: the fuser never sees it, so nothing should be learned from it).

        Returns:
            ``(loss, left)``, 0-d tensors: ``loss = CFM(noisy -> clean) + mean((e_hat(noisy) - clean)^2)``, the
            conditional flow matching term of Eq. A13 with ``x_0 = noisy``, ``x_1 = clean`` plus the refined output's
            error (which trains the gate, and the flow through its Euler steps); ``left`` (detached) is the share
            of the corruption the refined embedding still carries, ``sum ||e_hat - clean||^2 / sum ||noisy -
            clean||^2`` over the rows (1: nothing removed, 0: all of it; 0 when no row was corrupted). With
            ``mask``, both means and ``left`` run over the kept rows only (a loss of 0 when none is kept).
        """
        if noisy.shape != clean.shape or noisy.shape[-1] != self.dim:
            raise ValueError(
                f"noisy and clean must both be [*B, {self.dim}]; got {tuple(noisy.shape)} and {tuple(clean.shape)}"
            )
        x0, x1 = noisy.detach(), clean.detach()
        keep = torch.ones(x1.shape[:-1], dtype=x1.dtype, device=x1.device)
        if mask is not None:
            keep = mask.detach().reshape(x1.shape[:-1]).to(x1.dtype)
        kept = keep.sum().clamp_min(1.0)
        t = torch.rand(x1.shape[:-1], dtype=x1.dtype, device=x1.device)
        x_t, u = cfm_interpolant(x0, x1, t)
        flow_term = ((self.velocity(x_t, t) - u).pow(2).mean(-1) * keep).sum() / kept
        refined = self(x0)
        output_term = ((refined - x1).pow(2).mean(-1) * keep).sum() / kept
        with torch.no_grad():
            before = ((x0 - x1).pow(2).sum(-1) * keep).sum()
            after = ((refined - x1).pow(2).sum(-1) * keep).sum()
            left = torch.where(before > 0, after / before.clamp_min(1e-12), before)
        return flow_term + output_term, left

    def extra_repr(self) -> str:
        adaptive = f", adaptive_steps={self.adaptive_steps}, tau={self.tau}" if self.adaptive_steps else ""
        reliability = f", reliability={self.reliability}" if self.reliability != "off" else ""
        return f"dim={self.dim}, steps={self.steps}{adaptive}{reliability}"
