"""Imagination in the RSSM latent space as a TorchRL environment, and policy optimisation on it (Appendix J.4).

:class:`RSSMWorldModelEnv` is a :class:`torchrl.envs.model_based.ModelBasedEnvBase`: its state is the latent
``("deter" [D], "stoch" [S])`` of :class:`~freamer_rl.world_model.rssm.WorldModel` (plus ``"latent" = [deter;
stoch]`` for policies); ``reset`` takes posterior latents computed from real data; ``step`` is a prior-only RSSM step
(Eq. A28) with the reward and continuation heads read off the next latent. Imagination::

    seeds = env.reset(latents)                                   # latents: TensorDict(deter=[N, D], stoch=[N, S])
    traj = env.rollout(15, policy, auto_reset=False, tensordict=seeds)   # [N, 15]

:class:`ImaginationPPO` runs such rollouts under ``no_grad`` and optimises the policy with TorchRL's GAE +
ClipPPOLoss (paper Table A22: PPO), or with the ``lambda_return_actor_critic`` option (REINFORCE on TD(lambda)
returns, DreamerV3's estimator for discrete actions).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE, TDLambdaEstimator

from freamer_rl.run.optim import StepStats, optimizer_step
from freamer_rl.world_model.heads import PercentileReturnScale, TwoHotHead
from freamer_rl.world_model.rssm import WorldModel

logger = logging.getLogger(__name__)

__all__ = ["RSSMWorldModelEnv", "ImaginationPPO", "valid_imagination_mask"]

_DONE_MODES = ("threshold", "sample", "never")
RETURN_NORMS = ("none", "percentile")


class RSSMWorldModelEnv(ModelBasedEnvBase):
    """The RSSM of a :class:`WorldModel` as a TorchRL environment (prior-only imagination).

    Args:
        world_model: a (trained) :class:`WorldModel`; its ``rssm``, ``reward_head`` and ``continue_head`` are used.
        num_actions: size of the ``Categorical`` action spec (default ``world_model.action_dim``).
        action_spec: overrides the default ``Categorical(num_actions)`` spec (e.g. ``OneHot``).
        batch_size: env batch size for the specs (default ``()``). The env is not batch-locked: ``reset`` accepts
            latents of any batch shape and the rollout takes that shape.
        device: torch device.
        done_mode: how the continuation head ``c = sigmoid(logit)`` becomes ``terminated``:
            ``"threshold"`` (default, deterministic): ``c < continue_threshold``;
            ``"sample"``: ``terminated ~ Bernoulli(1 - c)``; ``"never"``: always False (DreamerEnv's behaviour).
            ``truncated`` is always False; ``done = terminated``.
        continue_threshold: threshold of ``"threshold"`` mode.
        sample: sample ``z' ~ p(z | h')`` (default) or use the prior mean.
        uncertainty_penalty: ``lambda_u``: the imagined reward is ``r_hat(s') - lambda_u * std_k r_hat_k(s')`` over the
            members of an ensemble reward head (:meth:`WorldModel.reward_std`; zero spread for a single head).
        deter_key, stoch_key, latent_key: observation/state keys.

    Behaviour notes:
        * ``reset`` requires the latents (``deter_key`` and ``stoch_key``) in its input TensorDict and raises
          ``ValueError`` otherwise -- imagination always starts from posterior latents of real data. Hence
          ``check_env_specs(env)`` needs them too: ``check_env_specs(env, tensordict=env.reset(latents))``.
        * Imagination has a fixed horizon: ``rollout`` defaults to ``break_when_any_done=False`` and
          ``maybe_reset`` is a no-op, so a predicted termination never shortens a rollout nor resets a latent. Steps
          after the first termination keep imagining from the latent; :func:`valid_imagination_mask` drops them.
    """

    def __init__(
        self,
        world_model: WorldModel,
        *,
        num_actions: int | None = None,
        action_spec: TensorSpec | None = None,
        batch_size: Sequence[int] | torch.Size = (),
        device: torch.device | str = "cpu",
        done_mode: str = "threshold",
        continue_threshold: float = 0.5,
        sample: bool = True,
        uncertainty_penalty: float = 0.0,
        deter_key: NestedKey = "deter",
        stoch_key: NestedKey = "stoch",
        latent_key: NestedKey = "latent",
    ) -> None:
        if done_mode not in _DONE_MODES:
            raise ValueError(f"done_mode: expected one of {_DONE_MODES}, got {done_mode!r}")
        super().__init__(world_model, device=device, batch_size=torch.Size(batch_size))
        self.done_mode = done_mode
        self.continue_threshold = continue_threshold
        self.sample_prior = sample
        if uncertainty_penalty < 0:
            raise ValueError(f"uncertainty_penalty: expected >= 0, got {uncertainty_penalty}")
        self.uncertainty_penalty = float(uncertainty_penalty)
        self.deter_key, self.stoch_key, self.latent_key = deter_key, stoch_key, latent_key
        bs = self.batch_size
        D, S = world_model.deter_dim, world_model.stoch_dim
        n = num_actions if num_actions is not None else world_model.action_dim
        self.observation_spec = Composite(
            {
                deter_key: Unbounded((*bs, D), device=self.device),
                stoch_key: Unbounded((*bs, S), device=self.device),
                latent_key: Unbounded((*bs, D + S), device=self.device),
            },
            shape=bs,
        )
        self.state_spec = Composite(
            {deter_key: Unbounded((*bs, D), device=self.device), stoch_key: Unbounded((*bs, S), device=self.device)},
            shape=bs,
        )
        self.action_spec = action_spec if action_spec is not None else Categorical(n, shape=bs, device=self.device)
        self.reward_spec = Unbounded((*bs, 1), device=self.device)
        self.done_spec = Composite(
            {
                k: Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=self.device)
                for k in ("done", "terminated", "truncated")
            },
            shape=bs,
        )

    # -- TorchRL API ----------------------------------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if (
            tensordict is None
            or self.deter_key not in tensordict.keys(True)
            or self.stoch_key not in tensordict.keys(True)
        ):
            have = "no TensorDict" if tensordict is None else f"keys {sorted(map(str, tensordict.keys(True, True)))}"
            raise ValueError(
                f"RSSMWorldModelEnv.reset needs posterior latents: pass a TensorDict with {self.deter_key!r} "
                f"[*B, {self.world_model.deter_dim}] and {self.stoch_key!r} [*B, {self.world_model.stoch_dim}] "
                f"(e.g. from WorldModel.loss(batch, return_latents=True)); got {have}"
            )
        h = tensordict.get(self.deter_key)
        z = tensordict.get(self.stoch_key)
        if h.shape[-1] != self.world_model.deter_dim or z.shape[-1] != self.world_model.stoch_dim:
            raise ValueError(
                f"RSSMWorldModelEnv.reset: expected {self.deter_key!r} [..., {self.world_model.deter_dim}] and "
                f"{self.stoch_key!r} [..., {self.world_model.stoch_dim}], got {tuple(h.shape)} and {tuple(z.shape)}"
            )
        return self._make_td(
            h,
            z,
            torch.cat([h, z], dim=-1),
            None,
            torch.zeros(*tensordict.batch_size, 1, dtype=torch.bool, device=h.device),
            tensordict.batch_size,
        )

    def _make_td(self, h, z, latent, reward, terminated, batch_size) -> TensorDict:
        src = {
            self.deter_key: h,
            self.stoch_key: z,
            self.latent_key: latent,
            "done": terminated,
            "terminated": terminated,
            "truncated": torch.zeros_like(terminated),
        }
        if reward is not None:
            src["reward"] = reward
        return TensorDict(src, batch_size=batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        wm: WorldModel = self.world_model
        h = tensordict.get(self.deter_key)
        z = tensordict.get(self.stoch_key)
        action = wm.action_to_onehot(tensordict.get(self.action_key), tensordict.batch_dims)
        h, _, z = wm.rssm.imagine_step(h, z, action, sample=self.sample_prior)
        feat = torch.cat([h, z], dim=-1)
        reward = wm.reward_head(feat)
        if self.uncertainty_penalty > 0:  # a config constant, not a tensor value: no host sync
            reward = reward - self.uncertainty_penalty * wm.reward_std(feat)
        if self.done_mode == "never":
            terminated = torch.zeros(*tensordict.batch_size, 1, dtype=torch.bool, device=h.device)
        else:
            cont = torch.sigmoid(wm.continue_head(feat))
            if self.done_mode == "threshold":
                terminated = cont < self.continue_threshold
            else:
                terminated = torch.bernoulli(1.0 - cont).bool()
        return self._make_td(h, z, feat, reward, terminated, tensordict.batch_size)

    def maybe_reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """No-op: imagination never resets mid-rollout (there is no real initial state to go back to)."""
        return tensordict

    def rollout(
        self, max_steps: int, policy=None, callback=None, *, break_when_any_done: bool | None = False, **kwargs
    ) -> TensorDictBase:
        """:meth:`EnvBase.rollout` with ``break_when_any_done=False`` by default (fixed-horizon imagination)."""
        return super().rollout(max_steps, policy, callback, break_when_any_done=break_when_any_done, **kwargs)

    def _set_seed(self, seed: int | None) -> None:
        """No-op: imagined samples come from the global torch RNG (seed it with ``torch.manual_seed``)."""


def valid_imagination_mask(traj: TensorDictBase, done_key: NestedKey = ("next", "done")) -> torch.Tensor:
    """Bool ``[*B, H]``: True for imagined steps taken before (or at) the first predicted termination."""
    done = traj.get(done_key).reshape(*traj.shape, -1).any(-1).int()
    return (done.cumsum(-1) - done) == 0


class ImaginationPPO:
    """Policy optimisation purely in imagination (Appendix J.4, Eq. A28).

    Args:
        env: the :class:`RSSMWorldModelEnv`.
        policy: a ``ProbabilisticActor`` reading ``"latent"`` (or any key of the env's observations) that writes
            ``"action"`` and, for PPO, ``"action_log_prob"`` (``return_log_prob=True``).
        value: a ``ValueOperator`` writing ``"state_value"``.
        horizon: imagination horizon H (15).
        gamma, lmbda: discount and GAE/TD(lambda) lambda (0.99, 0.95; Table A20).
        clip_epsilon, epochs, num_minibatches, entropy_coeff, critic_coeff: PPO settings (clip 0.2 and 4 epochs from
            Table A20).
        lr, adam_eps, max_grad_norm: Adam(lr=1e-4, eps=1e-5) and gradient clipping 1.0 (Table A20); ignored for
            the optimiser when ``optimizer`` is given.
        lambda_return_actor_critic: instead of PPO, one full-batch step of DreamerV3's discrete-action
            actor-critic: TD(lambda) returns ``R^lambda`` (TorchRL ``TDLambdaEstimator``) on the imagined trajectory,
            actor loss ``-log pi(a_t|s_t) * sg((R^lambda_t - V(s_t)) / max(1, P95 - P5))`` (REINFORCE with the
            return-range normalisation) minus ``entropy_coeff * H[pi]``, critic loss ``0.5 (V(s_t) -
            sg(R^lambda_t))^2``. Gradients do *not* flow through the imagined dynamics (discrete actions; the
            world model is frozen during policy learning).
        mask_after_termination: drop imagined steps after the first predicted termination from the loss.
        return_norm: ``"none"`` (PPO: ClipPPOLoss's per-minibatch advantage standardisation; the lambda-return
            path: the per-batch ``max(1, P95 - P5)``) or ``"percentile"`` (DreamerV3: advantages divided by
            ``S = max(1, EMA_0.99(P95) - EMA_0.99(P5))`` of the lambda-returns,
            :class:`~freamer_rl.world_model.heads.PercentileReturnScale`, in both paths; PPO then does not
            standardise).
        A value network whose module is a :class:`~freamer_rl.world_model.heads.TwoHotHead` is trained by its
        two-hot cross-entropy on ``value_target`` (weight ``critic_coeff``) instead of ClipPPOLoss's L2.

    :meth:`update` takes the seed latents and returns a dict of float metrics.
    """

    def __init__(
        self,
        env: RSSMWorldModelEnv,
        policy: TensorDictModule,
        value: TensorDictModule,
        *,
        horizon: int = 15,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        clip_epsilon: float = 0.2,
        epochs: int = 4,
        num_minibatches: int = 4,
        entropy_coeff: float = 0.01,
        critic_coeff: float = 0.5,
        lr: float = 1e-4,
        adam_eps: float = 1e-5,
        max_grad_norm: float = 1.0,
        lambda_return_actor_critic: bool = False,
        mask_after_termination: bool = True,
        return_norm: str = "none",
        optimizer: torch.optim.Optimizer | None = None,
    ) -> None:
        if return_norm not in RETURN_NORMS:
            raise ValueError(f"return_norm: expected one of {RETURN_NORMS}, got {return_norm!r}")
        self.return_scale = PercentileReturnScale() if return_norm == "percentile" else None
        head = getattr(value, "module", None)
        self.twohot_value = head if isinstance(head, TwoHotHead) else None
        self.env = env
        self.policy = policy
        self.value = value
        self.horizon = horizon
        self.epochs = epochs
        self.num_minibatches = num_minibatches
        self.entropy_coeff = entropy_coeff
        self.critic_coeff = critic_coeff
        self.max_grad_norm = max_grad_norm
        self.lambda_return_actor_critic = lambda_return_actor_critic
        self.mask_after_termination = mask_after_termination
        if lambda_return_actor_critic:
            self.estimator = TDLambdaEstimator(gamma=gamma, lmbda=lmbda, value_network=value)
            self.loss_module = None
            params = list(policy.parameters()) + list(value.parameters())
        else:
            self.estimator = GAE(gamma=gamma, lmbda=lmbda, value_network=value)
            self.loss_module = ClipPPOLoss(
                policy,
                value,
                clip_epsilon=clip_epsilon,
                entropy_coeff=entropy_coeff,
                critic_coeff=0.0 if self.twohot_value is not None else critic_coeff,  # 0: no L2 critic term
                loss_critic_type="l2",
                normalize_advantage=self.return_scale is None,
            )
            params = list(self.loss_module.parameters()) + list(value.parameters())
        # de-duplicate (shared trunks) while keeping order
        seen: set[int] = set()
        self._params = [p for p in params if p.requires_grad and not (id(p) in seen or seen.add(id(p)))]
        self.optimizer = optimizer if optimizer is not None else torch.optim.Adam(self._params, lr=lr, eps=adam_eps)
        self.step_stats = StepStats("imagination PPO")

    @torch.no_grad()
    def imagine(self, seed_latents: TensorDictBase) -> TensorDictBase:
        """Imagined trajectory ``[*N, H]`` from the seed latents (policy sampled; no gradients)."""
        with set_exploration_type(ExplorationType.RANDOM):
            start = self.env.reset(seed_latents.select(self.env.deter_key, self.env.stoch_key, strict=False))
            return self.env.rollout(self.horizon, self.policy, auto_reset=False, tensordict=start)

    def update(self, seed_latents: TensorDictBase) -> dict[str, float]:
        """Imagine from ``seed_latents`` (``TensorDict(deter=[N, D], stoch=[N, S])``, detached) and update the
        policy and value. Returns float metrics (``loss_objective``/``loss_actor``, ``loss_critic``,
        ``loss_entropy``, ``entropy``, ``imagined_reward``, ``valid_fraction``, ``grad_norm``, ...)."""
        traj = self.imagine(seed_latents)
        with torch.no_grad():
            traj = self.estimator(traj)
        mask = valid_imagination_mask(traj) if self.mask_after_termination else torch.ones(traj.shape, dtype=torch.bool)
        metrics = {
            "imagined_reward": float(traj.get(("next", "reward")).mean()),
            "imagined_termination_rate": float(traj.get(("next", "terminated")).float().mean()),
            "valid_fraction": float(mask.float().mean()),
        }
        data = traj[mask]
        if self.return_scale is not None:
            scale = self.return_scale.update(data.get("value_target"))
            data.set("advantage", data.get("advantage") / scale)
            metrics["return_scale"] = float(scale)
        if self.lambda_return_actor_critic:
            metrics.update(self._lambda_return_step(data))
        else:
            metrics.update(self._ppo_epochs(data))
        return metrics

    @property
    def skipped_updates(self) -> int:
        """Updates skipped for a non-finite gradient (:func:`~freamer_rl.run.optim.optimizer_step`)."""
        return self.step_stats.skipped

    def _step(self, loss: torch.Tensor) -> float:
        return float(optimizer_step(loss, self.optimizer, self._params, self.max_grad_norm, self.step_stats))

    def _ppo_epochs(self, data: TensorDictBase) -> dict[str, float]:
        n = data.shape[0]
        mb = max(1, n // max(1, self.num_minibatches))
        sums: dict[str, float] = {}
        count = 0
        for _ in range(self.epochs):
            perm = torch.randperm(n, device=data.device)
            for start in range(0, n, mb):
                sub = data[perm[start : start + mb]]
                out = self.loss_module(sub)
                loss = out["loss_objective"] + out.get("loss_entropy", 0.0)
                if self.twohot_value is not None:
                    out.set("loss_critic", self._twohot_critic(sub))
                loss = loss + out["loss_critic"]
                gn = self._step(loss)
                for k in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "clip_fraction", "kl_approx"):
                    if k in out.keys():
                        sums[k] = sums.get(k, 0.0) + float(out[k].detach().mean())
                sums["grad_norm"] = sums.get("grad_norm", 0.0) + gn
                count += 1
        return {k: v / count for k, v in sums.items()}

    def _lambda_return_step(self, data: TensorDictBase) -> dict[str, float]:
        target = data.get("value_target").detach()
        adv = data.get("advantage").detach()
        if self.return_scale is None:
            q = torch.quantile(target.flatten(), torch.tensor([0.05, 0.95]))
            scale = torch.clamp(q[1] - q[0], min=1.0)
        else:  # advantages already divided by the EMA scale in update()
            scale = torch.ones(())
        td = data.exclude("state_value").clone(False)
        dist = self.policy.get_dist(td)
        log_prob = dist.log_prob(td.get(self.env.action_key))
        entropy = dist.entropy()
        log_prob = log_prob.reshape(adv.shape[0], -1).sum(-1)
        entropy = entropy.reshape(adv.shape[0], -1).sum(-1)
        loss_actor = -(log_prob * (adv.reshape(-1) / scale)).mean()
        loss_entropy = -self.entropy_coeff * entropy.mean()
        if self.twohot_value is not None:
            loss_critic = self._twohot_critic(data)
        else:
            value = self.value(td.select(*self.value.in_keys)).get(self.value.out_keys[0])
            loss_critic = self.critic_coeff * 0.5 * (value - target).pow(2).mean()
        gn = self._step(loss_actor + loss_entropy + loss_critic)
        return {
            "loss_actor": float(loss_actor.detach()),
            "loss_critic": float(loss_critic.detach()),
            "loss_entropy": float(loss_entropy.detach()),
            "entropy": float(entropy.detach().mean()),
            "return_scale": float(scale),
            "grad_norm": gn,
        }

    def _twohot_critic(self, data: TensorDictBase) -> torch.Tensor:
        """``critic_coeff * CE(twohot(sg(R^lambda)), V_logits(s))`` of a two-hot value head."""
        feat = data.get(self.value.in_keys[0])
        target = data.get("value_target").detach().reshape(feat.shape[:-1])
        return self.critic_coeff * self.twohot_value.loss(feat, target)
