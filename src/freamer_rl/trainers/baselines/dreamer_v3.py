"""DreamerV3 (``trainer: dreamer_v3``; schema in :mod:`freamer_rl.trainers.baselines.config`, networks in
:mod:`.dreamer_v3_nets`): TorchRL's DreamerV3 losses over the networks, sequence replay, the trainer on the shared run
loop, its evaluator and parameter table."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer
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
from freamer_rl.trainers.baselines.dreamer_v3_nets import NUM_BINS, DreamerNets, is_image_spec

logger = logging.getLogger(__name__)

#: what shapes DreamerV3's weights: the env and the ``dreamer`` architecture fields (the registry entry's)
STRUCTURAL = ("env", *(f"dreamer.{k}" for k in ARCHITECTURE_FIELDS))

__all__ = [
    "DreamerConfig",
    "DreamerLearner",
    "DreamerTrainer",
    "SequenceReplay",
    "STRUCTURAL",
    "build_nets",
    "train",
    "evaluate",
    "params",
]


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

    def _trainable_parameters(self) -> int:
        return sum(p.numel() for params in self.learner.params.values() for p in params)

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
