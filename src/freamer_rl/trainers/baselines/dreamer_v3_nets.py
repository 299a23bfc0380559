"""DreamerV3's networks for :mod:`freamer_rl.trainers.baselines.dreamer_v3`: TorchRL's RSSM and heads, wired by tensordict keys.

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

import math

import torch
from tensordict.nn import (
    InteractionType,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictSequential,
)
from torch import nn
from torchrl.data import Composite, OneHot, Unbounded
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

#: what shapes DreamerV3's weights: the env and the ``dreamer`` architecture fields (the registry entry's)
__all__ = ["NUM_BINS", "is_image_spec", "DreamerNets"]

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
