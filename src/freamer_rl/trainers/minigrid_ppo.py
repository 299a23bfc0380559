"""Training loop: TorchRL Collector -> values/GAE -> sequence replay buffer -> ClipPPOLoss + auxiliary losses.

One call of :func:`train` owns one run directory::

    runs/<name>/config.yaml        resolved config
    runs/<name>/run_info.json      git commit, versions, command
    runs/<name>/progress.csv       one row per batch (frames, episodes, success, return, losses, gates, fps)
    runs/<name>/metrics/attempt_NN the selected TorchRL logger's files (CSV by default; wandb / tensorboard), one
                                   folder per start or resume (steps after the resumed checkpoint may repeat there;
                                   progress.csv is rewritten from the checkpoint and never repeats a row)
    runs/<name>/checkpoints/       the newest 3 checkpoint_<frames>.pt + ``latest`` (a rerun resumes from it)
    runs/<name>/.lock              held while a run writes (a second run on the directory is refused)
    runs/<name>/learning_curve.png success rate and return vs frames
    runs/<name>/summary.json       final figures

Design notes:
- Values for GAE are computed in *step mode* on the stored per-step DNC states (exact and one batched pass);
  GAE itself is TorchRL's, given precomputed ``state_value`` / ``("next", "state_value")``.
- Minibatches are whole sequences (``ppo.sequence_length`` steps) so the DNC trains in recurrent mode from the
  stored state at t=0 (TorchRL's recurrent pattern).
- The trunk runs once per minibatch; ClipPPOLoss receives the actor and value heads (TorchRL's shared-trunk option).
- The model stays in eval mode: no dropout and deterministic slot initialisation, so the log-probabilities the
  loss recomputes match the ones stored at collection time.
- The training machinery of the paper's App. A/G/K plugs in from the recipe: reward shaping
  (:mod:`freamer_rl.machinery.shaping`; GAE then reads ``("next", "shaped_reward")`` and success stays judged on the env
  reward), the success buffer (:class:`freamer_rl.machinery.success_buffer.SuccessReplay`), OGM-GE (:mod:`freamer_rl.machinery.ogm`:
  parameter groups and a hook before each optimiser step) and adaptive FM steps (inside the refiners).
"""

from __future__ import annotations

import copy
import functools
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from torchrl.modules import set_recurrent_mode
from torchrl.objectives.value import GAE

from freamer_rl.config.checks import Range
from freamer_rl.config.loader import VALIDATORS
from freamer_rl.config.sections import (
    BASE_RANGES,
    BASE_RENAMED,
    PPO_RANGES,
    BaseConfig,
    PPOConfig,
    check_base,
    check_ppo_layout,
    clean_key,
)
from freamer_rl.errors import CheckpointError, ConfigError
from freamer_rl.layers.checks import set_value_checks
from freamer_rl.machinery.checks import check_machinery, privileged_information
from freamer_rl.machinery.config import MACHINERY_RANGES, OGMConfig, ShapingConfig, SuccessBufferConfig
from freamer_rl.machinery.mission import parser_stats
from freamer_rl.machinery.ogm import OGMGE
from freamer_rl.machinery.shaping import SHAPED_REWARD, RewardShaper, env_transforms
from freamer_rl.machinery.success_buffer import SuccessReplay, weighted_ppo_loss
from freamer_rl.model.checks import check_model_names, check_model_shapes
from freamer_rl.model.config import AUX_RENAMED, MODEL_RANGES, AuxConfig, ModelConfig
from freamer_rl.model.factory import FreamerModules, build_freamer
from freamer_rl.model.losses import FreamerAuxLoss, paired_modalities
from freamer_rl.model.modalities import MODALITIES
from freamer_rl.model.params import parameter_table
from freamer_rl.model.weights import load_model_state
from freamer_rl.run.corruption import corruption_transforms, eval_entries
from freamer_rl.run.envs import check_env_options, check_env_writes, probe_specs
from freamer_rl.run.evaluation import read_checkpoint_config, run_episodes
from freamer_rl.run.loop import RunLoop, resolve_run_dir
from freamer_rl.run.metrics import LogMeans
from freamer_rl.run.optim import StepStats, optimizer_step, restore_optimizer, scheduled_lr, set_lr
from freamer_rl.run.sequences import sequence_replay_buffer, split_sequences
from freamer_rl.trainers.ppo_loss import clip_ppo_loss

logger = logging.getLogger(__name__)

