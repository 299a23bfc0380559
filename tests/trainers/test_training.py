"""Integration: factory -> TorchRL Collector -> GAE -> ClipPPOLoss, the Trainer's run directory, resume, CLI errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ClipPPOLoss

from freamer_rl import cli
from freamer_rl.errors import CheckpointError, EnvSetupError
from freamer_rl.model.factory import build_freamer
from freamer_rl.run import env_registry
from freamer_rl.run.envs import make_batched_env, make_single_env
from freamer_rl.run.sequences import split_sequences
from freamer_rl.trainers.minigrid_ppo import Trainer, build_modules
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"


def tiny_cfg(*overrides):
    return load_config(TINY, list(overrides))


MODALITY_SETS = [
    ["state"],
    ["reward"],
    ["language", "reward"],
    ["state", "language", "reward"],
    ["state", "vision", "language", "reward"],
]


@pytest.mark.parametrize("mods", MODALITY_SETS, ids=["+".join(m) for m in MODALITY_SETS])
def test_policy_rollout_any_modality_subset(mods):
    cfg = tiny_cfg(f"model.modalities=[{', '.join(mods)}]")
    modules = build_modules(cfg)
    env = make_batched_env(cfg, modules.primers(), seed=0)
    td = env.rollout(6, modules.policy)
    assert td.batch_size == (2, 6)
    assert td["hidden"].shape == (2, 6, cfg.model.embed_dim)
    assert td["action"].shape == (2, 6)
    assert torch.isfinite(td["action_log_prob"]).all()
    for m in mods:
        assert td["refined", m].shape == (2, 6, cfg.model.embed_dim)
    # memory is carried: the root state at t+1 is the next state written at t (unless the episode restarted)
    mem, nxt_mem = td["dnc", "memory"], td["next", "dnc", "memory"]
    keep = ~td["next", "done"].squeeze(-1)[:, :-1]
    assert torch.allclose(mem[:, 1:][keep], nxt_mem[:, :-1][keep])
    env.close()


@pytest.mark.parametrize("batch", [(), (2,), (3, 2)])
def test_trunk_over_batch_shapes(batch):
    cfg = tiny_cfg("model.modalities=[state, vision, language, reward]")
    modules = build_modules(cfg)
    env = TransformedEnv(make_single_env(cfg), Compose(InitTracker(), *modules.primers()))
    td = env.reset()
    td = td.expand(*batch).clone() if batch else td
    out = modules.policy(td)
    assert out["logits"].shape == (*batch, env.action_spec.space.n)
    assert out["hidden"].shape == (*batch, cfg.model.embed_dim)
    assert out["next", "dnc", "memory"].shape == (*batch, cfg.model.dnc.memory_slots, cfg.model.dnc.memory_width)


def test_gates_start_near_identity():
    cfg = tiny_cfg("model.modalities=[state, vision, language, reward]")
    gates = build_modules(cfg).gates()
    assert gates["vision"] == pytest.approx(torch.sigmoid(torch.tensor(-5.0)).item(), rel=1e-5)
    assert gates["reward"] == pytest.approx(torch.sigmoid(torch.tensor(-1.0)).item(), rel=1e-5)
    assert all(g < 0.3 for g in gates.values())


def test_missing_modality_is_a_clear_error(monkeypatch):
    cfg = tiny_cfg()
    env = make_single_env(cfg)
    obs_spec = env.observation_spec.clone()
    del obs_spec["mission_tokens"]
    with pytest.raises(EnvSetupError, match="'language'.*mission_tokens"):
        build_freamer(obs_spec, env.action_spec, cfg.model, env_name="a language-free env")


def test_collector_gae_and_torchrl_clip_ppo_loss(tmp_path):
    """The policy as-is through Collector -> GAE -> TorchRL's ClipPPOLoss (actor and full value operator)."""
    cfg = tiny_cfg()
    trainer = Trainer(cfg, tmp_path / "run", resume=False)
    modules = trainer.modules
    data = trainer.collect_batch()
    assert data.batch_size == (2, 64)
    data = trainer.compute_advantage(data)
    seqs = split_sequences(data, cfg.ppo.sequence_length)
    assert seqs.batch_size == (16, 8)
    loss = ClipPPOLoss(modules.policy, modules.value, functional=False)
    with set_recurrent_mode(True):
        out = loss(seqs)
    # the recomputed log-probs (recurrent mode from the stored t=0 state) match the collected ones
    assert out["kl_approx"].abs().item() < 1e-4
    total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
    total.backward()
    grads = [p.grad for p in modules.trunk.parameters() if p.requires_grad]
    assert any(g is not None and g.abs().sum() > 0 for g in grads)


