"""Auxiliary terms of the FreamerV1 objective (Eq. 6): L = L_PPO + l_FM L_FM + l_CL L_CL + l_s L_smooth.

:class:`FreamerAuxLoss` reads the intermediate keys that one trunk pass wrote into a minibatch tensordict
(``("embed", m)``, ``"modal_stack"`` and ``"fused_modalities"``) so no encoder is computed twice.

Where the smoothness gradient goes. Eq. A16 penalises ``sum_m ||E[m] - E[m+1]||^2`` on the fuser's output rows. Taken
literally (``smooth_fuser=None``) its gradient also flows into every encoder and refiner and pulls each modality's
embedding towards its neighbours'. When some modalities are constant over an episode (MiniGrid's mission and the
all-zero reward history of a sparse-reward task) this pulls the state embedding towards a constant: on
MultiRoom-N2-S4 the weighted term was ~0.1 against a PPO objective of ~0.005, so Adam spent the encoder's step
size on collapsing it (seeds 1 and 2: 5 % and 68 % success after ~2,100-2,400 episodes; with the term scoped to the
fuser both reached 95 % in ~1,500). The paper assigns the term to Layer 3 ("L_smooth and the FNO parameters govern
cross-modal fusion"), so by default we recompute the fuser on the detached stack ``E`` (``smooth_fuser`` given): the
term then trains only the fuser's own parameters. The recomputation costs one extra fuser pass (M x d, negligible).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from torch import nn

from freamer_rl.layers.fno import smoothness_loss


def info_nce(a: torch.Tensor, b: torch.Tensor, temperature: float = 0.1) -> torch.Tensor:
    """Symmetric InfoNCE between paired rows of ``a`` and ``b`` (``[*B, d]``, batch flattened): CLIP's loss."""
    a = F.normalize(a.reshape(-1, a.shape[-1]), dim=-1)
    b = F.normalize(b.reshape(-1, b.shape[-1]), dim=-1)
    logits = a @ b.T / temperature
    labels = torch.arange(a.shape[0], device=a.device)
    return 0.5 * (F.cross_entropy(logits, labels) + F.cross_entropy(logits.T, labels))


class FreamerAuxLoss(nn.Module):
    """Flow-matching (Eq. A13), vision-language contrastive and FNO smoothness (Eq. A16) losses.

    Args:
        refiners: the per-modality :class:`~freamer_rl.layers.flow_matching.FlowMatchingRefiner` modules.
        lambda_fm, lambda_cl, lambda_smooth: weights of Eq. 6. A zero weight skips the term.
        noise_std: perturbation scale of the denoising CFM pairs.
        smooth_fuser: the :class:`~freamer_rl.layers.fno.FNOFuser`. Given, ``L_smooth`` is computed on
            ``smooth_fuser(E.detach())`` (E read from ``modal_stack_key``) and trains only the fuser; ``None``: on the
            ``fused_modalities_key`` rows of the trunk pass, so the gradient reaches encoders and refiners too.
    Returns (forward): a TensorDict with weighted ``loss_fm``, ``loss_cl``, ``loss_smooth`` (scalars, summed into
    the objective by the caller) and unweighted per-modality diagnostics ``fm_<modality>``.
    """

    def __init__(
        self,
        refiners: nn.ModuleDict,
        *,
        lambda_fm: float = 0.1,
        lambda_cl: float = 0.1,
        lambda_smooth: float = 1e-3,
        noise_std: float = 1.0,
        temperature: float = 0.1,
        smooth_fuser: nn.Module | None = None,
        embed_key: str = "embed",
        modal_stack_key: str = "modal_stack",
        fused_modalities_key: str = "fused_modalities",
    ) -> None:
        super().__init__()
        self.refiners = refiners
        self.lambda_fm = lambda_fm
        self.lambda_cl = lambda_cl
        self.lambda_smooth = lambda_smooth
        self.noise_std = noise_std
        self.temperature = temperature
        self.smooth_fuser = smooth_fuser
        self.embed_key = embed_key
        self.modal_stack_key = modal_stack_key
        self.fused_modalities_key = fused_modalities_key

    def forward(self, td: TensorDictBase) -> TensorDict:
        out: dict[str, torch.Tensor] = {}
        zero = torch.zeros((), device=td.device)
        if self.lambda_fm:
            per_mod = {m: r.cfm_loss(td.get((self.embed_key, m)), noise_std=self.noise_std) for m, r in self.refiners.items()}
            for m, v in per_mod.items():
                out[f"fm_{m}"] = v.detach()
            out["loss_fm"] = self.lambda_fm * torch.stack(list(per_mod.values())).mean()
        if self.lambda_cl and "vision" in self.refiners and "language" in self.refiners:
            v = td.get((self.embed_key, "vision"))
            l = td.get((self.embed_key, "language"))
            out["loss_cl"] = self.lambda_cl * info_nce(v, l, self.temperature) if v.numel() // v.shape[-1] > 1 else zero
        if self.lambda_smooth:
            if self.smooth_fuser is not None:
                rows = self.smooth_fuser(td.get(self.modal_stack_key).detach())[1]
            else:
                rows = td.get(self.fused_modalities_key)
            out["loss_smooth"] = self.lambda_smooth * smoothness_loss(rows)
        return TensorDict(out, batch_size=[])