__all__ = ["FreamerConfig", "validate", "STRUCTURAL", "build_modules", "Trainer", "train", "evaluate", "params"]

#: config sections that shape FreamerV1's weights (a resume needs them equal; the registry entry's)
STRUCTURAL = ("model", "env")


# --------------------------------------------------------------------------------------------------------------
# Config: the shared base + FreamerV1's own sections
# --------------------------------------------------------------------------------------------------------------


@dataclass
class FreamerConfig(BaseConfig):
    """``trainer: minigrid_ppo`` (the default): env / collector / logging / run / optim, plus ``model``, ``ppo``,
    ``aux`` (auxiliary loss weights, Eq. 6), ``shaping``, ``success_buffer`` and ``ogm``."""

    model: ModelConfig = field(default_factory=ModelConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    aux: AuxConfig = field(default_factory=AuxConfig)
    shaping: ShapingConfig = field(default_factory=ShapingConfig)
    success_buffer: SuccessBufferConfig = field(default_factory=SuccessBufferConfig)
    ogm: OGMConfig = field(default_factory=OGMConfig)

    RANGES: ClassVar[dict[str, Range]] = {**BASE_RANGES, **PPO_RANGES, **MODEL_RANGES, **MACHINERY_RANGES}
    RENAMED: ClassVar[dict[str, str]] = {**BASE_RENAMED, **AUX_RENAMED}

    def reads_observation(self, key: str) -> bool:
        m = self.model
        return any(key in (m.observation_keys.get(name) or MODALITIES[name].default_keys) for name in m.modalities)


def validate(cfg: FreamerConfig) -> None:
    """Cross-field checks of a built FreamerConfig (types, unknown keys and number ranges are the loader's)."""
    check_base(cfg)
    check_env_writes(cfg)  # shaping terms the env cannot provide (R_lang on Crafter), refused at load
    check_env_options(cfg)  # env.options / env.eval_options the adapter does not take
    for i, c in enumerate(cfg.env.corrupt):
        if c.key.startswith("embed.") and (
            c.when != "eval" or c.kind != "gaussian" or c.key.split(".", 1)[1] not in cfg.model.modalities
        ):
            raise ConfigError(
                f"env.corrupt[{i}]: an embedding key (embed.<modality>, one of {cfg.model.modalities}) "
                f"takes kind gaussian when eval (Table 13's protocol), got {c.key} {c.kind} {c.when}"
            )
    check_model_names(cfg.model)
    check_model_shapes(cfg)
    if cfg.model.flow.reliability != "off" and not cfg.aux.lambda_fm:
        raise ConfigError(
            f"model.flow.reliability: {cfg.model.flow.reliability} standardises the refiners' scores by statistics "
            "the flow-matching loss gathers, but aux.lambda_fm is 0; give aux.lambda_fm > 0"
        )
    _check_paired_targets(cfg)
    check_machinery(cfg)
    check_ppo_layout(cfg)


def _check_paired_targets(cfg: FreamerConfig) -> None:
    """``model.flow.targets=paired`` needs the FM loss on, clean copies, and each of them read by the model and
    corrupted during training (else every pair is a clean embedding and itself)."""
    copies = cfg.env.clean_copies
    if cfg.model.flow.targets != "paired":
        if copies:
            raise ConfigError(
                f"env.clean_copies: {copies} are targets of model.flow.targets=paired, which is "
                f"{cfg.model.flow.targets!r} here; drop env.clean_copies or set model.flow.targets=paired"
            )
        return
    if not cfg.aux.lambda_fm:
        raise ConfigError("model.flow.targets: paired trains through the flow-matching loss, but aux.lambda_fm is 0")
    if not copies:
        raise ConfigError(
            "model.flow.targets: paired needs env.clean_copies, the observation keys whose training corruption the "
            "refiners learn to undo (e.g. env.clean_copies=[grid])"
        )
    trained = {c.key.split("[", 1)[0] for c in cfg.env.corrupt if c.when in ("train", "both")}
    for key in copies:
        if not cfg.reads_observation(key):
            raise ConfigError(f"env.clean_copies: the model reads no observation {key!r}, so it has nothing to pair")
        if key not in trained:
            raise ConfigError(
                f"env.clean_copies: {key!r} is not corrupted during training (env.corrupt with when train or both), "
                "so its pairs would be a clean embedding and itself"
            )


VALIDATORS[FreamerConfig] = validate


def build_modules(cfg: FreamerConfig) -> FreamerModules:
    obs_spec, act_spec = probe_specs(cfg)
    return build_freamer(obs_spec, act_spec, cfg.model, env_name=f"env '{cfg.env.id}'")


# --------------------------------------------------------------------------------------------------------------
# FreamerV1's PPO (the run loop itself is freamer_rl.run.loop.RunLoop, shared with the baselines)
# --------------------------------------------------------------------------------------------------------------


class Trainer(RunLoop):
    """PPO on FreamerV1 with TorchRL parts. ``Trainer(cfg, run_dir).train()``; see the module docstring."""

    trainer_name = "minigrid_ppo"
    trainer_label = "FreamerV1 PPO"  # the registry key is historical: it trains MiniGrid, gym and Crafter envs alike
    structural = STRUCTURAL

    def __init__(self, cfg: FreamerConfig, run_dir: str | Path, *, resume: bool = True) -> None:
        super().__init__(cfg, run_dir)
        if self.device.type != "cpu":  # their host syncs would stall the accelerator once per layer call
            set_value_checks(False)
            logger.info("run.device=%s: the layers' eager value checks (NaN inputs, index ranges) are off", self.device)
        self.modules = build_modules(cfg)
        # model, losses, replay storage and (created after the move) the optimiser state live on run.device;
        # the envs stay on the CPU (the Collector moves observations to the policy's device)
        self.modules.actor_value.to(self.device)
        self.modules.actor_value.eval()  # see module docstring: deterministic trunk for consistent log-probs
        p = cfg.ppo
        # per-step losses with the success buffer, weighted by its truncated importance weights (App. G.3)
        reduction = "none" if cfg.success_buffer.enabled else None
        self.ppo_loss = clip_ppo_loss(self.modules.actor, self.modules.critic, p, reduction=reduction).to(self.device)
        self.gae = GAE(gamma=p.gamma, lmbda=p.gae_lambda, value_network=None, average_gae=False)
        # reward shaping (App. G.1-G.2, A.5): PPO trains on ("next", "shaped_reward"); success uses the env reward
        self.shaper = RewardShaper(
            cfg,
            self.modules.modalities,
            cfg.model.embed_dim,
            _action_count(self.modules.actor),
            self.device,
            gamma=p.gamma,
        )
        if self.shaper.active:
            self.gae.set_keys(reward=SHAPED_REWARD)
        self._shaping_logs: dict[str, float] = {}
        # App. G.3: successful episodes replayed with an off-policy correction (None when the recipe leaves it off)
        self.replay = SuccessReplay.from_config(cfg, self.modules, self.device, ("next", self.gae.tensor_keys.reward))
        self.aux_loss = FreamerAuxLoss(
            self.modules.refiners,
            lambda_fm=cfg.aux.lambda_fm,
            lambda_cl=cfg.aux.lambda_cl,
            # Eq. A16 smooths the FNO's mixed rows: the concat / mean fusers mix no rows, so it is off with them
            lambda_smooth=cfg.aux.lambda_smooth if cfg.model.fusion == "fno" else 0.0,
            noise_std=cfg.model.flow.noise_std,
            relative_noise=cfg.model.flow.noise_scale == "relative",
            smooth_fuser=None if cfg.aux.smooth_into_encoders else self.modules.fuser,
            modalities=self.modules.modalities,
            clean_keys={k: clean_key(k) for k in cfg.env.clean_copies} if cfg.model.flow.targets == "paired" else None,
            encoders=self.modules.encoders,
            paired_modalities=paired_modalities(
                self.modules.modalities, cfg.env.clean_copies, cfg.model.observation_keys
            ),
            presence_keys=cfg.model.presence_keys,
        ).to(self.device)
        # built once: a new buffer per batch costs time and logs TorchRL's storage INFO line every batch
        self._sequence_buffer = sequence_replay_buffer(
            p.frames_per_batch // p.sequence_length, p.minibatch_size // p.sequence_length, device=self.device
        )
        self.params = [q for q in self.modules.actor_value.parameters() if q.requires_grad]
        # OGM-GE (Section 4.3.5, App. K): a parameter group per modality's gate (Mode A) or refiner (Mode B)
        o = cfg.ogm
        self.ogm = (
            None
            if o.mode == "none"
            else OGMGE(self.modules.refiners, mode=o.mode, alpha=o.alpha, lr_scale=o.lr_scale, noise=o.noise, ema=o.ema)
        )
        lr = cfg.optim.lr
        groups = self.params if self.ogm is None else self.ogm.param_groups(lr, self.params)
        # fused Adam / foreach clipping: ~4x less optimiser overhead for the ~90 small parameter tensors
        self.optimizer = torch.optim.Adam(groups, lr=lr, eps=cfg.optim.eps, fused=True)
        self.step_stats = StepStats("PPO")
        # held from here until train() ends: a second run on this directory is refused instead of interleaving
        self._start(resume)
        frozen = sum(q.numel() for q in self.modules.actor_value.parameters() if not q.requires_grad)
        logger.info(
            "run dir %s | %s trainable parameters%s | device %s",
            self.run_dir,
            f"{sum(q.numel() for q in self.params):,}",
            f" ({frozen:,} frozen)" if frozen else "",
            self.device,
        )

    # -- RunLoop hooks -----------------------------------------------------------------------------------------
    @property
    def frames_per_batch(self) -> int:
        return self.cfg.ppo.frames_per_batch

    def _env_transforms(self) -> list:
        return [*env_transforms(self.cfg), *corruption_transforms(self.cfg.env.corrupt, "train")]

    def _policy(self):
        return self.modules.policy

    def _primers(self) -> list:
        return self.modules.primers()

    def _learn(self, data: TensorDictBase) -> dict[str, float]:
        return self._update(self._compute_advantage(data))

    def _compiling(self) -> bool:
        return self.cfg.model.compile

    transfer_sections = ("model",)

    def _load_weights(self, state: dict[str, Any], path: Path) -> None:
        load_model_state(self.modules, state, path)

    def _load_model_state(self, ckpt: dict[str, Any], path: Path) -> None:
        saved_ogm = (ckpt["config"].get("ogm") or {}).get("mode", "none")
        if saved_ogm != self.cfg.ogm.mode:  # OGM-GE's parameter groups shape the optimiser state
            raise CheckpointError(
                f"checkpoint {path} was trained with ogm.mode={saved_ogm}, this config has "
                f"ogm.mode={self.cfg.ogm.mode}; resume with the same mode"
            )
        load_model_state(self.modules, ckpt["model"], path)
        restore_optimizer(
            self.optimizer, ckpt["optimizer"], self.cfg.optim, int(ckpt["frames"]), self.cfg.run.total_frames
        )
        if "ppo_steps" in ckpt:  # absent in checkpoints written before the shared optimiser step
            self.step_stats.load_state_dict(ckpt["ppo_steps"])
        self.shaper.load_state_dict(ckpt.get("shaping", {}))
        if self.ogm is not None and ckpt.get("ogm"):
            self.ogm.load_state_dict(ckpt["ogm"])

    def _model_state(self) -> dict[str, Any]:
        return {
            "model": self.modules.actor_value.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "ppo_steps": self.step_stats.state_dict(),
            "shaping": self.shaper.state_dict(),
            "ogm": self.ogm.state_dict() if self.ogm is not None else None,
        }

    def _extra_row(self) -> dict[str, Any]:
        return {
            **{f"gate_{m}": g for m, g in self.modules.gates().items()},
            **self._shaping_logs,
            **(self.ogm.metrics() if self.ogm is not None else {}),
            **self._parser_logs(),
            **{f"fm_steps_{m}": float(r.last_steps) for m, r in self.modules.refiners.items() if r.adaptive_steps},
            **self._fallback_counts(),
        }

    def _extra_summary(self) -> dict[str, Any]:
        return {"gates": self.modules.gates(), **self._fallback_counts()}

    def _privileged_information(self) -> list[str]:
        return privileged_information(self.cfg)

    # -- inspection seams (tests, benchmarks): one step of what train() does, without training -----------------
    def collect_batch(self) -> TensorDictBase:
        """One training batch ``[*B, T]`` (``frames_per_batch`` frames) from fresh envs under the current policy."""
        collector = self._make_collector(self.frames_per_batch)
        try:
            return next(iter(collector))
        finally:
            collector.shutdown()

    def compute_advantage(self, data: TensorDictBase) -> TensorDictBase:
        """The values, reward shaping and GAE that a batch ``[*B, T]`` gets before the PPO epochs (in place)."""
        return self._compute_advantage(data)

    @torch.no_grad()
    def _compute_advantage(self, data: TensorDictBase) -> TensorDictBase:
        """Step-mode values on the stored states (root and next), then TorchRL's GAE.

        ``data`` is ``[*B, T]`` with time last (the collector's layout). Within an episode the next state of step
        ``t`` is the root state of step ``t + 1`` (the same observation and DNC memory, ``is_init`` False), so its
        value is taken from the root pass; only the steps whose episode ended and the last step of each row get
        their own value pass (about ``1/T`` of the batch plus the episode ends, instead of a second full pass).
        """
        value = self.modules.value
        keys = [k for k in value.in_keys if k != "is_init"]
        root = data.select(*keys, "is_init", strict=False)
        root_value = value(root)["state_value"]  # [*B, T, 1]
        need = data["next", "done"].reshape(data.shape).clone()  # the next root is a reset: V(next) is not there
        need[..., -1] = True  # the step after the batch was not collected
        next_value = torch.empty_like(root_value)
        next_value[..., :-1, :] = root_value[..., 1:, :]
        nxt = data["next"][need].select(*keys, strict=False)
        nxt.set("is_init", torch.zeros_like(data["is_init"][need]))  # a next state never starts an episode
        next_value[need] = value(nxt)["state_value"]
        data.set("state_value", root_value)
        data.set(("next", "state_value"), next_value)
        if self.shaper.active:
            self._shaping_logs = self.shaper(data, self.stats.success_rate)
        return self.gae(data)

    def update(self, data: TensorDictBase) -> dict[str, float]:
        """The PPO epochs on a batch that :meth:`compute_advantage` prepared; returns the averaged loss terms."""
        return self._update(data)

    # -- optimisation ---------------------------------------------------------------------------------------
    def _update(self, data: TensorDictBase) -> dict[str, float]:
        p = self.cfg.ppo
        lr = scheduled_lr(self.cfg.optim, self.frames, self.cfg.run.total_frames)
        set_lr(self.optimizer, lr)
        modulate = None if self.ogm is None else functools.partial(self.ogm.modulate, self.optimizer, lr)
        # the minibatches need the trunk's inputs, the action, its log-prob, advantage and value target: "next"
        # (GAE is done) and the trunk's intermediate outputs (recomputed on every minibatch) would only be copied
        seqs = split_sequences(data.exclude("next", *self.modules.trunk.out_keys), p.sequence_length)
        rb = self._sequence_buffer
        rb.empty()
        rb.extend(seqs)
        means = LogMeans()
        for _ in range(p.epochs):
            for _ in range(max(1, seqs.shape[0] // rb.batch_size)):
                mb = rb.sample()
                if self.replay is not None:
                    mb = self.replay.mix(mb)
                with set_recurrent_mode(True):
                    mb = self.modules.trunk(mb)
                loss_td = self.ppo_loss(mb)
                if self.replay is not None:  # per-step losses weighted by the truncated IS weights
                    loss_td = weighted_ppo_loss(loss_td, mb["loss_weight"])
                aux_td = self.aux_loss(mb)
                total = loss_td["loss_objective"] + loss_td["loss_critic"] + loss_td["loss_entropy"]
                for k in ("loss_fm", "loss_cl", "loss_smooth"):
                    if k in aux_td.keys():
                        total = total + aux_td[k]
                grad_norm = optimizer_step(
                    total,
                    self.optimizer,
                    self.params,
                    self.cfg.optim.max_grad_norm,
                    self.step_stats,
                    foreach=True,
                    before_step=modulate,
                )  # non-finite: skipped, counted
                if self.ogm is not None:  # each modality's FM-loss convergence drives its coefficient
                    self.ogm.observe({m: aux_td[f"fm_{m}"] for m in self.modules.refiners})
                means.add(
                    {
                        **self.modules.telemetry(mb),
                        "loss_total": total,
                        "grad_norm": grad_norm,
                        **{k: v for k, v in loss_td.items() if v.numel() == 1},
                        **{k: v for k, v in aux_td.items()},
                    }
                )
        out = means.means()
        if self.replay is not None:  # after the epochs: a batch's own successes are replayed from the next
            out["success_buffer_size"] = float(self.replay.store(data))
        return out

    def _fallback_counts(self) -> dict[str, int]:
        """Numerical fallbacks: slot-attention NaN guards and DNC memory clamps counted by the layers, optimiser
        steps skipped for a non-finite gradient (this run's count, kept across resumes), and compiled parts that
        fell back to eager execution (``model.compile``)."""
        mods = list(self.modules.trunk.modules())
        return {
            "nan_fallbacks": int(sum(int(getattr(m, "nan_fallbacks", 0)) for m in mods)),
            "dnc_clip_events": int(sum(int(getattr(m, "clip_events", 0)) for m in mods)),
            "skipped_steps": self.step_stats.skipped,
            "compile_fallbacks": int(sum(int(getattr(m, "compile_fallbacks", 0)) for m in mods)),
        }

    def _parser_logs(self) -> dict[str, float]:
        """Mission-parser cache hit rate and LLM fallbacks (App. A.1) of this process's parsers, with R_lang on."""
        if not self.cfg.shaping.language.weight:
            return {}
        stats = parser_stats()
        return {"parser_hit_rate": float(stats["hit_rate"]), "parser_fallbacks": float(stats["fallbacks"])}


def _action_count(actor) -> int:
    """Discrete actions of the policy head's spec, or the action's size for a continuous one (curiosity's input)."""
    spec = actor.spec["action"] if "action" in actor.spec.keys() else actor.spec
    n = getattr(getattr(spec, "space", None), "n", None)
    return int(n) if n is not None else int(spec.shape[-1]) if len(spec.shape) else 1


def train(cfg: FreamerConfig, run_dir: str | Path | None = None, *, resume: bool = True) -> dict[str, Any]:
    """Train FreamerV1 with the config; returns the run summary (also written to ``summary.json``).

    ``run_dir`` default: ``run.output_dir/run.name`` (or a name from env id, seed and time). ``resume=False`` on a
    directory that already holds checkpoints raises FreamerError (nothing is deleted).
    """
    return Trainer(cfg, resolve_run_dir(cfg, run_dir), resume=resume).train()


@torch.no_grad()
def evaluate(
    checkpoint: str | Path,
    *,
    episodes: int = 20,
    deterministic: bool = False,
    num_envs: int | None = None,
    seed: int = 12345,
    max_steps: int = 100_000,
    corrupt: list | None = None,
) -> dict[str, Any]:
    """Run ``episodes`` complete episodes with the checkpoint's policy (sampling unless ``deterministic``)."""
    path = Path(checkpoint)
    ckpt, cfg = read_checkpoint_config(path, FreamerConfig)
    torch.set_num_threads(cfg.run.threads)
    # eager: compiling (~20 s) costs more than it saves over an evaluation's few thousand steps (same maths)
    cfg.model.compile = False
    modules = build_modules(cfg)
    load_model_state(modules, ckpt["model"], path)
    modules.actor_value.eval()
    # ("embed", m) entries (key "embed.<m>", kind gaussian) perturb an embedding before its refiner (Table 13)
    entries = eval_entries(cfg.env.corrupt, corrupt)
    embedded = [c for c in entries if c.key.startswith("embed.")]
    if any(c.kind != "gaussian" for c in embedded):
        raise ConfigError("env.corrupt: an embedding (embed.<modality>) takes kind gaussian only")
    embed = {c.key.split(".", 1)[1]: c.level for c in embedded}
    corrupt = [c for c in entries if c not in embedded]
    policy = modules.policy_with_embedding_noise(embed) if embed else modules.policy
    result = run_episodes(
        cfg,
        policy,
        modules.primers(),
        episodes=episodes,
        deterministic=deterministic,
        num_envs=num_envs,
        seed=seed,
        max_steps=max_steps,
        corrupt=corrupt,
        step_metrics=modules.telemetry,
    )
    result.update({f"gate_{m}": g for m, g in modules.gates().items()})
    result["embedding_noise"] = embed
    return {"checkpoint": str(path), **result, "frames_trained": ckpt.get("frames")}


def params(cfg: FreamerConfig) -> list[dict]:
    """:func:`~freamer_rl.model.params.parameter_table` of ``cfg``'s model built with random weights, so no CLIP
    weights are resolved. A pretrained tag or checkpoint changes the values of the weights, never their number;
    building the tower at random keeps ``freamer-rl params`` instant and offline."""
    cfg = copy.deepcopy(cfg)
    vision = cfg.model.vision
    vision.clip_pretrained, vision.clip_checkpoint, vision.allow_random_weights = None, None, True
    clip_log = logging.getLogger("freamer_rl.layers.clip_backbone")
    level = clip_log.level
    clip_log.setLevel(logging.ERROR)  # its "RANDOM weights" warning is the point here, not a problem
    try:
        return parameter_table(build_modules(cfg))
    finally:
        clip_log.setLevel(level)
