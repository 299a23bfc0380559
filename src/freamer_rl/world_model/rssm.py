"""RSSM world model of the health domain (paper Appendix J.1 and J.3).

Plain ``nn.Module``s on tensors. Every method accepts arbitrary leading batch dims ``[*B, ...]``.

Latent state ``s_t = [h_t; z_t]`` with a deterministic GRU state ``h_t`` (``deter_dim``, 256 in Table A20) and a
diagonal-Gaussian stochastic state ``z_t`` (``stoch_dim``, 64):

* transition (Eq. A23): ``h_{t+1} = GRU(h_t, [z_t; e(a_t)])``
* prior (Eq. A24): ``p(z_t | h_t) = N(mu(h_t), sigma(h_t))``
* posterior (Eq. A25): ``q(z_t | h_t, o_t) = N(mu(h_t, e_t), sigma(h_t, e_t))`` with ``e_t`` the encoder output
* loss (Eq. A27): ``L_rec + beta * max(KL(q || p), free_nats) + L_rew + L_con``

Time convention (DreamerV3's): element ``t`` of a sequence holds the observation ``o_t`` and the action that *led*
to it (``a_{t-1}``). :meth:`WorldModel.loss` builds such a sequence of length ``T + 1`` from a TorchRL ``[*B, T]``
slice (root observation of step 0 followed by every ``("next", obs)``), so the reward head at latent ``s_{t+1}``
predicts ``("next", "reward")[t]`` and the continuation head learns from the terminal observations too -- the same
convention as :class:`~freamer_rl.world_model.imagination.RSSMWorldModelEnv`, whose step maps ``(s_t, a_t)`` to
``s_{t+1}`` and reads reward/continuation off ``s_{t+1}``.

Training from a replay buffer (what the training loop does)::

    rb = ReplayBuffer(storage=LazyTensorStorage(N), sampler=SliceSampler(slice_len=T, traj_key=("collector",
                      "traj_ids")), batch_size=num_slices * T)
    rb.extend(collected_data.reshape(-1))
    batch = as_sequences(rb.sample(), seq_len=T)          # [num_slices, T]
    losses = world_model.loss(batch)                       # dict: loss_rec, loss_kl, loss_rew, loss_con, total
    losses["total"].backward()

or simply ``train_world_model(world_model, rb, optimizer, steps)`` (:mod:`.training`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import LossModule

from freamer_rl.layers.moments import merge_moments
from freamer_rl.world_model.functional import (
    _check_last_dim,
    _flat,
    action_to_onehot,
    free_nats_kl,
    gaussian_kl,
    mlp,
    symexp,
    symlog,
)
from freamer_rl.world_model.heads import head_loss, make_scalar_head
from freamer_rl.world_model.obs_nets import MLPObsDecoder, MLPObsEncoder

logger = logging.getLogger(__name__)

__all__ = ["RSSM", "WorldModel"]


# ----------------------------------------------------------------------------------------------------------------------
# RSSM core
# ----------------------------------------------------------------------------------------------------------------------
class RSSM(nn.Module):
    """Recurrent state-space model with a Gaussian stochastic state (Eqs. A23-A25).

    Args:
        obs_embed_dim: size ``E`` of the encoder output ``o_t^embed``.
        action_dim: size ``A`` of the (one-hot) action vector.
        deter_dim: GRU state size (256, Table A20).
        stoch_dim: Gaussian latent size (64, Table A20).
        hidden: width of the GRU input projection of ``[z; e(a)]`` and of the prior/posterior MLPs.
        min_std: lower bound of the prior/posterior std (``softplus(x) + min_std``).
    """

    def __init__(
        self,
        obs_embed_dim: int,
        action_dim: int,
        deter_dim: int = 256,
        stoch_dim: int = 64,
        hidden: int = 256,
        min_std: float = 0.1,
    ) -> None:
        super().__init__()
        self.obs_embed_dim = obs_embed_dim
        self.action_dim = action_dim
        self.deter_dim = deter_dim
        self.stoch_dim = stoch_dim
        self.min_std = min_std
        # [z_t; e(a_t)] -> GRU input. The action embedding e(a) = W_a a is linear in the one-hot action (an embedding
        # lookup), so it is folded into this first layer: Linear([z; a]) = W_z z + W_a a + b.
        self.gru_in = nn.Sequential(nn.Linear(stoch_dim + action_dim, hidden), nn.LayerNorm(hidden), nn.SiLU())
        self.gru = nn.GRUCell(hidden, deter_dim)
        self.prior_net = mlp(deter_dim, hidden, 2 * stoch_dim, layers=1)
        self.post_net = mlp(deter_dim + obs_embed_dim, hidden, 2 * stoch_dim, layers=1)

    # -- pieces ---------------------------------------------------------------------------------------------------
    def initial_state(
        self, batch_shape: Sequence[int] = (), device: torch.device | None = None, dtype: torch.dtype | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero ``(h, z)`` of shapes ``[*batch_shape, deter_dim]`` and ``[*batch_shape, stoch_dim]``."""
        h = torch.zeros(*batch_shape, self.deter_dim, device=device, dtype=dtype)
        z = torch.zeros(*batch_shape, self.stoch_dim, device=device, dtype=dtype)
        return h, z

    def _params(self, out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, pre_std = out.chunk(2, dim=-1)
        return mean, F.softplus(pre_std) + self.min_std

    def transition(self, h: torch.Tensor, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Eq. A23: ``[*B, D], [*B, S], [*B, A] -> h' [*B, D]``."""
        _check_last_dim("h", h, self.deter_dim)
        _check_last_dim("z", z, self.stoch_dim)
        _check_last_dim("action (one-hot)", action, self.action_dim)
        hf, lead = _flat(h)
        x = torch.cat([z.reshape(hf.shape[0], -1), action.reshape(hf.shape[0], -1).to(z.dtype)], dim=-1)
        return self.gru(self.gru_in(x), hf).reshape(*lead, self.deter_dim)

    def prior(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Eq. A24: ``h [*B, D] -> (mean, std)`` each ``[*B, S]``."""
        return self._params(self.prior_net(h))

    def posterior(self, h: torch.Tensor, embed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Eq. A25: ``h [*B, D], embed [*B, E] -> (mean, std)`` each ``[*B, S]``."""
        _check_last_dim("embed", embed, self.obs_embed_dim)
        return self._params(self.post_net(torch.cat([h, embed], dim=-1)))

    @staticmethod
    def sample(mean: torch.Tensor, std: torch.Tensor, sample: bool = True) -> torch.Tensor:
        """Reparameterised sample (or the mean when ``sample=False``)."""
        return mean + std * torch.randn_like(std) if sample else mean

    # -- steps ----------------------------------------------------------------------------------------------------
    def imagine_step(
        self, h: torch.Tensor, z: torch.Tensor, action: torch.Tensor, sample: bool = True
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor], torch.Tensor]:
        """Prior-only step (Eq. A28): ``(h_t, z_t, a_t) -> (h_{t+1}, (prior mean, prior std), z_{t+1} ~ prior)``.

        Shapes: ``h [*B, D]``, ``z [*B, S]``, ``action [*B, A]`` (one-hot float).
        """
        h_next = self.transition(h, z, action)
        mean, std = self.prior(h_next)
        return h_next, (mean, std), self.sample(mean, std, sample)

    def obs_step(
        self,
        h: torch.Tensor,
        z: torch.Tensor,
        action: torch.Tensor,
        embed: torch.Tensor,
        is_first: torch.Tensor | None = None,
        sample: bool = True,
    ) -> dict[str, torch.Tensor]:
        """One filtering step: transition from the previous latent with the action that led to ``o_t``, then the
        prior and the posterior given ``embed = e(o_t)``. Where ``is_first`` (bool ``[*B]``) is True, the previous
        latent and the action are zeroed first (a fresh episode: ``h_t`` is then a learned function of nothing).

        Returns a dict of ``[*B, *]`` tensors: ``h``, ``z`` (posterior sample), ``prior_mean``, ``prior_std``,
        ``post_mean``, ``post_std``.
        """
        if is_first is not None:
            keep = (~is_first.bool()).unsqueeze(-1).to(h.dtype)
            h, z, action = h * keep, z * keep, action * keep
        h = self.transition(h, z, action)
        prior_mean, prior_std = self.prior(h)
        post_mean, post_std = self.posterior(h, embed)
        z = self.sample(post_mean, post_std, sample)
        return {
            "h": h,
            "z": z,
            "prior_mean": prior_mean,
            "prior_std": prior_std,
            "post_mean": post_mean,
            "post_std": post_std,
        }

    def observe(
        self,
        embeds: torch.Tensor,
        actions: torch.Tensor,
        is_first: torch.Tensor,
        h0: torch.Tensor | None = None,
        z0: torch.Tensor | None = None,
        sample: bool = True,
    ) -> dict[str, torch.Tensor]:
        """Filter a sequence (posterior rollout).

        Args:
            embeds: ``[*B, T, E]`` encoder outputs ``e(o_t)``.
            actions: ``[*B, T, A]`` one-hot; ``actions[..., t, :]`` is the action that led to ``o_t``
                (ignored where ``is_first``).
            is_first: bool ``[*B, T]``; the state is reset (previous latent and action zeroed) where True.
            h0, z0: ``[*B, D]``, ``[*B, S]`` latent preceding ``embeds[..., 0, :]`` (zeros when omitted).
            sample: reparameterised posterior samples (True) or posterior means (False) are fed forward.

        Returns:
            dict of ``[*B, T, *]`` tensors: ``h``, ``z``, ``prior_mean``, ``prior_std``, ``post_mean``, ``post_std``.
        """
        if embeds.ndim < 2:
            raise ValueError(f"embeds: expected [*B, T, E], got {tuple(embeds.shape)}")
        lead = embeds.shape[:-2]
        T = embeds.shape[-2]
        if actions.shape[:-1] != embeds.shape[:-1]:
            raise ValueError(f"actions: expected leading shape {tuple(embeds.shape[:-1])}, got {tuple(actions.shape)}")
        if is_first.shape != embeds.shape[:-1]:
            raise ValueError(f"is_first: expected shape {tuple(embeds.shape[:-1])}, got {tuple(is_first.shape)}")
        e = embeds.reshape(-1, T, embeds.shape[-1])
        a = actions.reshape(-1, T, actions.shape[-1])
        first = is_first.reshape(-1, T).bool()
        n = e.shape[0]
        h, z = self.initial_state((n,), device=e.device, dtype=e.dtype)
        if h0 is not None:
            h = h0.reshape(n, self.deter_dim)
        if z0 is not None:
            z = z0.reshape(n, self.stoch_dim)
        outs: dict[str, list[torch.Tensor]] = {}
        for t in range(T):
            step = self.obs_step(h, z, a[:, t], e[:, t], first[:, t], sample=sample)
            h, z = step["h"], step["z"]
            for k, v in step.items():
                outs.setdefault(k, []).append(v)
        return {k: torch.stack(v, dim=1).reshape(*lead, T, -1) for k, v in outs.items()}


# ----------------------------------------------------------------------------------------------------------------------
# world model
# ----------------------------------------------------------------------------------------------------------------------
class WorldModel(nn.Module):
    """Encoder + RSSM + decoder + reward and continuation heads, with the loss of Eq. A27.

    Args:
        obs_dims: ``{observation key: feature size}``, e.g. ``{"imu": 36, "hr_features": 16}``; these keys are
            encoded and reconstructed.
        action_dim: number of discrete actions (integer actions are one-hot encoded) or the size of a float action.
        encoder: any module mapping the observations to ``[*B, embed_dim]``. A plain ``nn.Module`` is called with a
            ``dict`` ``{key: [*B, T, d]}``; a ``TensorDictModuleBase`` is called with a TensorDict holding the
            observation keys (plus ``"is_init"`` ``[*B, T, 1]``, True at the first step of each sequence) under
            ``torchrl.modules.set_recurrent_mode(True)`` (time = last batch dim; a single sequence ``[T]`` is run as
            ``[1, T]``) and its first out_key is read. Default :class:`MLPObsEncoder`.
        rssm: default ``RSSM(embed_dim, action_dim, deter_dim, stoch_dim, hidden, min_std)``.
        decoder: latent ``[*B, D + S]`` -> ``{key: [*B, d_key]}``; default :class:`MLPObsDecoder`.
        reward_head, continue_head: latent -> ``[*B, 1]`` (reward; continuation Bernoulli logit).
        beta: KL weight ``beta_d`` (1.0 in J.3; Table A20 lists 0.5).
        free_nats: per-step KL floor (1.0, Table A20).
        kl_balance: ``None`` for the paper's plain ``KL(q || p)``; a float ``alpha`` for DreamerV2-style balancing
            ``alpha KL(sg(q) || p) + (1 - alpha) KL(q || sg(p))``. Free nats clamp each step's balanced KL; the
            two terms have the same value, so this equals DreamerV3's per-term clip ``dyn max(fn, KL(sg(q)||p)) +
            rep max(fn, KL(q||sg(p)))`` in value and gradient with ``beta = dyn + rep``, ``alpha = dyn / beta``
            (DreamerV3's 0.5 / 0.1: ``beta = 0.6``, ``alpha = 5/6``; tested in test_world_model_options).
        symlog_targets: reconstruct ``symlog(obs)`` (DreamerV3) instead of the raw observation. The reported
            ``mse_<key>`` metrics are always in raw observation units.
        recon_norm: reconstruct per-feature standardised observations ``(obs - mean) / max(std, norm_std_floor)``
            instead (overrides ``symlog_targets``). ``mean``/``std`` are running statistics over every training
            batch seen (buffers ``recon_mean_<i>``, ``recon_var_<i>``, ``recon_count``, updated in train mode only,
            saved with the state dict). Without it a feature's weight in ``L_rec`` is its squared scale: the health
            env's heart-rate features (``HR / 200``, zone, fatigue, ...; std ~0.05-0.3) cost ~100x less than the IMU
            (m/s^2) per unit of relative error, so the posterior stops encoding the heart rate once the KL sits
            at its free-nats floor.
        norm_std_floor: lower bound of the std used by ``recon_norm`` (near-constant features).
        reward_scale, continue_scale: weights of ``L_rew`` and ``L_con``.
        reward_head_kind: default reward head: ``"mse"`` (an MLP, MSE loss) or ``"twohot"`` (symlog two-hot,
            :class:`~freamer_rl.world_model.heads.TwoHotHead`); ``ensemble`` K > 1 makes it K such heads
            (:class:`~freamer_rl.world_model.heads.HeadEnsemble`: mean prediction, :meth:`reward_std` their spread).
        action_key, reward_key, terminated_key, done_key: TensorDict keys read by :meth:`loss`.
    """

    def __init__(
        self,
        obs_dims: Mapping[NestedKey, int],
        action_dim: int,
        *,
        encoder: nn.Module | None = None,
        rssm: RSSM | None = None,
        decoder: nn.Module | None = None,
        reward_head: nn.Module | None = None,
        continue_head: nn.Module | None = None,
        embed_dim: int = 256,
        deter_dim: int = 256,
        stoch_dim: int = 64,
        hidden: int = 256,
        min_std: float = 0.1,
        beta: float = 1.0,
        free_nats: float = 1.0,
        kl_balance: float | None = None,
        symlog_targets: bool = True,
        recon_norm: bool = False,
        norm_std_floor: float = 1e-2,
        reward_scale: float = 1.0,
        continue_scale: float = 1.0,
        reward_head_kind: str = "mse",
        ensemble: int = 1,
        action_key: NestedKey = "action",
        reward_key: NestedKey = ("next", "reward"),
        terminated_key: NestedKey = ("next", "terminated"),
        done_key: NestedKey = ("next", "done"),
    ) -> None:
        super().__init__()
        self.obs_dims = dict(obs_dims)
        self.action_dim = action_dim
        self.encoder = encoder if encoder is not None else MLPObsEncoder(self.obs_dims, embed_dim, hidden)
        self.rssm = rssm if rssm is not None else RSSM(embed_dim, action_dim, deter_dim, stoch_dim, hidden, min_std)
        if self.rssm.action_dim != action_dim:
            raise ValueError(f"rssm: action_dim {self.rssm.action_dim} != world model action_dim {action_dim}")
        self.deter_dim = self.rssm.deter_dim
        self.stoch_dim = self.rssm.stoch_dim
        latent = self.latent_dim
        self.decoder = decoder if decoder is not None else MLPObsDecoder(latent, self.obs_dims, hidden)
        if reward_head is None:
            reward_head = make_scalar_head(reward_head_kind, latent, hidden, ensemble)
        self.reward_head = reward_head
        self.continue_head = continue_head if continue_head is not None else mlp(latent, hidden, 1)
        if kl_balance is not None and not 0.0 <= kl_balance <= 1.0:
            raise ValueError(f"kl_balance: expected None or a float in [0, 1], got {kl_balance}")
        self.beta = beta
        self.free_nats = free_nats
        self.kl_balance = kl_balance
        self.symlog_targets = symlog_targets
        self.recon_norm = recon_norm
        if norm_std_floor <= 0:
            raise ValueError(f"norm_std_floor: expected a positive float, got {norm_std_floor}")
        self.norm_std_floor = norm_std_floor
        if recon_norm:
            for i, d in enumerate(self.obs_dims.values()):
                self.register_buffer(f"recon_mean_{i}", torch.zeros(d))
                self.register_buffer(f"recon_var_{i}", torch.ones(d))
            self.register_buffer("recon_count", torch.zeros((), dtype=torch.float64))
        self.reward_scale = reward_scale
        self.continue_scale = continue_scale
        self.action_key = action_key
        self.reward_key = reward_key
        self.terminated_key = terminated_key
        self.done_key = done_key

    @property
    def latent_dim(self) -> int:
        return self.deter_dim + self.stoch_dim

    def reward_std(self, feat: torch.Tensor) -> torch.Tensor:
        """Spread ``[*B, 1]`` of an ensemble reward head over its members at latent ``feat [*B, L]`` (zeros for a
        single head)."""
        if hasattr(self.reward_head, "std"):
            return self.reward_head.std(feat)
        return feat.new_zeros(*feat.shape[:-1], 1)

    # -- pieces ---------------------------------------------------------------------------------------------------
    @staticmethod
    def features(h: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Latent ``s = [h; z]``: ``[*B, D], [*B, S] -> [*B, D + S]``."""
        return torch.cat([h, z], dim=-1)

    def action_to_onehot(self, action: torch.Tensor, batch_ndim: int) -> torch.Tensor:
        """See :func:`action_to_onehot`."""
        return action_to_onehot(action, self.action_dim, batch_ndim)

    def embed(self, obs: Mapping[NestedKey, torch.Tensor] | TensorDictBase) -> torch.Tensor:
        """Encode observation sequences ``{key: [*B, T, d]}`` -> ``[*B, T, E]`` with the pluggable encoder (a
        TensorDict encoder gets a TensorDict, see :meth:`encode`)."""
        if isinstance(self.encoder, TensorDictModuleBase):
            if not isinstance(obs, TensorDictBase):
                raise TypeError("a TensorDictModule encoder needs a TensorDict of observations")
            return self.encode(obs).get(self.encoder.out_keys[0])
        if isinstance(obs, TensorDictBase):
            obs = {k: obs.get(k) for k in self.obs_dims}
        return self.encoder(obs)

    def encode(self, obs: TensorDictBase) -> TensorDictBase:
        """Run a TensorDict encoder on a ``[*B, T]`` sequence tensordict (observations, ``"is_init" [*B, T, 1]``)
        under ``set_recurrent_mode(True)``; a 1-D ``[T]`` one runs as ``[1, T]``. Returns what the encoder wrote
        (a shallow copy of ``obs``: the caller's tensordict is left as it was), e.g. ``out_keys[0] [*B, T, E]``
        and the intermediate keys an auxiliary loss reads."""
        single = obs.batch_dims == 1
        td = obs.unsqueeze(0) if single else obs.copy()
        with set_recurrent_mode(True):
            td = self.encoder(td)
        return td.squeeze(0) if single else td

    def kl(self, out: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Per-step ``KL(q || p)`` summed over latent dims (``[*B, T]``), optionally balanced (see ``kl_balance``)."""
        q = (out["post_mean"], out["post_std"])
        p = (out["prior_mean"], out["prior_std"])
        if self.kl_balance is None:
            return gaussian_kl(*q, *p)
        a = self.kl_balance
        sg_q = tuple(x.detach() for x in q)
        sg_p = tuple(x.detach() for x in p)
        return a * gaussian_kl(*sg_q, *p) + (1 - a) * gaussian_kl(*q, *sg_p)

    def sequence(self, batch: TensorDictBase) -> dict[str, torch.Tensor | dict]:
        """Turn a TorchRL slice ``[*B, T]`` into the ``T + 1`` filtering sequence of the module docstring.

        Returns ``obs`` (``{key: [*B, T+1, d]}``), ``actions`` (one-hot ``[*B, T+1, A]``, zeros at 0),
        ``is_first`` (``[*B, T+1]``, True at 0 only), ``reward`` and ``cont`` (``[*B, T]``, targets of steps 1..T).
        Raises ``ValueError`` when the slice crosses an episode boundary (use a ``SliceSampler`` with a
        ``traj_key``/``end_key``).
        """
        if batch.batch_dims < 1:
            raise ValueError(f"batch: expected a [*B, T] TensorDict (time last), got batch_size {batch.batch_size}")
        td = batch.ndim - 1  # time dim
        done = batch.get(self.done_key, None)
        if done is not None and batch.shape[-1] > 1:
            d = done.reshape(*batch.shape, -1).any(-1)
            if d[..., :-1].any():
                raise ValueError(
                    f"batch: {self.done_key} is True before the last step of a slice: slices must not cross episode "
                    "boundaries (sample with SliceSampler(traj_key=..., or end_key=...))"
                )
        obs = {}
        for k in self.obs_dims:
            first = batch.get(k)
            nxt = batch.get(("next", *((k,) if isinstance(k, str) else k)))
            obs[k] = torch.cat([first.narrow(td, 0, 1), nxt], dim=td).float()
        a = self.action_to_onehot(batch.get(self.action_key), batch.ndim)
        actions = torch.cat([torch.zeros_like(a.narrow(td, 0, 1)), a], dim=td)
        is_first = torch.zeros(*batch.shape[:-1], batch.shape[-1] + 1, dtype=torch.bool, device=a.device)
        is_first[..., 0] = True
        reward = batch.get(self.reward_key).reshape(*batch.shape).float()
        terminated = batch.get(self.terminated_key, None)
        if terminated is None:
            terminated = torch.zeros(batch.shape, dtype=torch.bool, device=a.device)
        cont = 1.0 - terminated.reshape(*batch.shape).float()
        return {"obs": obs, "actions": actions, "is_first": is_first, "reward": reward, "cont": cont}

    def observe(self, batch: TensorDictBase, sample: bool = True) -> tuple[dict[str, torch.Tensor], dict]:
        """Encode and filter a ``[*B, T]`` slice. Returns (RSSM outputs ``[*B, T+1, *]``, :meth:`sequence`); with a
        TensorDict encoder the sequence dict also holds ``"encoded"``, the tensordict ``[*B, T+1]`` it wrote."""
        seq = self.sequence(batch)
        obs = seq["obs"]
        if isinstance(self.encoder, TensorDictModuleBase):
            # a TensorDict encoder (e.g. a recurrent one) also sees where the sequence starts: "is_init" [*B, T+1, 1]
            obs = TensorDict({**obs, "is_init": seq["is_first"].unsqueeze(-1)}, batch_size=seq["is_first"].shape)
            seq["encoded"] = self.encode(obs)
            embeds = seq["encoded"].get(self.encoder.out_keys[0])
        else:
            embeds = self.embed(obs)
        out = self.rssm.observe(embeds, seq["actions"], seq["is_first"], sample=sample)
        return out, seq

    # -- reconstruction targets -----------------------------------------------------------------------------------
    @torch.no_grad()
    def _update_recon_stats(self, obs: Mapping[NestedKey, torch.Tensor]) -> None:
        """Merge the batch's per-feature mean / variance into the running statistics (Chan et al.'s parallel
        update; every key of a batch has the same number of rows)."""
        n_old = self.recon_count.clone()
        n_new = None
        for i, k in enumerate(self.obs_dims):
            x = obs[k].reshape(-1, self.obs_dims[k]).double()
            n_new = x.shape[0]
            m_b, v_b = x.mean(0), x.var(0, unbiased=False)
            mean, var = getattr(self, f"recon_mean_{i}").double(), getattr(self, f"recon_var_{i}").double()
            _, new_mean, new_var = merge_moments(n_old, mean, var, n_new, m_b, v_b)
            getattr(self, f"recon_mean_{i}").copy_(new_mean.float())
            getattr(self, f"recon_var_{i}").copy_(new_var.float())
        if n_new is not None:
            self.recon_count.add_(n_new)

    def _recon_stats(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        mean = getattr(self, f"recon_mean_{i}")
        std = getattr(self, f"recon_var_{i}").clamp_min(0.0).sqrt().clamp_min(self.norm_std_floor)
        return mean, std

    def _to_target(self, i: int, obs: torch.Tensor) -> torch.Tensor:
        """Raw observation of the ``i``-th key -> the decoder's target (standardised, symlog or raw)."""
        if self.recon_norm:
            mean, std = self._recon_stats(i)
            return (obs - mean) / std
        return symlog(obs) if self.symlog_targets else obs

    def _from_target(self, i: int, pred: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`_to_target`: a decoder output of the ``i``-th key in raw observation units."""
        if self.recon_norm:
            mean, std = self._recon_stats(i)
            return pred * std + mean
        return symexp(pred) if self.symlog_targets else pred

    def recon_target(self, key: NestedKey, obs: torch.Tensor) -> torch.Tensor:
        """The decoder's target for raw observation ``obs [*B, d_key]`` (standardised, symlog or raw)."""
        return self._to_target(list(self.obs_dims).index(key), obs)

    def decode(self, latent: torch.Tensor) -> dict[NestedKey, torch.Tensor]:
        """Decoded observations in raw units: ``[*B, D + S] -> {key: [*B, d_key]}``."""
        recon = self.decoder(latent)
        return {k: self._from_target(i, recon[k]) for i, k in enumerate(self.obs_dims)}

    # -- loss -----------------------------------------------------------------------------------------------------
    def loss(
        self, batch: TensorDictBase, return_latents: bool = False, *, aux_loss: LossModule | None = None
    ) -> dict[str, torch.Tensor] | tuple[dict[str, torch.Tensor], TensorDict]:
        """Eq. A27 on a ``[*B, T]`` TorchRL slice (time = last batch dim).

        Reads the observation keys at the root and under ``"next"``, ``action_key``, ``reward_key``,
        ``terminated_key`` (and ``done_key`` for the episode-boundary check).

        * ``loss_rec``: per key, squared error summed over features, mean over ``[*B, T+1]``; summed over keys.
        * ``loss_kl``: ``mean(max(KL_t(q || p), free_nats))`` over ``[*B, T+1]`` (unweighted; ``total`` uses beta).
        * ``loss_rew``: MSE of the reward head at ``s_{t+1}`` vs ``("next", "reward")[t]``.
        * ``loss_con``: BCE of the continuation logit at ``s_{t+1}`` vs ``1 - ("next", "terminated")[t]``.
        * ``total`` = rec + beta kl + reward_scale rew + continue_scale con (+ the ``loss_*`` of ``aux_loss``).
        Diagnostics (detached): ``kl`` (unclamped mean), ``mse_<key>`` (raw units).

        ``aux_loss`` (e.g. the encoder's ``make_aux_loss()``, a :class:`~freamer_rl.model.losses.FreamerAuxLoss`) is run
        on the tensordict the TensorDict encoder wrote for this slice (``[*B, T+1]``, :meth:`observe`'s
        ``"encoded"``); all its entries join the returned dict and its ``loss_*`` terms are added to ``total``.

        With ``return_latents=True`` also returns the detached posterior latents ``TensorDict(deter=[N, D],
        stoch=[N, S])`` flattened over ``[*B, T+1]``: imagination seeds for
        :class:`~freamer_rl.world_model.imagination.RSSMWorldModelEnv`.
        """
        out, seq = self.observe(batch)
        if self.recon_norm and self.training:
            self._update_recon_stats(seq["obs"])
        feat = self.features(out["h"], out["z"])  # [*B, T+1, L]
        recon = self.decoder(feat)
        loss_rec = feat.new_zeros(())
        metrics: dict[str, torch.Tensor] = {}
        for i, (k, target) in enumerate(seq["obs"].items()):
            pred = recon[k]
            loss_rec = loss_rec + (pred - self._to_target(i, target)).pow(2).sum(-1).mean()
            raw = self._from_target(i, pred)
            name = k if isinstance(k, str) else "_".join(k)
            metrics[f"mse_{name}"] = (raw.detach() - target).pow(2).mean()
        kl_t = self.kl(out)
        loss_kl = free_nats_kl(kl_t, self.free_nats)
        nxt = feat[..., 1:, :]
        loss_rew = head_loss(self.reward_head, nxt, seq["reward"])  # MSE, two-hot CE, or the ensemble's mean
        loss_con = F.binary_cross_entropy_with_logits(self.continue_head(nxt).squeeze(-1), seq["cont"])
        total = loss_rec + self.beta * loss_kl + self.reward_scale * loss_rew + self.continue_scale * loss_con
        aux = self._aux_terms(aux_loss, seq)
        for k, v in aux.items():
            if k.startswith("loss_"):
                total = total + v
        losses = {
            "loss_rec": loss_rec,
            "loss_kl": loss_kl,
            "loss_rew": loss_rew,
            "loss_con": loss_con,
            "total": total,
            "kl": kl_t.detach().mean(),
            **metrics,
            **aux,
        }
        if not return_latents:
            return losses
        latents = TensorDict(
            {
                "deter": out["h"].detach().reshape(-1, self.deter_dim),
                "stoch": out["z"].detach().reshape(-1, self.stoch_dim),
            },
            batch_size=[out["h"][..., 0].numel()],
        )
        return losses, latents

    def _aux_terms(self, aux_loss: LossModule | None, seq: Mapping) -> dict[str, torch.Tensor]:
        """``aux_loss`` on the encoder's tensordict -> ``{name: scalar}`` (``{}`` without a loss)."""
        if aux_loss is None:
            return {}
        if "encoded" not in seq:
            raise TypeError(
                f"aux_loss: the encoder {type(self.encoder).__name__} is not a TensorDict module, so there is no "
                "tensordict for the auxiliary loss to read (its make_aux_loss() gives None)"
            )
        return dict(aux_loss(seq["encoded"]).items())

    @torch.no_grad()
    def episode_kl(self, episode: TensorDictBase) -> torch.Tensor:
        """Per-step ``KL(q || p)`` along one recorded episode ``[T]`` (or ``[*B, T]``), posterior means fed forward.

        Returns ``[*B, T + 1]``: element 0 is the reset step (observation at the root of step 0), element ``t + 1``
        the KL after ``("next", obs)[t]`` -- the values :class:`~freamer_rl.world_model.anomaly.KLAnomalyTransform`
        computes online.
        """
        out, _ = self.observe(episode, sample=False)
        return gaussian_kl(out["post_mean"], out["post_std"], out["prior_mean"], out["prior_std"])