def test_trainer_run_directory_and_resume(tmp_path):
    run = tmp_path / "run"
    summary = Trainer(tiny_cfg(), run).train()
    assert summary["frames"] == 256
    for name in ("config.yaml", "run_info.json", "progress.csv", "learning_curve.png", "summary.json"):
        assert (run / name).is_file(), name
    info = json.loads((run / "run_info.json").read_text())
    assert "commit" in info
    header = (run / "progress.csv").read_text().splitlines()[0].split(",")
    for col in (
        "frames",
        "success_rate",
        "return_mean",
        "loss_objective",
        "loss_fm",
        "gate_state",
        "gate_reward",
        "fps",
    ):
        assert col in header
    assert any((run / "metrics").rglob("*.csv")), "TorchRL CSV logger files"
    # resume: same run dir, more frames -> continues from the checkpoint
    trainer = Trainer(tiny_cfg("run.total_frames=384"), run)
    assert trainer.frames == 256 and trainer.resumed_from is not None
    assert trainer.train()["frames"] == 384
    assert len((run / "progress.csv").read_text().splitlines()) == 1 + 3
    # another model config cannot resume this run
    with pytest.raises(CheckpointError, match="another config.*model.embed_dim"):
        Trainer(tiny_cfg("run.total_frames=512", "model.embed_dim=16"), run)


@pytest.mark.parametrize("into_encoders", [False, True])
def test_smoothness_term_reaches_encoders_only_when_asked(tmp_path, into_encoders):
    """aux.smooth_into_encoders=false (default): L_smooth of a training minibatch trains the fuser only."""
    trainer = Trainer(tiny_cfg(f"aux.smooth_into_encoders={str(into_encoders).lower()}"), tmp_path / "run")
    data = trainer.collect_batch()
    mb = split_sequences(trainer.compute_advantage(data), trainer.cfg.ppo.sequence_length)
    with set_recurrent_mode(True):
        mb = trainer.modules.trunk(mb)
    loss = trainer.aux_loss(mb)["loss_smooth"]
    fuser_params = {id(p) for p in trainer.modules.fuser.parameters()}
    upstream = [p for p in trainer.modules.trunk.parameters() if p.requires_grad and id(p) not in fuser_params]
    grads = torch.autograd.grad(loss, list(trainer.modules.fuser.parameters()) + upstream, allow_unused=True)
    fuser_grads, upstream_grads = grads[: len(fuser_params)], grads[len(fuser_params) :]
    reached = [g is not None and float(g.abs().sum()) > 0 for g in upstream_grads]
    assert any(g is not None and float(g.abs().sum()) > 0 for g in fuser_grads)
    assert any(reached) == into_encoders


def test_frozen_encoders_are_left_out_of_training(tmp_path):
    cfg = tiny_cfg("model.freeze_encoders=[language, reward]", "run.total_frames=128")
    trainer = Trainer(cfg, tmp_path / "run")
    frozen = {name: p.detach().clone() for name, p in trainer.modules.trunk.named_parameters() if not p.requires_grad}
    assert frozen, "the language and reward encoders should be frozen"
    assert all(p.requires_grad for p in trainer.params)  # the optimiser holds trainable parameters only
    trained = {n: p.detach().clone() for n, p in trainer.modules.trunk.named_parameters() if p.requires_grad}
    trainer.train()
    params = dict(trainer.modules.trunk.named_parameters())
    for name, before in frozen.items():
        assert torch.equal(params[name], before), name
    assert any(not torch.equal(params[n], before) for n, before in trained.items())  # the rest did train
    # the parameter table counts them as frozen
    from freamer_rl.model.params import parameter_table

    rows = {r["component"]: r for r in parameter_table(trainer.modules)}
    assert any(r["frozen"] > 0 for r in rows.values())


