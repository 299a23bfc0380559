"""Actor-critic networks of the TorchRL baselines, built from the env's specs and the recipe's ``network`` section.

``kind: mlp`` -- every observation key cast to float, flattened and concatenated (MiniGrid's ``grid`` + ``direction``
is FlatObsWrapper's observation without the mission characters, which are constant in MultiRoom); ``kind: cnn`` --
the one image key (uint8 ``[H, W, C]``, scaled to [0, 1]; ``network.image_key`` names it among several) through the Nature-DQN conv stack, the other keys flattened
beside its features. ``shared: false`` gives the actor and the critic their own encoder (TorchRL's PPO-MLP);
``shared: true`` one trunk for both (the usual PPO-CNN). Either way the pieces are an ``ActorValueOperator``:
``common`` writes ``hidden_pi`` / ``hidden_v``, the heads of :mod:`freamer_rl.model.heads` read them. ``init``
(:func:`~freamer_rl.trainers.baselines.config.network_init`): the heads' and the encoder's orthogonal init, or every
Linear layer reset to PyTorch's own init (what ``torchrl.modules.MLP`` gives a TorchRL user; the stronger PPO-MLP on
MiniGrid, README "TorchRL baselines").

``kind: mlp_lstm`` / ``cnn_lstm`` -- the same encoder, then TorchRL's :class:`~torchrl.modules.LSTMModule`
(``network.lstm_hidden`` units, default ``network.hidden``; PyTorch's own LSTM init) whose output the heads read: a
recurrent PPO with memory matched to FreamerV1's DNC. ``shared: true`` -- one encoder and one LSTM for actor and
critic (like FreamerV1's trunk); ``shared: false`` -- an encoder and an LSTM each. The LSTM state lives in the
tensordict (``lstm_h`` / ``lstm_c``, or ``lstm_pi_*`` / ``lstm_v_*`` unshared; ``[*B, 1, lstm_hidden]``), declared
to the env by :func:`recurrent_primers` and reset wherever ``is_init`` (InitTracker) is set: one step at a time
while collecting, whole ``[N, T]`` sequences in recurrent mode (``torchrl.modules.set_recurrent_mode``) in the loss.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import TensorDictPrimer
from torchrl.modules import ActorValueOperator, LSTMModule

from freamer_rl.errors import EnvSetupError
from freamer_rl.model.action_prior import check_prior_key
from freamer_rl.model.heads import build_actor, build_critic
from freamer_rl.trainers.baselines.config import RECURRENT_KINDS, NetworkConfig, lstm_width, network_init

__all__ = [
    "ObservationEncoder",
    "ActorCriticTrunk",
    "build_actor_critic",
    "reset_linear_layers",
    "recurrent_primers",
    "is_recurrent",
]

PI, V = "hidden_pi", "hidden_v"


class ObservationEncoder(nn.Module):
    """``(*obs [*B, *shape_i]) -> [*B, hidden]``: a conv stack on the image (``image_index``) and/or an MLP on the
    flattened rest; ReLU after the convs, tanh (mlp) or ReLU (cnn) after the last linear layer."""

    def __init__(
        self,
        shapes: list[tuple[int, ...]],
        hidden: int,
        image_index: int | None = None,
        channels: tuple[int, ...] = (32, 64, 64),
    ) -> None:
        super().__init__()
        self.shapes = [tuple(s) for s in shapes]
        self.image_index = image_index
        flat = sum(int(torch.Size(s).numel()) for i, s in enumerate(self.shapes) if i != image_index)
        self.conv = None
        if image_index is not None:
            h, w, c = self.shapes[image_index]
            if min(h, w) < 36:  # 8x8 stride 4, 4x4 stride 2, 3x3: the smallest frame that leaves one cell
                raise EnvSetupError(
                    f"network.kind=cnn / cnn_lstm: the image is {h}x{w}; the Nature-DQN conv stack needs at least 36x36"
                )
            c1, c2, c3 = channels
            self.conv = nn.Sequential(
                nn.Conv2d(c, c1, 8, stride=4),
                nn.ReLU(),
                nn.Conv2d(c1, c2, 4, stride=2),
                nn.ReLU(),
                nn.Conv2d(c2, c3, 3, stride=1),
                nn.ReLU(),
                nn.Flatten(),
            )
            with torch.no_grad():
                flat += self.conv(torch.zeros(1, c, h, w)).shape[-1]
        act = nn.ReLU() if self.conv is not None else nn.Tanh()
        self.fc = nn.Sequential(nn.Linear(flat, hidden), act)
        nn.init.orthogonal_(self.fc[0].weight, gain=2**0.5)
        nn.init.zeros_(self.fc[0].bias)

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        batch = obs[0].shape[: obs[0].ndim - len(self.shapes[0])]
        parts = []
        for i, (x, shape) in enumerate(zip(obs, self.shapes)):
            if i == self.image_index:  # uint8 HWC -> float CHW in [0, 1]
                parts.append(self.conv(x.reshape(-1, *shape).float().permute(0, 3, 1, 2) / 255.0))
            else:  # scalar entries (MiniGrid's direction) become one column
                parts.append(x.reshape(-1, int(torch.Size(shape).numel())).float())
        return self.fc(torch.cat(parts, dim=-1)).reshape(*batch, -1)


class ActorCriticTrunk(nn.Module):
    """One encoder for both heads (``shared``) or one each: ``obs -> (hidden_pi, hidden_v)``."""

    def __init__(self, make_encoder, shared: bool) -> None:
        super().__init__()
        self.pi = make_encoder()
        self.v = None if shared else make_encoder()

    def forward(self, *obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.pi(*obs)
        return h, (h if self.v is None else self.v(*obs))


def _image_index(keys: list[str], shapes: list[tuple[int, ...]], image_key: str | None = None) -> int:
    """Position of the key the conv stack reads: ``image_key`` if given, else the one ``[H, W, C]`` key."""
    if image_key is not None:
        i = keys.index(image_key)
        if len(shapes[i]) != 3:
            raise EnvSetupError(f"network.image_key: {image_key!r} has shape {shapes[i]}, expected [H, W, C]")
        return i
    images = [i for i, s in enumerate(shapes) if len(s) == 3 and s[-1] in (1, 3, 4)]
    if len(images) != 1:
        raise EnvSetupError(
            f"network.kind=cnn / cnn_lstm needs exactly one image key ([H, W, C]) among network.observation_keys"
            f" {keys}; shapes {shapes} (name the one to convolve with network.image_key)"
        )
    return images[0]


def reset_linear_layers(module: nn.Module) -> None:
    """Every ``nn.Linear`` of ``module`` back to PyTorch's init: weights and biases U(+-1/sqrt(fan_in))."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            layer.reset_parameters()


