"""OGM-GE for the per-modality residual gates (paper Section 4.3.5 and Appendix K).

The paper: "we adopt OGM-GE (On-the-fly Gradient Modulation with Gradient Enhancement) [26], which dynamically
modulates the alpha gradients based on per-modality FM loss progress. Modalities with slower-converging FM receive
enhanced gradients (gate opens faster), while faster-converging modalities are suppressed (gate stays closed)."

Signal. OGM-GE as published compares per-modality classification confidences; RL has no labels, so the paper uses
"each modality's FM loss convergence rate" (Section 3.3). With ``L_m(s)`` the CFM loss (Eq. A13) of modality ``m``
at update step ``s`` (the trainer's detached ``fm_<m>``):

    ema_m   <- beta * ema_m + (1 - beta) * L_m(s)        (ema_m = L_m at the first observation; beta = ``ema``)
    c_m      = ema_m / first_m                           convergence ratio: lower = converged faster
    d_m      = mean_j(c_j) / c_m                         discrepancy: > 1 for modalities converging faster than the mean
    k_m      = 1 - tanh(alpha * relu(d_m - 1))           modulation coefficient (OGM-GE's rule; alpha = ``alpha``)

so the "dominant" modalities (faster than the mean) get ``k_m < 1`` (suppressed) and the others ``k_m = 1``. The
reference implementation feeds ``relu(rho)`` to ``tanh``; we use ``relu(d_m - 1)`` so that equal convergence gives
``k = 1`` for every modality (no modulation without a discrepancy).

Modes (Appendix K). "Mode A (alpha-only): Modulates only the alpha^m gradient with an amplified learning rate
(scale x lr_scale, where lr_scale = 10)". "Mode B (full-params): Modulates all FM parameters (velocity network +
alpha), matching the original OGM-GE paper [26]" (base learning rate). :meth:`OGMGE.param_groups` builds one
optimiser group per modality (``"name": "ogm_<m>"``) plus one group with every other parameter.

Applying the coefficient. OGM-GE scales the gradient (``g <- k g``) for SGD. Adam divides the step by the running
gradient RMS, so a constant gradient scale is normalised away; :meth:`OGMGE.modulate` therefore applies ``k_m`` to
the group's step size instead (``lr_group = lr * lr_scale * k_m``), the SGD-equivalent of the gradient scaling.
Gradient enhancement (GE): ``g <- g + N(0, sigma^2)`` with ``sigma`` the standard deviation of the unscaled gradient
of each parameter tensor (as the reference applies it per tensor). For a one-element tensor (the scalar gate logit
alpha) the unbiased std is NaN, so ``sigma = |g|`` there and the population std (``unbiased=False``) otherwise.

Usage (the trainer, once per minibatch)::

    ogm = OGMGE(modules.refiners, mode="A")
    optimizer = torch.optim.Adam(ogm.param_groups(lr, params), lr=lr)
    ...
    optimizer_step(loss, optimizer, params, max_grad_norm, before_step=lambda: ogm.modulate(optimizer, lr))
    ogm.observe({m: float(aux[f"fm_{m}"]) for m in modalities})
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from typing import Any

import torch
from torch import nn

logger = logging.getLogger(__name__)

__all__ = ["OGMGE"]

_EPS = 1e-12  # floor of a first loss / convergence ratio (a loss of exactly 0 must not divide by zero)


class OGMGE:
    """On-the-fly gradient modulation with gradient enhancement for the refiners' gates (Section 4.3.5, App. K).

    Args:
        refiners: ``{modality: FlowMatchingRefiner}`` (e.g. ``FreamerModules.refiners``); each has a scalar ``alpha``.
        mode: ``"A"`` (alpha only, ``lr * lr_scale``; the paper's choice) or ``"B"`` (all refiner parameters,
            base lr).
        alpha: modulation strength of ``k = 1 - tanh(alpha * relu(d - 1))`` (not the gate logit).
        lr_scale: Mode A learning-rate amplification of the gate logits (paper: 10).
        noise: add the GE noise ``N(0, sigma^2)`` to the modulated gradients.
        ema: decay ``beta`` of the FM-loss moving average.
    """

    def __init__(
        self,
        refiners: Mapping[str, nn.Module],
        *,
        mode: str = "A",
        alpha: float = 0.5,
        lr_scale: float = 10.0,
        noise: bool = True,
        ema: float = 0.9,
    ) -> None:
        if mode not in ("A", "B"):
            raise ValueError(f"mode must be 'A' (alpha only) or 'B' (all refiner parameters); got {mode!r}")
        if not (math.isfinite(alpha) and alpha >= 0):
            raise ValueError(f"alpha (modulation strength) must be a finite non-negative float; got {alpha}")
        if not (math.isfinite(lr_scale) and lr_scale > 0):
            raise ValueError(f"lr_scale must be a finite positive float; got {lr_scale}")
        if not 0.0 <= ema < 1.0:
            raise ValueError(f"ema must be in [0, 1); got {ema}")
        if not refiners:
            raise ValueError("OGMGE needs at least one refiner")
        self.refiners = dict(refiners)
        self.mode = mode
        self.alpha = float(alpha)
        self.lr_scale = float(lr_scale)
        self.noise = bool(noise)
        self.ema = float(ema)
        self.steps = 0
        self._ema: dict[str, float] = {}
        self._first: dict[str, float] = {}
        self._coeff: dict[str, float] = {m: 1.0 for m in self.refiners}

    # ------------------------------------------------------------------ optimiser groups
    def _modulated_params(self, refiner: nn.Module) -> list[nn.Parameter]:
        """Mode A: the gate logit ``alpha`` only; Mode B: every trainable parameter of the refiner."""
        if self.mode == "A":
            return [refiner.alpha] if refiner.alpha.requires_grad else []
        return [p for p in refiner.parameters() if p.requires_grad]

    def param_groups(self, base_lr: float, all_params: Iterable[torch.Tensor]) -> list[dict[str, Any]]:
        """Optimiser parameter groups: one per modality, then one with the rest of ``all_params``.

        Each group carries ``"name"`` (``"ogm_<m>"`` / ``"base"``), ``"lr_scale"`` (Mode A: ``lr_scale`` for the
        gate groups; otherwise 1) and ``"lr" = base_lr * lr_scale``; a modality group also carries
        ``"ogm_modality": m``. A schedule sets ``lr = scheduled_lr * lr_scale`` (and :meth:`modulate` times ``k_m``).
        Parameters listed twice are kept once; a group left empty is omitted.
        """
        group_scale = self.lr_scale if self.mode == "A" else 1.0
        claimed: set[int] = set()
        groups: list[dict[str, Any]] = []
        for m, refiner in self.refiners.items():
            params = [p for p in self._modulated_params(refiner) if id(p) not in claimed]
            claimed.update(id(p) for p in params)
            if params:
                groups.append(
                    {
                        "params": params,
                        "lr": base_lr * group_scale,
                        "lr_scale": group_scale,
                        "name": f"ogm_{m}",
                        "ogm_modality": m,
                    }
                )
        rest: list[torch.Tensor] = []
        for p in all_params:
            if id(p) not in claimed:
                claimed.add(id(p))
                rest.append(p)
        if rest:
            groups.append({"params": rest, "lr": base_lr, "lr_scale": 1.0, "name": "base"})
        return groups

    # ------------------------------------------------------------------ the modulation signal
    def observe(self, fm_losses: Mapping[str, float | torch.Tensor]) -> None:
        """Record one update step's FM losses ``{m: L_m}`` (floats or 0-d tensors; call once per update step).

        Updates the EMA (the first finite value of a modality also becomes its ``first_m``) and recomputes the
        coefficients ``k_m`` (module docstring). Unknown modalities and non-finite losses are ignored; a modality
        never observed keeps ``k_m = 1``.
        """
        self.steps += 1
        for m, value in fm_losses.items():
            if m not in self.refiners:
                continue
            loss = float(value)
            if not math.isfinite(loss):
                logger.debug("OGM-GE: non-finite FM loss %s for %s ignored", loss, m)
                continue
            if m not in self._ema:
                self._ema[m] = self._first[m] = loss
            else:
                self._ema[m] = self.ema * self._ema[m] + (1.0 - self.ema) * loss
        self._coeff = self._coefficients()

    def convergence(self) -> dict[str, float]:
        """Convergence ratios ``c_m = ema_m / first_m`` of the observed modalities (lower = converged faster)."""
        return {m: max(self._ema[m], 0.0) / max(self._first[m], _EPS) for m in self._ema}

    def _coefficients(self) -> dict[str, float]:
        """``k_m = 1 - tanh(alpha * relu(mean(c) / c_m - 1))`` for every refiner (1 where not observed)."""
        ratios = self.convergence()
        coeff = {m: 1.0 for m in self.refiners}
        if len(ratios) < 2:  # no discrepancy between modalities to act on
            return coeff
        mean_c = sum(ratios.values()) / len(ratios)
        for m, c in ratios.items():
            d = mean_c / max(c, _EPS)
            coeff[m] = 1.0 - math.tanh(self.alpha * max(d - 1.0, 0.0))
        return coeff

    def coefficients(self) -> dict[str, float]:
        """The current modulation coefficients ``{m: k_m}`` in ``[0, 1]``."""
        return dict(self._coeff)

    def metrics(self) -> dict[str, float]:
        """Scalars for the log: ``ogm_coeff_<m>`` (``k_m``) and ``ogm_conv_<m>`` (``c_m``, observed modalities)."""
        out = {f"ogm_coeff_{m}": k for m, k in self._coeff.items()}
        out.update({f"ogm_conv_{m}": c for m, c in self.convergence().items()})
        return out

    # ------------------------------------------------------------------ the optimiser side
    def modulate(self, optimizer: torch.optim.Optimizer, lr: float) -> None:
        """Set every group's step size and add the GE noise; call after backward/clipping, before ``step()``.

        For a modality group ``lr_group = lr * lr_scale_group * k_m`` (with Adam a plain gradient scale would be
        normalised away, so ``k_m`` acts on the step size: the SGD-equivalent of OGM's gradient scaling); every
        other group gets ``lr * lr_scale_group``. With ``noise=True`` each gradient ``g`` of a modality group
        receives ``N(0, sigma^2)``, ``sigma`` = population std of ``g`` (``|g|`` for a one-element ``g``); no host
        sync, never NaN for finite gradients.
        """
        for group in optimizer.param_groups:
            scale = float(group.get("lr_scale", 1.0))
            m = group.get("ogm_modality")
            if m is None:
                group["lr"] = lr * scale
                continue
            group["lr"] = lr * scale * self._coeff.get(m, 1.0)
            if self.noise:
                for p in group["params"]:
                    if p.grad is not None:
                        p.grad.add_(gradient_enhancement_noise(p.grad))

    # ------------------------------------------------------------------ resume
    def state_dict(self) -> dict[str, Any]:
        """Plain Python values (readable by ``torch.load(weights_only=True)``)."""
        return {"steps": self.steps, "ema": dict(self._ema), "first": dict(self._first)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.steps = int(state["steps"])
        self._ema = {str(m): float(v) for m, v in state["ema"].items()}
        self._first = {str(m): float(v) for m, v in state["first"].items()}
        self._coeff = self._coefficients()


def gradient_enhancement_noise(grad: torch.Tensor) -> torch.Tensor:
    """GE noise ``N(0, sigma^2)`` shaped like ``grad`` (any shape), ``sigma`` = population std of ``grad``.

    A one-element gradient (a scalar gate logit) has no spread, and ``grad.std()`` (unbiased) is NaN there: its
    ``sigma`` is ``|grad|`` instead. An empty gradient gets empty noise.
    """
    if grad.numel() == 0:
        return torch.zeros_like(grad)
    sigma = grad.abs() if grad.numel() == 1 else grad.std(unbiased=False)
    return torch.randn_like(grad) * sigma