def test_two_worker_collection(tmp_path):
    summary = Trainer(
        tiny_cfg("collector.num_collectors=2", "env.num_envs=1", "run.total_frames=256"), tmp_path / "r"
    ).train()
    assert summary["frames"] == 256


def test_eval_command(tmp_path, capsys):
    run = tmp_path / "run"
    Trainer(tiny_cfg(), run).train()
    assert cli.main(["eval", str(run), "--episodes", "3"]) == 0
    out = capsys.readouterr().out
    result = json.loads(out)
    assert result["episodes"] == 3 and len(result["episode_returns"]) == 3
    assert result["success_rate"] == pytest.approx(sum(result["episode_successes"]) / 3)
    assert f'"episode_returns": {json.dumps(result["episode_returns"])}' in out  # one line, not one per episode
    # the same seed gives the same episodes whatever the process drew before (sampled actions, corruption)
    torch.manual_seed(999)
    torch.rand(1000)
    assert cli.main(["eval", str(run), "--episodes", "3", "--corrupt", "grid:salt:0.3"]) == 0
    first = json.loads(capsys.readouterr().out)["episode_returns"]
    torch.rand(77)
    assert cli.main(["eval", str(run), "--episodes", "3", "--corrupt", "grid:salt:0.3"]) == 0
    assert json.loads(capsys.readouterr().out)["episode_returns"] == first


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["ppo.lrr=1"], "unknown key 'ppo.lrr'"),
        (["optim.lr=fast"], "optim.lr: expected float"),
        (["env.id=MiniGrid-DoesNotExist-v0"], "MiniGrid-DoesNotExist-v0"),
        (
            [
                "model.vision.backbone=clip",
                "model.modalities=[vision]",
                "model.vision.clip_checkpoint=/nonexistent/clip.pt",
            ],
            "clip",
        ),
    ],
)
def test_cli_user_errors_are_one_line(tmp_path, capsys, args, fragment):
    code = cli.main(["train", str(TINY), *args, "--run-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
    assert fragment.lower() in err.lower()


def test_cli_checkpoint_errors(tmp_path, capsys):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    assert cli.main(["eval", str(bad)]) == 2
    assert "cannot read checkpoint" in capsys.readouterr().err
    assert cli.main(["eval", str(tmp_path / "missing.pt")]) == 2
    assert "not found" in capsys.readouterr().err


def test_cli_missing_modality(tmp_path, capsys, monkeypatch):
    real = env_registry.make_env

    def no_language(adapter, env_id, *, seed=None, **options):
        env = real(adapter, env_id, seed=seed, **options)
        del env.observation_spec["mission_tokens"]
        return env

    monkeypatch.setattr(env_registry, "make_env", no_language)
    assert cli.main(["train", str(TINY), "--run-dir", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "model.modalities includes 'language'" in err


def test_console_script_installed(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "freamer_rl.cli", "train", str(TINY), "ppo.epochs=many"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["error: ppo.epochs: expected int, got str 'many'"]


def test_interrupted_run_checkpoints_and_resumes(tmp_path, monkeypatch):
    run = tmp_path / "run"
    cfg = tiny_cfg("run.total_frames=384", "logging.checkpoint_every_frames=100000")
    trainer = Trainer(cfg, run)
    real_update, calls = trainer._update, []

    def interrupted_on_second_batch(data):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_update(data)

    monkeypatch.setattr(trainer, "_update", interrupted_on_second_batch)
    with pytest.raises(KeyboardInterrupt):
        trainer.train()
    resumed = Trainer(cfg, run)
    assert resumed.frames == 128  # the first batch was trained and checkpointed on interrupt
    assert resumed.train()["frames"] == 384
