"""DreamerV3 (``trainer: dreamer_v3``; schema in :mod:`freamer_rl.trainers.baselines.config`): TorchRL's RSSM and heads, wired by tensordict keys.

The maths is TorchRL's (``RSSMPriorV3``, ``RSSMPosteriorV3``, ``RSSMStateEstimatorV3``, ``RSSMRolloutV3``,
``DreamerV3MLP``, ``DreamerV3ImageEncoder`` / ``Decoder``, ``SymExpTwoHot``); this module only builds them from the
env specs and binds keys. Shapes (``S = categoricals * classes``, ``D = deter``, ``A = actions``, ``F`` = the flat
features of the non-image observation keys, ``E`` = the embedding):

* featurizer: observation keys -> ``"obs_features"`` float ``[*B, F]`` (one-hot for integer entries, symlog for
  float ones; the reconstruction target of the vector decoder);
* encoder: ``obs_features`` (and an image ``uint8 [*B, H, W, C]``) -> ``"encoded_latents"`` ``[*B, E]``;
* world model (training, ``[B, T]`` replay slices): root ``state [S]``, ``belief [D]``, ``action_onehot [A]``,
  ``is_init``; ``("next", obs)`` -> ``("next", prior_logits / posterior_logits [K, C], state, belief,
  reco_obs_features, reco_<image>, reward_logits [255], reward [1], continue_pred [1])``;
* collection policy (one step ``[*B]``): root ``state``, ``belief``, ``previous_action`` (the carried state, primed
  with zeros), observation, ``is_init`` -> ``action_onehot``, ``action`` (index) and the carried state at
  ``("next", state | belief | previous_action)`` (TorchRL's primer pattern).

Episode starts follow ``RSSMRolloutV3``'s reset rule (state, belief *and* the step's action zeroed where
``is_init``): the world model filters an episode from its second observation on, from a zero state. The collection
policy acts on the first observation with the same zero-state posterior, and then carries zeros (not that
posterior) into the next step, so the belief it acts on is exactly the one the world model is trained to produce.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import (
    InteractionType,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictSequential,
)
from torch import nn
from torchrl.data import Composite, LazyTensorStorage, OneHot, ReplayBuffer, Unbounded
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.envs.transforms import TensorDictPrimer
from torchrl.modules import (
    DreamerV3ImageDecoder,
    DreamerV3ImageEncoder,
    DreamerV3MLP,
    OneHotCategorical,
    RSSMPosteriorV3,
    RSSMPriorV3,
    RSSMRolloutV3,
    RSSMStateEstimatorV3,
    SymExpTwoHot,
    WorldModelWrapper,
)
from torchrl.modules.functional import symlog
from torchrl.objectives import DreamerV3ActorLoss, DreamerV3ModelLoss, DreamerV3ValueLoss, SoftUpdate
from torchrl.objectives.utils import ValueEstimators

from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.run.corruption import corruption_transforms
from freamer_rl.run.envs import probe_specs
from freamer_rl.run.evaluation import read_checkpoint_config, run_episodes
from freamer_rl.run.loop import RunLoop, resolve_run_dir
from freamer_rl.run.metrics import LogMeans
from freamer_rl.run.optim import StepStats, optimizer_step
from freamer_rl.run.params import parameter_rows
from freamer_rl.trainers.baselines.config import ARCHITECTURE_FIELDS, DreamerConfig

#: what shapes DreamerV3's weights: the env and the ``dreamer`` architecture fields (the registry entry's)
STRUCTURAL = ("env", *(f"dreamer.{k}" for k in ARCHITECTURE_FIELDS))

__all__ = [
    "DreamerConfig",
    "DreamerNets",
    "DreamerLearner",
    "DreamerTrainer",
    "SequenceReplay",
    "STRUCTURAL",
    "build_nets",
    "train",
    "evaluate",
    "params",
]

logger = logging.getLogger(__name__)

NUM_BINS = 255


def is_image_spec(spec) -> bool:
    """An image observation: ``uint8 [H, W, C]``."""
    return spec.dtype == torch.uint8 and len(spec.shape) == 3


def _classes(spec) -> int:
    n = getattr(getattr(spec, "space", None), "n", None)
    return int(n) if n is not None else int(spec.space.high.max()) + 1


class ObsFeaturizer(nn.Module):
    """Non-image observations -> one flat float vector ``[*B, F]``: integer entries one-hot over their classes
    (MiniGrid's symbolic grid, direction), float entries through symlog (Crafter's inventory)."""

    def __init__(self, shapes: list[tuple[int, ...]], classes: list[int | None]) -> None:
        super().__init__()
        self.shapes, self.classes = shapes, classes
        self.out_features = sum(math.prod(s) * (c or 1) for s, c in zip(shapes, classes))

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        parts = []
        for x, shape, n in zip(obs, self.shapes, self.classes):
            batch = x.shape[: x.ndim - len(shape)]
            if n is None:
                parts.append(symlog(x.float()).reshape(*batch, -1))
            else:
                onehot = nn.functional.one_hot(x.long().clamp(0, n - 1), n).to(torch.float32)
                parts.append(onehot.reshape(*batch, -1))
        return torch.cat(parts, -1)


class MultiEncoder(nn.Module):
    """``[features [*B, F]] [, image uint8 [*B, H, W, C]]`` -> ``[*B, E]`` (an MLP and / or TorchRL's CNN)."""

    def __init__(
        self,
        features: int,
        image_shape: tuple[int, int, int] | None,
        hidden: int,
        depth: int,
        cnn_depth: int,
        cnn_mults: tuple[int, ...],
    ) -> None:
        super().__init__()
        self.mlp = DreamerV3MLP(features, None, depth=depth, num_cells=hidden) if features else None
        self.cnn = None
        self.out_features = hidden if features else 0
        if image_shape is not None:
            h, w, c = image_shape
            self.cnn = DreamerV3ImageEncoder(in_channels=c, depth=cnn_depth, mults=cnn_mults)
            self.out_features += self.cnn.output_features((c, h, w))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        out, rest = [], list(inputs)
        if self.mlp is not None:
            out.append(self.mlp(rest.pop(0)))
        if self.cnn is not None:
            out.append(self.cnn(rest.pop(0).movedim(-1, -3)))
        return torch.cat(out, -1)


class ImageDecoder(nn.Module):
    """``state [*B, S], belief [*B, D]`` -> image ``[*B, H, W, C]`` (TorchRL's decoder, channels moved last)."""

    def __init__(
        self, in_features: int, image_shape: tuple[int, int, int], cnn_depth: int, cnn_mults: tuple[int, ...]
    ) -> None:
        super().__init__()
        h, w, c = image_shape
        self.net = DreamerV3ImageDecoder(in_features, (c, h, w), depth=cnn_depth, mults=cnn_mults, num_blocks=1)

    def forward(self, state: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        return self.net(state, belief).movedim(-3, -1)


class UnimixLogits(nn.Module):
    """Logits of ``(1 - u) softmax(x) + u / A`` (DreamerV3's 1% uniform mix on the actor) ``[*B, A] -> [*B, A]``."""

    def __init__(self, unimix: float) -> None:
        super().__init__()
        self.unimix = unimix

    def forward(self, logits: torch.Tensor) -> torch.Tensor:
        probs = torch.softmax(logits, -1)
        return torch.log((1 - self.unimix) * probs + self.unimix / logits.shape[-1])


class CarryState(nn.Module):
    """The state carried to the next step: the posterior, its belief and the action, zeros where ``is_init``
    (see the module docstring). ``[*B, S], [*B, D], [*B, A], bool [*B, 1] -> the same three``."""

    def forward(self, state, belief, action, is_init):
        keep = ~is_init.reshape(*state.shape[:-1], 1)
        return state * keep, belief * keep, action.to(state.dtype) * keep


class OneHotToIndex(nn.Module):
    """``[*B, A]`` one-hot -> int64 index ``[*B]`` (the env's Categorical action)."""

    def forward(self, onehot: torch.Tensor) -> torch.Tensor:
        return onehot.argmax(-1)


class Sigmoid(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x)


class DreamerNets(nn.Module):
    """Every DreamerV3 network of one agent, built from the env's unbatched specs and the ``dreamer`` section.

    Submodules hold all parameters (``world_model_params()``, ``actor``, ``value``); the tensordict wrappers
    (``world_model``, ``policy``, ``imagination_env``, ...) are built around them.
    """

    def __init__(self, obs_spec: Composite, n_actions: int, d) -> None:
        super().__init__()
        keys = list(d.observation_keys)
        self.image_key = next((k for k in keys if is_image_spec(obs_spec[k])), None)
        self.vector_keys = [k for k in keys if k != self.image_key]
        specs = [obs_spec[k] for k in self.vector_keys]
        self.featurizer = ObsFeaturizer(
            [tuple(s.shape) for s in specs], [None if s.dtype.is_floating_point else _classes(s) for s in specs]
        )
        image_shape = tuple(obs_spec[self.image_key].shape) if self.image_key else None
        mults = tuple(d.cnn_mults)
        self.encoder = MultiEncoder(
            self.featurizer.out_features if self.vector_keys else 0,
            image_shape,
            d.hidden,
            d.mlp_layers,
            d.cnn_depth,
            mults,
        )
        self.n_actions = n_actions
        self.stoch = d.stoch_categoricals * d.stoch_classes
        self.deter = d.deter
        feat = self.stoch + self.deter
        self.prior = RSSMPriorV3(
            action_shape=(n_actions,),
            action_dim=n_actions,
            hidden_dim=d.hidden,
            rnn_hidden_dim=d.deter,
            num_categoricals=d.stoch_categoricals,
            num_classes=d.stoch_classes,
            unimix=d.unimix,
        )
        self.posterior = RSSMPosteriorV3(
            hidden_dim=d.hidden,
            rnn_hidden_dim=d.deter,
            obs_embed_dim=self.encoder.out_features,
            num_categoricals=d.stoch_categoricals,
            num_classes=d.stoch_classes,
            use_rms_norm=True,
            unimix=d.unimix,
        )
        self.vector_decoder = (
            DreamerV3MLP(feat, self.featurizer.out_features, depth=d.mlp_layers, num_cells=d.hidden)
            if self.vector_keys
            else None
        )
        self.image_decoder = ImageDecoder(feat, image_shape, d.cnn_depth, mults) if self.image_key else None
        self.reward_head = DreamerV3MLP(feat, NUM_BINS, depth=d.mlp_layers, num_cells=d.hidden, outscale=0.0)
        self.continue_head = DreamerV3MLP(feat, 1, depth=d.mlp_layers, num_cells=d.hidden)
        self.two_hot = SymExpTwoHot(NUM_BINS)
        self.actor_net = DreamerV3MLP(feat, n_actions, depth=d.mlp_layers, num_cells=d.hidden, outscale=0.01)
        self.value_net = DreamerV3MLP(feat, NUM_BINS, depth=d.mlp_layers, num_cells=d.hidden, outscale=0.0)
        self.unimix_logits = UnimixLogits(d.unimix)
        self._build_wrappers()

    # -- parameter groups --------------------------------------------------------------------------------------
    def world_model_params(self) -> list[nn.Parameter]:
        parts = [
            self.featurizer,
            self.encoder,
            self.prior,
            self.posterior,
            self.vector_decoder,
            self.image_decoder,
            self.reward_head,
            self.continue_head,
        ]
        return [p for m in parts if m is not None for p in m.parameters()]

    def components(self) -> dict[str, nn.Module]:
        """Named parts for the parameter table."""
        named = {
            "encoder": self.encoder,
            "rssm prior": self.prior,
            "rssm posterior": self.posterior,
            "vector decoder": self.vector_decoder,
            "image decoder": self.image_decoder,
            "reward head": self.reward_head,
            "continue head": self.continue_head,
            "actor": self.actor_net,
            "critic": self.value_net,
        }
        return {k: v for k, v in named.items() if v is not None}

    # -- tensordict wrappers -----------------------------------------------------------------------------------
    def _encode(self, prefix: tuple[str, ...]) -> list[TensorDictModule]:
        mods = []
        enc_in = []
        if self.vector_keys:
            mods.append(
                TensorDictModule(
                    self.featurizer,
                    in_keys=[(*prefix, k) for k in self.vector_keys],
                    out_keys=[(*prefix, "obs_features")],
                )
            )
            enc_in.append((*prefix, "obs_features"))
        if self.image_key:
            enc_in.append((*prefix, self.image_key))
        mods.append(TensorDictModule(self.encoder, in_keys=enc_in, out_keys=[(*prefix, "encoded_latents")]))
        return mods

    def _heads(self, prefix: tuple[str, ...]) -> list[TensorDictModule]:
        s, b = (*prefix, "state"), (*prefix, "belief")
        mods = [
            TensorDictModule(self.reward_head, in_keys=[s, b], out_keys=[(*prefix, "reward_logits")]),
            TensorDictModule(self.two_hot, in_keys=[(*prefix, "reward_logits")], out_keys=[(*prefix, "reward")]),
        ]
        return mods

    def _build_wrappers(self) -> None:
        nxt = ("next",)
        prior = TensorDictModule(
            self.prior,
            in_keys=["state", "belief", "action_onehot"],
            out_keys=[("next", "prior_logits"), ("next", "state"), ("next", "belief")],
        )
        posterior = TensorDictModule(
            self.posterior,
            in_keys=[("next", "belief"), ("next", "encoded_latents")],
            out_keys=[("next", "posterior_logits"), ("next", "state")],
        )
        wm = [*self._encode(nxt), RSSMRolloutV3(prior, posterior, reset_key="is_init", action_key="action_onehot")]
        feats = [("next", "state"), ("next", "belief")]
        if self.vector_decoder is not None:
            wm.append(TensorDictModule(self.vector_decoder, in_keys=feats, out_keys=[("next", "reco_obs_features")]))
        if self.image_decoder is not None:
            reco = ("next", f"reco_{self.image_key}")
            wm.append(TensorDictModule(self.image_decoder, in_keys=feats, out_keys=[reco]))
        wm += self._heads(nxt)
        wm.append(TensorDictModule(self.continue_head, in_keys=feats, out_keys=[("next", "continue_pred")]))
        self.world_model = TensorDictSequential(*wm)
        # imagination: the prior alone steps the latent; reward from the decoded two-hot head
        transition = TensorDictModule(
            self.prior, in_keys=["state", "belief", "action"], out_keys=["prior_logits", "state", "belief"]
        )
        self.imagination_model = WorldModelWrapper(transition, TensorDictSequential(*self._heads(())))
        self.continuation_model = TensorDictSequential(
            TensorDictModule(self.continue_head, in_keys=["state", "belief"], out_keys=["continue_logit"]),
            TensorDictModule(Sigmoid(), in_keys=["continue_logit"], out_keys=["continuation"]),
        )
        self.actor = self._actor("action")
        self.value = TensorDictSequential(
            TensorDictModule(self.value_net, in_keys=["state", "belief"], out_keys=["state_value_logits"]),
            TensorDictModule(self.two_hot, in_keys=["state_value_logits"], out_keys=["state_value"]),
        )
        self.policy = self._collection_policy()

    def _actor(self, action_key: str, state="state", belief="belief") -> ProbabilisticTensorDictSequential:
        return ProbabilisticTensorDictSequential(
            TensorDictModule(self.actor_net, in_keys=[state, belief], out_keys=["actor_raw_logits"]),
            TensorDictModule(self.unimix_logits, in_keys=["actor_raw_logits"], out_keys=["logits"]),
            ProbabilisticTensorDictModule(
                in_keys=["logits"],
                out_keys=[action_key],
                distribution_class=OneHotCategorical,
                return_log_prob=False,
                default_interaction_type=InteractionType.RANDOM,
            ),
        )

    def _collection_policy(self) -> TensorDictSequential:
        estimator = RSSMStateEstimatorV3(
            self.prior,
            self.posterior,
            in_keys=["state", "belief", "previous_action", "encoded_latents", "is_init"],
            out_keys=["post_state", "post_belief"],
        )
        carry = TensorDictModule(
            CarryState(),
            in_keys=["post_state", "post_belief", "action_onehot", "is_init"],
            out_keys=[("next", "state"), ("next", "belief"), ("next", "previous_action")],
        )
        to_index = TensorDictModule(OneHotToIndex(), in_keys=["action_onehot"], out_keys=["action"])
        return TensorDictSequential(
            *self._encode(()), estimator, self._actor("action_onehot", "post_state", "post_belief"), carry, to_index
        )

    def primer(self) -> TensorDictPrimer:
        """Zeros for the carried ``state [S]``, ``belief [D]`` and ``previous_action [A]`` at every reset."""
        return TensorDictPrimer(
            {
                "state": Unbounded(shape=(self.stoch,)),
                "belief": Unbounded(shape=(self.deter,)),
                "previous_action": Unbounded(shape=(self.n_actions,)),
            },
            default_value=0.0,
            expand_specs=True,
        )

    def imagination_env(self) -> DreamerEnv:
        """TorchRL's ``DreamerEnv`` over the prior and the reward head (batch size follows the reset tensordict)."""
        env = DreamerEnv(
            self.imagination_model, prior_shape=torch.Size([self.stoch]), belief_shape=torch.Size([self.deter])
        )
        env.observation_spec = Composite(state=Unbounded(self.stoch), belief=Unbounded(self.deter))
        env.state_spec = Composite(state=Unbounded(self.stoch), belief=Unbounded(self.deter))
        env.action_spec = OneHot(self.n_actions)
        env.reward_spec = Unbounded(1)
        return env


# --------------------------------------------------------------------------------------------------------------
# Losses, replay and the trainer
# --------------------------------------------------------------------------------------------------------------


def build_nets(cfg) -> DreamerNets:
    """The networks for ``cfg``'s env (probes its unbatched specs); ConfigError names a missing observation key."""
    obs_spec, act_spec = probe_specs(cfg)
    for key in cfg.dreamer.observation_keys:
        if key not in obs_spec.keys():
            raise ConfigError(
                f"dreamer.observation_keys: env '{cfg.env.id}' has no observation {key!r} (it has "
                f"{', '.join(sorted(map(str, obs_spec.keys())))})"
            )
    factor = 2 ** len(cfg.dreamer.cnn_mults)  # each conv stage halves the frame
    for key in cfg.dreamer.observation_keys:
        shape = tuple(obs_spec[key].shape)
        if is_image_spec(obs_spec[key]) and (shape[0] % factor or shape[1] % factor):
            raise ConfigError(
                f"dreamer.observation_keys: image {key!r} is {shape[0]}x{shape[1]}, but the image "
                f"encoder's {len(cfg.dreamer.cnn_mults)} stages (dreamer.cnn_mults) need height and width "
                f"divisible by {factor}"
            )
    n = getattr(getattr(act_spec, "space", None), "n", None)
    if n is None or act_spec.shape != torch.Size([]):
        raise ConfigError(
            f"env.id: DreamerV3 here needs a Categorical action (an index), '{cfg.env.id}' has "
            f"{type(act_spec).__name__}{tuple(act_spec.shape)}"
        )
    return DreamerNets(obs_spec, int(n), cfg.dreamer)


class DreamerLearner:
    """TorchRL's DreamerV3 losses over :class:`DreamerNets`, one optimiser each (world model, actor, critic).

    ``update(batch [B, L])``: world-model loss on the replay slices, imagination of ``horizon`` steps from every
    posterior state (``[B * L, H]``), REINFORCE actor loss with return normalisation, two-hot critic loss with the
    slow-critic regulariser; each step through :func:`freamer_rl.run.optim.optimizer_step`.
    """

    #: the scalars :meth:`update` returns (progress.csv columns, in this order)
    LOG_KEYS = (
        "loss_model_kl",
        "loss_model_reco",
        "loss_model_reward",
        "loss_actor",
        "loss_value",
        "loss_model_dyn",
        "loss_model_rep",
        "loss_model_continue",
        "actor_entropy",
        "return_scale",
        "imagined_return",
    )

    def __init__(self, nets: DreamerNets, d, optim) -> None:
        self.nets, self.d = nets, d
        targets, recos = [], []
        if nets.vector_keys:
            targets, recos = ["obs_features"], ["reco_obs_features"]
        if nets.image_key:
            targets, recos = [*targets, nets.image_key], [*recos, f"reco_{nets.image_key}"]
        self.model_loss = DreamerV3ModelLoss(
            nets.world_model,
            kl_mode="separate",
            lambda_dynamic=d.lambda_dynamic,
            lambda_representation=d.lambda_representation,
            free_bits=d.free_nats,
            unimix=d.unimix,
            lambda_continue=1.0,
            reco_symlog=[False] * len(targets),
            num_reward_bins=NUM_BINS,
        )
        self.model_loss.set_keys(pixels=targets, reco_pixels=recos)
        self.actor_loss = DreamerV3ActorLoss(
            nets.actor,
            nets.value,
            nets.imagination_env(),
            continuation_model=nets.continuation_model,
            imagination_horizon=d.horizon,
            use_reinforce=True,
            entropy_bonus=d.entropy_bonus,
        )
        self.actor_loss.make_value_estimator(ValueEstimators.TDLambda, gamma=d.gamma, lmbda=d.lmbda)
        self.value_loss = DreamerV3ValueLoss(
            nets.value,
            value_loss="two_hot",
            num_value_bins=NUM_BINS,
            actor_loss=self.actor_loss,
            slow_critic_regularization=d.slow_critic,
        )
        self.target = SoftUpdate(self.value_loss, tau=d.slow_critic_tau) if d.slow_critic else None
        self.params = {
            "model": nets.world_model_params(),
            "actor": list(nets.actor_net.parameters()),
            "value": [p for p in self.value_loss.value_model_params.values(True, True) if p.requires_grad],
        }
        lrs = {"model": optim.lr, "actor": d.actor_lr, "value": d.value_lr}  # the world model's is the optim section
        self.optimizers = {k: torch.optim.Adam(p, lr=lrs[k], eps=optim.eps) for k, p in self.params.items()}
        self.clips = {"model": optim.max_grad_norm, "actor": d.actor_grad_clip, "value": d.value_grad_clip}
        self.stats = {k: StepStats(f"dreamer {k}") for k in self.params}

    def _step(self, name: str, loss: torch.Tensor) -> None:
        optimizer_step(loss.reshape(()), self.optimizers[name], self.params[name], self.clips[name], self.stats[name])

    def update(self, batch) -> dict[str, torch.Tensor]:
        """One update on replay slices ``batch [B, L]``; returns detached scalar losses."""
        losses, post = self.model_loss(batch)
        kl = losses["loss_model_dynamic"] + losses["loss_model_representation"]
        model_total = kl + losses["loss_model_reco"] + losses["loss_model_reward"] + losses["loss_model_continue"]
        self._step("model", model_total)
        start = post.get("next").select("state", "belief").reshape(-1)  # detached: [B * L]
        actor_losses, imagined = self.actor_loss(start)
        self._step("actor", actor_losses["loss_actor"])
        value_losses, _ = self.value_loss(imagined.detach())
        self._step("value", value_losses["loss_value"])
        if self.target is not None:
            self.target.step()
        out = {
            "loss_model_kl": kl,
            "loss_model_dyn": losses["loss_model_dynamic"],
            "loss_model_rep": losses["loss_model_representation"],
            "loss_model_reco": losses["loss_model_reco"],
            "loss_model_reward": losses["loss_model_reward"],
            "loss_model_continue": losses["loss_model_continue"],
            "loss_actor": actor_losses["loss_actor"],
            "actor_entropy": actor_losses["actor_entropy"],
            "return_scale": actor_losses["return_scale"],
            "loss_value": value_losses["loss_value"],
            "imagined_return": imagined["lambda_target"].mean(),
        }
        return {k: out[k].detach().reshape(()) for k in self.LOG_KEYS}

    def state_dict(self) -> dict:
        return {
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "retnorm": self.actor_loss.retnorm.state_dict(),
            "value_loss": self.value_loss.state_dict(),
            "steps": {k: s.state_dict() for k, s in self.stats.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        self.value_loss.load_state_dict(state["value_loss"])
        self.actor_loss.retnorm.load_state_dict(state["retnorm"])
        for k, o in self.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        for k, s in self.stats.items():
            s.load_state_dict(state["steps"][k])


class SequenceReplay:
    """Collected rows ``[N envs, T steps]`` kept as ``N`` sequences in a TorchRL ``LazyTensorStorage``; ``sample()``
    draws ``batch_size`` stored sequences and a random window of ``length`` steps in each -> ``[B, L]``.

    A stored step is what the world model trains on: the posterior ``state`` / ``belief`` the policy computed on
    its observation (zeros at an episode start), ``action_onehot``, ``is_init`` and ``("next", obs / reward /
    done / terminated)``. Episode ends inside a window are handled by ``is_init`` (the rollout resets there).
    """

    def __init__(self, capacity_frames: int, steps: int, batch_size: int, length: int, obs_keys: list[str]):
        self.steps, self.length, self.obs_keys = steps, length, obs_keys
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(max(capacity_frames // steps, 1)), batch_size=batch_size)

    def __len__(self) -> int:
        return len(self.buffer) * self.steps

    def extend(self, data) -> None:
        nxt = data.get("next")
        keep = data.select("action_onehot", "is_init")
        keep.set("state", nxt.get("state"))
        keep.set("belief", nxt.get("belief"))
        keep.set("next", nxt.select(*self.obs_keys, "reward", "done", "terminated"))
        self.buffer.extend(keep.reshape(-1, data.shape[-1]).clone())

    def sample(self):
        seqs = self.buffer.sample()  # [B, T]
        b = seqs.shape[0]
        offsets = torch.randint(0, self.steps - self.length + 1, (b, 1))
        idx = offsets + torch.arange(self.length)
        rows = torch.arange(b).unsqueeze(-1)
        return seqs.apply(lambda x: x[rows, idx], batch_size=[b, self.length])


class DreamerTrainer(RunLoop):
    """DreamerV3 through the shared run loop: collect with the online posterior, learn from replay.

    ``_learn(data)`` adds the batch to the replay; once ``dreamer.prefill_frames`` are stored it runs one update
    per ``dreamer.train_every`` collected frames (the fraction carries over). The replay buffer is **not**
    checkpointed: a resumed run refills ``dreamer.prefill_frames`` (acting with the restored policy) before
    it updates again; model, optimisers, return normaliser and slow critic are restored.
    """

    trainer_name = "dreamer_v3"
    structural = STRUCTURAL

    def __init__(self, cfg, run_dir, *, resume: bool = True) -> None:
        super().__init__(cfg, run_dir)
        d = cfg.dreamer
        self.nets = build_nets(cfg).to(self.device)
        self.learner = DreamerLearner(self.nets, d, cfg.optim)
        steps = d.frames_per_batch // cfg.env.num_envs
        self.replay = SequenceReplay(
            d.replay_capacity, steps, d.batch_size, d.sequence_length, list(d.observation_keys)
        )
        self.updates, self._credit = 0, 0.0
        self._last: dict[str, float] = {}
        self._start(resume)
        n = sum(p.numel() for p in self.nets.parameters())
        logger.info("run dir %s | DreamerV3 %s parameters | device %s", self.run_dir, f"{n:,}", self.device)

    @property
    def frames_per_batch(self) -> int:
        return self.cfg.dreamer.frames_per_batch

    def _policy(self):
        return self.nets.policy

    def _primers(self) -> list:
        return [self.nets.primer()]

    def _env_transforms(self) -> list:
        return corruption_transforms(self.cfg.env.corrupt, "train")

    def _learn(self, data) -> dict[str, float]:
        d = self.cfg.dreamer
        self.replay.extend(data)
        if len(self.replay) < d.prefill_frames:
            self._credit = 0.0
        else:
            self._credit += data.numel() / d.train_every
        means = LogMeans()
        n = int(self._credit)
        for _ in range(n):
            means.add(self.learner.update(self.replay.sample()))
        self._credit -= n
        self.updates += n
        if n:
            self._last = means.means()
        # the same columns before the first update (prefill, also after a resume): NaN until trained
        return {**{k: math.nan for k in DreamerLearner.LOG_KEYS}, **self._last, "updates": float(self.updates)}

    def _extra_row(self) -> dict:
        return {"replay_frames": len(self.replay)}

    def _extra_summary(self) -> dict:
        return {"updates": self.updates}

    def _model_state(self) -> dict:
        return {"model": self.nets.state_dict(), "learner": self.learner.state_dict(), "updates": self.updates}

    def _load_model_state(self, ckpt: dict, path) -> None:
        self.nets.load_state_dict(ckpt["model"])
        self.learner.load_state_dict(ckpt["learner"])
        self.updates = int(ckpt["updates"])


@torch.no_grad()
def evaluate(
    path,
    *,
    episodes: int = 20,
    deterministic: bool = False,
    num_envs: int | None = None,
    seed: int = 12345,
    corrupt: list | None = None,
) -> dict:
    """Episodes of a DreamerV3 checkpoint's collection policy (online posterior + actor) in its config's env.

    ``deterministic``: the actor takes its most likely action; the posterior latent is still sampled (as in
    DreamerV3's own evaluation).
    """
    ckpt, cfg = read_checkpoint_config(path, DreamerConfig)
    torch.set_num_threads(cfg.run.threads)
    nets = build_nets(cfg)
    try:  # the config is the checkpoint's own: only a damaged or hand-edited file fails here
        nets.load_state_dict(ckpt["model"])
    except RuntimeError as err:
        raise CheckpointError(f"checkpoint {path}: weights do not fit the networks of its own config") from err
    nets.eval()
    result = run_episodes(
        cfg,
        nets.policy,
        [nets.primer()],
        episodes=episodes,
        deterministic=deterministic,
        num_envs=num_envs,
        seed=seed,
        corrupt=corrupt,
    )
    return {"checkpoint": str(path), **result, "frames_trained": ckpt.get("frames")}


def train(cfg: DreamerConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    """Train DreamerV3 with ``cfg``; returns the run summary (``summary.json``). See :class:`DreamerTrainer`."""
    return DreamerTrainer(cfg, resolve_run_dir(cfg, run_dir), resume=resume).train()


def params(cfg: DreamerConfig) -> list[dict]:
    """Rows ``{"component", "trainable", "frozen"}`` per network, then ``Total`` (probes the env's specs)."""
    return parameter_rows(build_nets(cfg).components())