def _recurrent_trunk(make_encoder, obs_keys: list[str], net: NetworkConfig) -> TensorDictSequential:
    """``obs -> encoder -> LSTMModule -> (hidden_pi, hidden_v)``, one chain (``shared``) or one per head."""
    width = lstm_width(net)
    branches = [("", PI)] if net.shared else [("_pi", PI), ("_v", V)]
    parts: list = []
    for tag, out in branches:
        features, h, c = f"features{tag}", f"lstm{tag}_h", f"lstm{tag}_c"
        parts.append(TensorDictModule(make_encoder(), in_keys=list(obs_keys), out_keys=[features]))
        parts.append(
            LSTMModule(
                input_size=net.hidden,
                hidden_size=width,
                in_keys=[features, h, c],
                out_keys=[out, ("next", h), ("next", c)],
            )
        )
    if net.shared:  # both heads read the one LSTM's output
        parts.append(TensorDictModule(nn.Identity(), in_keys=[PI], out_keys=[V]))
    return TensorDictSequential(*parts)


def build_actor_critic(observation_spec, action_spec, net: NetworkConfig) -> ActorValueOperator:
    """The baseline's ``ActorValueOperator`` for unbatched env specs; the action head follows the action spec.

    ``net.kind`` ``mlp_lstm`` / ``cnn_lstm``: the ``common`` part is recurrent (see the module docstring); give the
    env :func:`recurrent_primers` of the result.
    """
    missing = [k for k in net.observation_keys if k not in observation_spec.keys()]
    if missing:
        known = ", ".join(str(k) for k in observation_spec.keys())
        raise EnvSetupError(f"network.observation_keys: {missing} not in the env's observations ({known})")
    shapes = [tuple(observation_spec[k].shape) for k in net.observation_keys]
    image = _image_index(net.observation_keys, shapes, net.image_key) if net.kind in ("cnn", "cnn_lstm") else None

    def make_encoder() -> ObservationEncoder:
        return ObservationEncoder(shapes, net.hidden, image, tuple(net.cnn_channels))

    if net.kind in RECURRENT_KINDS:
        trunk = common = _recurrent_trunk(make_encoder, net.observation_keys, net)
        width = lstm_width(net)
    else:
        trunk = ActorCriticTrunk(make_encoder, net.shared)
        common = TensorDictModule(trunk, in_keys=list(net.observation_keys), out_keys=[PI, V])
        width = net.hidden
    check_prior_key(net.action_prior, observation_spec, action_spec, "network")
    actor = build_actor(action_spec, width, net.hidden, in_key=PI, prior=net.action_prior)
    critic = build_critic(width, net.hidden, in_key=V)
    if network_init(net) == "torch_default":
        for part in (trunk, actor, critic):
            reset_linear_layers(part)
    return ActorValueOperator(common, actor, critic)


def is_recurrent(net: nn.Module) -> bool:
    """Whether ``net`` holds an ``LSTMModule`` (its state must be primed and its batches kept in sequences)."""
    return any(isinstance(m, LSTMModule) for m in net.modules())


def recurrent_primers(net: nn.Module) -> list[TensorDictPrimer]:
    """One ``TensorDictPrimer`` per ``LSTMModule`` of ``net`` (declares and zero-initialises its ``h`` / ``c``
    state in the env's specs, so the collector feeds it back); ``[]`` for a feed-forward network."""
    return [m.make_tensordict_primer() for m in net.modules() if isinstance(m, LSTMModule)]
