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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule

from freamer_rl.layers.fno import smoothness_loss
from freamer_rl.model.modalities import modality_keys


def info_nce(a: torch.Tensor, b: torch.Tensor, temperature: float = 0.1) -> torch.Tensor:
    """Symmetric InfoNCE between paired rows of ``a`` and ``b`` (``[*B, d]``, batch flattened): CLIP's loss."""
    a = F.normalize(a.reshape(-1, a.shape[-1]), dim=-1)
    b = F.normalize(b.reshape(-1, b.shape[-1]), dim=-1)
    logits = a @ b.T / temperature
    labels = torch.arange(a.shape[0], device=a.device)
    return 0.5 * (F.cross_entropy(logits, labels) + F.cross_entropy(logits.T, labels))


class FreamerAuxLoss(LossModule):
    """Flow-matching (Eq. A13), vision-language contrastive and FNO smoothness (Eq. A16) losses, as a TorchRL loss.

    Use it beside :class:`~torchrl.objectives.ClipPPOLoss` and add the ``loss_*`` entries of both (Eq. 6)::

        aux = FreamerAuxLoss(modules.refiners, smooth_fuser=modules.fuser)
        with set_recurrent_mode(True):
            mb = modules.trunk(mb)                # [B, T] sequences: one trunk pass writes the keys below
        ppo = ClipPPOLoss(modules.actor, modules.critic)(mb)    # the heads read "hidden"
        loss = sum(v for k, v in {**ppo, **aux(mb)}.items() if k.startswith("loss_"))

    Given ``trunk=``, the loss runs the trunk itself on every minibatch (in recurrent mode, as every TorchRL loss
    does; on a shallow copy, so the caller's tensordict is left as it was), so it can sit beside
    ``ClipPPOLoss(policy, value)`` on raw minibatches at the cost of one more trunk pass. It always reruns it:
    collected data already holds the trunk's keys, but computed at collection time, without gradients.

    Keys read (``set_keys`` renames them, TorchRL's pattern; shapes for a minibatch of batch ``[*B]``):
        embed: prefix of the Layer-1 embeddings ``(embed, m) [*B, d]`` for every refined modality ``m``.
        modal_stack: the Layer-3 input ``E [*B, M, d]`` (used when ``smooth_fuser`` is given).
        fused_modalities: the fuser's rows ``E_out [*B, M, d]`` (used when ``smooth_fuser`` is None).

    Args:
        refiners: ``{modality: FlowMatchingRefiner}`` (``FreamerModules.refiners``).
        lambda_fm, lambda_cl, lambda_smooth: weights of Eq. 6. A zero weight skips the term.
        noise_std: perturbation scale of the denoising CFM pairs.
        relative_noise: ``noise_std`` in units of each embedding row's own std (``model.flow.noise_scale``).
        temperature: InfoNCE temperature of the contrastive term (used only with vision and language).
        smooth_fuser: the :class:`~freamer_rl.layers.fno.FNOFuser`. Given, ``L_smooth`` is computed on
            ``smooth_fuser(E.detach())`` and trains only the fuser; ``None``: on the trunk's ``fused_modalities``
            rows, so the gradient reaches encoders and refiners too (the literal Eq. 6; see the module docstring).
        trunk: optional trunk run on every minibatch before the keys above are read.
        clean_keys: ``{observation key: key of its clean copy}`` (``model.flow.targets=paired``, with
            ``env.clean_copies``): each refiner is also trained on the pair (embedding of the observation as
            collected, embedding with the clean copies in its place) (:meth:`FlowMatchingRefiner.paired_loss`), its
            synthetic CFM term then on the clean embedding; needs ``encoders``.
        paired_modalities: the refiners trained on those pairs (default: all): the modalities whose inputs the
            clean copies replace (:func:`paired_modalities`); the others keep the synthetic loss alone.
        encoders: Layer 1 alone (``FreamerModules.encoders``), run without gradients on the clean copies.
        modalities: the model's modalities (default: the refiners' keys); the contrastive term needs vision and
            language among them.
        presence_keys: ``{modality: flag key [*B, 1]}`` (``model.presence_keys``): a refiner's synthetic CFM term,
            its paired term and its score statistics leave out the rows whose flag is 0 (a dropped sensor's
            embedding is no sample of what the modality looks like, and the fuser never sees it).

    Returns (forward): a TensorDict with the weighted scalars ``loss_fm``, ``loss_cl``, ``loss_smooth`` (each only when
    its weight is non-zero and its inputs exist) and detached per-modality diagnostics ``fm_<modality>`` (with
    ``clean_keys``, also ``fm_left_<modality>``: the share of the corruption the refined embedding still carries).
    """

    @dataclass
    class _AcceptedKeys:
        embed: NestedKey = "embed"
        modal_stack: NestedKey = "modal_stack"
        fused_modalities: NestedKey = "fused_modalities"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(
        self,
        refiners: nn.ModuleDict,
        *,
        lambda_fm: float = 0.1,
        lambda_cl: float = 0.1,
        lambda_smooth: float = 1e-3,
        noise_std: float = 1.0,
        relative_noise: bool = False,
        temperature: float = 0.1,
        smooth_fuser: nn.Module | None = None,
        trunk: nn.Module | None = None,
        modalities: Sequence[str] | None = None,
        clean_keys: Mapping[NestedKey, NestedKey] | None = None,
        encoders: nn.Module | None = None,
        paired_modalities: Sequence[str] | None = None,
        presence_keys: Mapping[str, NestedKey] | None = None,
    ) -> None:
        super().__init__()
        self.refiners = refiners
        self.lambda_fm = lambda_fm
        self.lambda_cl = lambda_cl
        self.lambda_smooth = lambda_smooth
        self.noise_std = noise_std
        self.relative_noise = relative_noise
        self.temperature = temperature
        self.smooth_fuser = smooth_fuser
        self.trunk = trunk
        # the contrastive pair is read from the Layer-1 embeddings, refined or not (model.flow.placement)
        self.modalities = list(refiners) if modalities is None else list(modalities)
        self.clean_keys = dict(clean_keys or {})
        self.presence_keys = {m: k for m, k in (presence_keys or {}).items() if m in refiners}
        if self.clean_keys and encoders is None:
            raise ValueError("FreamerAuxLoss: clean_keys needs encoders= (Layer 1, FreamerModules.encoders)")
        self.paired = set(refiners) if paired_modalities is None else set(paired_modalities)
        if self.clean_keys and not self.paired <= set(refiners):
            raise ValueError(f"FreamerAuxLoss: paired_modalities {sorted(self.paired)} not all in {list(refiners)}")
        # only the Layer-1 steps the paired embeddings need run on the clean copies (not, say, the language
        # Transformer when only the grid is paired): the same modules, every minibatch
        self.encoders = (
            encoders.select_subsequence(out_keys=[(*_as_tuple(self.tensor_keys.embed), m) for m in sorted(self.paired)])
            if self.clean_keys
            else None
        )

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """No value estimator: nothing to forward (TorchRL calls this from ``set_keys``)."""

    @property
    def in_keys(self) -> list:
        keys = self.tensor_keys
        out = [(*_as_tuple(keys.embed), m) for m in self.refiners]
        out.append(keys.modal_stack if self.smooth_fuser is not None else keys.fused_modalities)
        return out + list(self.clean_keys.values()) + list(self.presence_keys.values())

    def _embed(self, td: TensorDictBase, m: str) -> torch.Tensor:
        return self._get(td, (*_as_tuple(self.tensor_keys.embed), m))

    @staticmethod
    def _get(td: TensorDictBase, key: NestedKey) -> torch.Tensor:
        """``td[key]``, or a ``KeyError`` naming the key (it is written by a trunk pass on this tensordict)."""
        value = td.get(key, None)
        if value is None:
            raise KeyError(
                f"FreamerAuxLoss: {key!r} is missing from the tensordict; run the trunk on it first "
                "(or give the loss trunk=)"
            )
        return value

    def _fm_terms(self, td: TensorDictBase, out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Per refiner: the synthetic CFM loss (Eq. A13) on its embedding, or with ``clean_keys`` the mean of that
        loss on the clean embedding and the paired loss (``fm_left_<m>`` written to ``out``)."""
        clean = self._clean_embeddings(td) if self.clean_keys else None
        terms = {}
        for m, r in self.refiners.items():
            e = self._embed(td, m)
            mask = self._get(td, self.presence_keys[m]) if m in self.presence_keys else None
            if clean is None or m not in self.paired:
                terms[m] = r.cfm_loss(e, noise_std=self.noise_std, relative=self.relative_noise, mask=mask)
                continue
            target = clean.get((*_as_tuple(self.tensor_keys.embed), m))
            paired, out[f"fm_left_{m}"] = r.paired_loss(e, target, mask=mask)
            synthetic = r.cfm_loss(target, noise_std=self.noise_std, relative=self.relative_noise, mask=mask)
            terms[m] = 0.5 * (synthetic + paired)
        return terms

    def _clean_embeddings(self, td: TensorDictBase) -> TensorDictBase:
        """Layer 1 on ``td``'s inputs with each observation replaced by its clean copy (no gradients)."""
        missing = [k for k in self.clean_keys.values() if td.get(k, None) is None]
        if missing:
            raise KeyError(
                f"FreamerAuxLoss: the clean copies {missing} are missing from the tensordict (env.clean_copies "
                "writes them; keep them in the stored batch)"
            )
        inputs = td.select(*self.encoders.in_keys, strict=False)
        for key, copy_key in self.clean_keys.items():
            inputs.set(key, td.get(copy_key))
        with torch.no_grad():
            return self.encoders(inputs)

    def forward(self, td: TensorDictBase) -> TensorDict:
        keys = self.tensor_keys
        if self.trunk is not None:
            td = self.trunk(td.copy())  # recurrent mode is on inside every LossModule.forward
        out: dict[str, torch.Tensor] = {}
        if self.lambda_fm and len(self.refiners):
            per_mod = self._fm_terms(td, out)
            for m, v in per_mod.items():
                out[f"fm_{m}"] = v.detach()
            out["loss_fm"] = self.lambda_fm * torch.stack(list(per_mod.values())).mean()
        if self.lambda_cl and "vision" in self.modalities and "language" in self.modalities:
            v, lang = self._embed(td, "vision"), self._embed(td, "language")
            zero = torch.zeros((), device=v.device)
            out["loss_cl"] = (
                self.lambda_cl * info_nce(v, lang, self.temperature) if v.numel() // v.shape[-1] > 1 else zero
            )
        if self.lambda_smooth:
            if self.smooth_fuser is not None:
                rows = self.smooth_fuser(self._get(td, keys.modal_stack).detach())[1]
            else:
                rows = self._get(td, keys.fused_modalities)
            out["loss_smooth"] = self.lambda_smooth * smoothness_loss(rows)
        return TensorDict(out, batch_size=[])


def paired_modalities(modalities: Sequence[str], clean_copies: Sequence[str], observation_keys: dict) -> list[str]:
    """The modalities whose Layer-1 inputs include one of ``clean_copies`` (``env.clean_copies``); vision and
    language together when either is (their slots attend to each other before pooling)."""
    copies = set(clean_copies)
    paired = {m for m in modalities if copies & set(modality_keys(m, observation_keys))}
    if {"vision", "language"} <= set(modalities) and paired & {"vision", "language"}:
        paired |= {"vision", "language"}
    return [m for m in modalities if m in paired]


def _as_tuple(key: NestedKey) -> tuple:
    return key if isinstance(key, tuple) else (key,)
