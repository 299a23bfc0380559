"""Runs that survive faults and bad input: safe checkpoint loading, atomic rotated writes, run-dir locks, resume after
kill -9 and SIGTERM, run names that stay inside the output folder."""

from __future__ import annotations

import csv
import json
import os
import pickle
import random
import signal
import subprocess
import sys
import time
from collections import OrderedDict, deque
from pathlib import Path

import numpy as np
import pytest
import torch

from freamer_rl import cli
from freamer_rl.config.checks import run_name_problem
from freamer_rl.errors import CheckpointError, ConfigError, FreamerError
from freamer_rl.run.checkpoint import (
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    read_checkpoint,
    remove_stale_temps,
    save_checkpoint,
    to_plain,
)
from freamer_rl.run.loop import default_run_name
from freamer_rl.run.rundir import (
    RunDirLock,
    Terminated,
    catch_sigterm,
    interrupt_in_chain,
    restore_sigterm,
    surfaced_interrupts,
)
from freamer_rl.trainers.minigrid_ppo import Trainer
from freamer_rl.trainers.registry import load_config

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "recipes" / "tiny.yaml"
ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def tiny_cfg(*overrides):
    return load_config(TINY, list(overrides))


def progress_frames(run: Path) -> list[int]:
    with (run / "progress.csv").open(newline="") as f:
        return [int(r["frames"]) for r in csv.DictReader(f)]


class _Evil:
    """Unpickling this calls os.system: what weights_only loading must refuse."""

    def __init__(self, witness: Path) -> None:
        self.witness = witness

    def __reduce__(self):
        return (os.system, (f"touch {self.witness}",))


def _one_line(text: str) -> str:
    text = text.strip()
    assert text.startswith("error: ") and "\n" not in text and "Traceback" not in text, text
    return text


# ----------------------------------------------------------------------------------------------------------------------
# 1. weights_only loading
# ----------------------------------------------------------------------------------------------------------------------
def test_crafted_pickle_is_refused_everywhere(tmp_path, capsys):
    witness = tmp_path / "pwned"
    evil = tmp_path / "evil.pt"
    torch.save({"model": _Evil(witness), "config": {}, "format": "freamer_rl/1"}, evil)
    raw = tmp_path / "raw.pkl"  # a plain pickle, not a torch zip
    raw.write_bytes(pickle.dumps({"model": _Evil(witness)}))
    for path in (evil, raw):
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
        assert cli.main(["eval", str(path)]) == 2
        assert str(path) in _one_line(capsys.readouterr().err)
    assert "posix.system" in str(pytest.raises(CheckpointError, load_checkpoint, evil).value)
    # the health loader and a run's resume refuse it too
    from freamer_rl.health.agent import load_agent

    with pytest.raises(CheckpointError, match="refusing to load"):
        load_agent(evil)
    ckpt_dir = tmp_path / "run" / "checkpoints"
    ckpt_dir.mkdir(parents=True)
    (ckpt_dir / "checkpoint_000000128.pt").write_bytes(evil.read_bytes())
    (ckpt_dir / "latest").write_text("checkpoint_000000128.pt\n")
    with pytest.raises(CheckpointError, match="refusing to load"):
        Trainer(tiny_cfg(), tmp_path / "run")
    assert not witness.exists(), "a crafted checkpoint ran code"
    RunDirLock(tmp_path / "run").acquire().release()  # the failed Trainer released its lock


def test_to_plain_makes_payloads_weights_only_loadable(tmp_path):
    sd = OrderedDict(w=torch.ones(2))
    sd._metadata = {"": {"version": 1}}  # what nn.Module.state_dict() carries
    payload = {
        "format": "x/1",
        "frames": np.int64(7),
        "lr": np.float32(0.5),
        "arr": np.arange(3),
        "q": deque([1.0, 2.0]),
        "path": tmp_path,
        "flag": np.bool_(True),
        "model": sd,
        "nested": [(np.int32(1), "a")],
    }
    plain = to_plain(payload)
    assert plain["model"] is sd, "unchanged state dicts keep their identity and _metadata"
    path = save_checkpoint(tmp_path, payload)
    back = read_checkpoint(path)
    assert back["frames"] == 7 and type(back["frames"]) is int and back["q"] == [1.0, 2.0]
    assert back["path"] == str(tmp_path) and back["flag"] is True and back["nested"] == [(1, "a")]
    assert torch.equal(back["arr"], torch.arange(3)) and back["model"]._metadata == sd._metadata
    with pytest.raises(TypeError, match=r"payload\['bad'\]"):
        save_checkpoint(tmp_path, {"format": "x/1", "frames": 1, "bad": object()})
    with pytest.raises(ValueError, match="format"):
        save_checkpoint(tmp_path, {"frames": 1})


def test_damaged_checkpoints_are_one_line_errors(tmp_path):
    good = save_checkpoint(tmp_path / "a", {"format": "freamer_rl/1", "frames": 1, "model": {}, "config": {}})
    cases = {
        "truncated": good.read_bytes()[:200],
        "empty": b"",
        "text": b"not a checkpoint",
        "list": None,
    }
    for name, data in cases.items():
        path = tmp_path / f"{name}.pt"
        if data is None:
            torch.save([1, 2], path)
        else:
            path.write_bytes(data)
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value), name
    health_ckpt = save_checkpoint(
        tmp_path / "h", {"format": "freamer_rl.health/1", "model": {}, "config": {}}, filename="checkpoint.pt"
    )
    with pytest.raises(CheckpointError, match="not a MiniGrid checkpoint"):
        load_checkpoint(health_ckpt)


# ----------------------------------------------------------------------------------------------------------------------
# 2. the latest marker
# ----------------------------------------------------------------------------------------------------------------------
BAD_MARKERS = [
    "../outside.pt",
    "/etc/passwd",
    "sub/checkpoint_000000001.pt",
    "checkpoint_1.pt/../../x.pt",
    "..",
    "",
    "evil.pt",
    "checkpoint_..pt",
    "checkpoint_1.pt\x00",
    "..\\checkpoint_1.pt",
    "x" * 600,
]


@pytest.mark.parametrize("marker", BAD_MARKERS)
def test_latest_marker_must_name_a_checkpoint_file_inside(tmp_path, marker):
    ckpt_dir = tmp_path / "checkpoints"
    ckpt_dir.mkdir()
    (tmp_path / "outside.pt").write_bytes(b"x")
    (ckpt_dir / "latest").write_text(marker)
    with pytest.raises(CheckpointError, match="must name a checkpoint_"):
        latest_checkpoint(tmp_path)


def test_latest_marker_other_cases(tmp_path):
    ckpt_dir = tmp_path / "checkpoints"
    ckpt_dir.mkdir()
    (ckpt_dir / "latest").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(CheckpointError, match="marker"):
        latest_checkpoint(tmp_path)
    (ckpt_dir / "latest").write_text("checkpoint_000000128.pt")
    with pytest.raises(CheckpointError, match="does not exist"):
        latest_checkpoint(tmp_path)
    # a kill between the checkpoint's rename and the marker's: the newest complete file is used
    (ckpt_dir / "latest").unlink()
    for frames in (128, 256):
        (ckpt_dir / f"checkpoint_{frames:09d}.pt").write_bytes(b"x")
    assert latest_checkpoint(tmp_path).name == "checkpoint_000000256.pt"
    (ckpt_dir / "latest").write_text("checkpoint_000000128.pt")
    assert latest_checkpoint(tmp_path).name == "checkpoint_000000256.pt"
    assert latest_checkpoint(tmp_path / "nothing") is None


# ----------------------------------------------------------------------------------------------------------------------
# 3. one atomic, rotating writer
# ----------------------------------------------------------------------------------------------------------------------
def test_save_checkpoint_rotates_atomically(tmp_path, monkeypatch):
    for frames in range(1, 6):
        save_checkpoint(tmp_path, {"format": "t/1", "frames": frames})
    ckpt_dir = tmp_path / "checkpoints"
    assert [p.name for p in list_checkpoints(ckpt_dir)] == [f"checkpoint_{f:09d}.pt" for f in (3, 4, 5)]
    assert (ckpt_dir / "latest").read_text().strip() == "checkpoint_000000005.pt"
    # a write with a lower frame count (the oldest by name) is never the one rotated away
    path = save_checkpoint(tmp_path, {"format": "t/1", "frames": 2})
    assert path.is_file() and latest_checkpoint(tmp_path) == ckpt_dir / "checkpoint_000000005.pt"
    # a failing write leaves the previous file and marker intact and no temporary file
    before = path.read_bytes()

    def broken_save(obj, f, *a, **k):
        f.write(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(tmp_path, {"format": "t/1", "frames": 2})
    monkeypatch.undo()
    assert path.read_bytes() == before and read_checkpoint(path)["frames"] == 2
    assert not [p for p in ckpt_dir.iterdir() if p.name.startswith(".")]
    assert remove_stale_temps(ckpt_dir) == 0


def test_health_checkpoint_goes_through_the_atomic_writer(tmp_path, monkeypatch):
    sys.path.insert(0, str(ROOT / "tests" / "health"))
    from test_health_pipeline import TINY as HEALTH_TINY

    from freamer_rl.health.agent import build_agent, load_agent, save_agent
    from freamer_rl.health.config import load_health_config

    agent = build_agent(load_health_config(ROOT / "recipes" / "health" / "health_mlp.yaml", HEALTH_TINY))
    path = save_agent(agent, tmp_path, iteration=1, frames=np.int64(64))  # numpy values become plain ints
    assert path == tmp_path / "checkpoint.pt" and read_checkpoint(path)["frames"] == 64
    before = path.read_bytes()
    monkeypatch.setattr(torch, "save", lambda obj, f, *a, **k: (f.write(b"half"), 1 / 0))
    with pytest.raises(ZeroDivisionError):
        save_agent(agent, tmp_path, iteration=2, frames=128)
    monkeypatch.undo()
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]
    assert load_agent(tmp_path).cfg.encoder.kind == "mlp"


_WRITER_PAYLOAD_MB = 4


def _writer_child(run: Path, frames: int) -> None:
    """Write checkpoints in a loop until killed (forked child: torch is already imported)."""
    weights = torch.randn(_WRITER_PAYLOAD_MB * 262_144)
    try:
        while True:
            frames += 1
            save_checkpoint(run, {"format": "freamer_rl/1", "frames": frames, "model": {"w": weights}, "config": {}})
    finally:
        os._exit(0)


def test_kill_during_checkpoint_writes_never_corrupts(tmp_path):
    run = tmp_path / "run"
    rng = random.Random(0)
    loaded = corrupt = torn = 0
    frames = 0
    for _ in range(20):
        pid = os.fork()
        if pid == 0:
            _writer_child(run, frames)
        time.sleep(rng.uniform(0.05, 0.25))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        torn += remove_stale_temps(run / "checkpoints")  # writes the kill cut short
        latest = latest_checkpoint(run)
        if latest is None:
            continue
        for path in list_checkpoints(run / "checkpoints"):
            try:
                assert load_checkpoint(path)["model"]["w"].numel() == _WRITER_PAYLOAD_MB * 262_144
                loaded += 1
            except CheckpointError:
                corrupt += 1
        assert load_checkpoint(latest)["frames"] >= frames  # never goes back
        frames = load_checkpoint(latest)["frames"]
    assert corrupt == 0 and loaded > 0 and frames > 20
    print(f"{torn} of 20 kills cut a write short; {loaded} checkpoint loads, 0 corrupt")
    assert len(list_checkpoints(run / "checkpoints")) <= 3 + 1  # rotation (+1: killed before rotating)


# ----------------------------------------------------------------------------------------------------------------------
# 4. run-directory lock
# ----------------------------------------------------------------------------------------------------------------------
_HOLD = (
    "import sys, time; from freamer_rl.run.rundir import RunDirLock; lock = RunDirLock(sys.argv[1]).acquire(); "
    "print('locked', flush=True); time.sleep(60)"
)


def test_second_run_on_a_locked_dir_is_refused(tmp_path, capsys):
    run = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(run)], stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(FreamerError, match=rf"in use by another run \(pid {holder.pid} on "):
            Trainer(tiny_cfg(), run)
        assert cli.main(["train", str(TINY), "--run-dir", str(run)]) == 2
        assert f"pid {holder.pid}" in _one_line(capsys.readouterr().err)
        from freamer_rl.health.config import load_health_config
        from freamer_rl.trainers.health import train as train_health

        with pytest.raises(FreamerError, match="in use by another run"):
            train_health(load_health_config(None, ["logging.progress_bar=false"]), run)
        assert not (run / "checkpoints").exists() and not (run / "config.yaml").exists()
    finally:
        holder.kill()  # kill -9 releases the lock: no stale lock after a crash
        holder.wait()
    with RunDirLock(run) as lock:
        assert lock.held and str(os.getpid()) in (run / ".lock").read_text()
        with pytest.raises(FreamerError, match=f"pid {os.getpid()}"):
            RunDirLock(run).acquire()  # a second writer in the same process is refused as well
    assert (run / ".lock").read_text() == ""


# ----------------------------------------------------------------------------------------------------------------------
# 5 + 6. progress.csv on resume / fresh start, metrics per attempt, --no-resume
# ----------------------------------------------------------------------------------------------------------------------
def test_resume_rewrites_progress_and_fresh_start_truncates(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "progress.csv").write_text("frames,old\n999,1\n")
    trainer = Trainer(tiny_cfg(), run)
    assert (run / "progress.csv").read_text() == "", "a fresh start truncates an old progress.csv"
    trainer.train()
    assert progress_frames(run) == [128, 256]
    with (run / "progress.csv").open("a") as f:  # a row written after the last checkpoint, then kill -9
        f.write("384" + ",0" * 20 + "\n")
    Trainer(tiny_cfg("run.total_frames=512"), run).train()
    assert progress_frames(run) == [128, 256, 384, 512]
    assert sorted(p.name for p in (run / "metrics").iterdir()) == ["attempt_01", "attempt_02"]
    # --no-resume on a run with checkpoints: one line, and nothing changes on disk
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file() and p.name != ".lock"}
    assert cli.main(["train", str(TINY), "--run-dir", str(run), "--no-resume"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"run dir {run} already holds checkpoints; use another run.name or delete it" in err
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file() and p.name != ".lock"} == before


# ----------------------------------------------------------------------------------------------------------------------
# 7. SIGTERM
# ----------------------------------------------------------------------------------------------------------------------
def test_sigterm_checkpoints_and_restores_the_handler(tmp_path, monkeypatch):
    run = tmp_path / "run"
    trainer = Trainer(tiny_cfg("run.total_frames=384", "logging.checkpoint_every_frames=100000"), run)
    real_update, calls = trainer._update, []

    def terminated_on_second_batch(data):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return real_update(data)

    def previous(signum, frame):  # the caller's own handler, which train() must put back
        raise AssertionError("previous handler called")

    old = signal.signal(signal.SIGTERM, previous)
    try:
        monkeypatch.setattr(trainer, "_update", terminated_on_second_batch)
        with pytest.raises(Terminated):
            trainer.train()
        assert signal.getsignal(signal.SIGTERM) is previous
    finally:
        signal.signal(signal.SIGTERM, old)
    resumed = Trainer(tiny_cfg("run.total_frames=384"), run)
    assert resumed.frames == 128 and resumed.resumed_from is not None
    resumed.life.lock.release()


def test_an_error_caused_by_an_interrupt_is_raised_as_the_interrupt():
    def wrapped(interrupt):
        try:
            raise interrupt
        except KeyboardInterrupt:
            try:
                raise ValueError("inner cleanup")
            except ValueError as inner:
                raise RuntimeError("outer") from inner

    with pytest.raises(RuntimeError) as info:
        wrapped(Terminated("SIGTERM"))
    assert isinstance(interrupt_in_chain(info.value), Terminated)
    assert interrupt_in_chain(RuntimeError("plain")) is None
    with pytest.raises(Terminated):
        with surfaced_interrupts():
            wrapped(Terminated("SIGTERM"))
    with pytest.raises(ValueError, match="unrelated"):  # other errors pass through unchanged
        with surfaced_interrupts():
            raise ValueError("unrelated")


def _library_turns_it_into_its_own_error() -> None:
    raise RuntimeError("a library's own error while the interrupt unwound") from None


def _library_swallows_it() -> None:
    # seen in a suite worker: a library caught the first Terminated whole, the run trained on, and every later
    # SIGTERM was ignored as "already stopping"; now the loop stops at the batch end and checkpoints there
    pass


@pytest.mark.parametrize(
    "library, saved_at, warning",
    [
        (_library_turns_it_into_its_own_error, 128, None),
        (_library_swallows_it, 256, "caught inside a library and did not stop the run"),
    ],
)
def test_a_sigterm_inside_a_library_still_checkpoints_and_stops(
    tmp_path, monkeypatch, caplog, library, saved_at, warning
):
    run = tmp_path / "run"
    trainer = Trainer(tiny_cfg("run.total_frames=384", "logging.checkpoint_every_frames=100000"), run)
    real_update, calls = trainer._update, []

    def sigterm_inside_a_library_on_second_batch(data):
        calls.append(1)
        if len(calls) == 2:
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)  # the handler raises Terminated here
            except BaseException:  # noqa: BLE001 -- what the library does with it
                library()
        return real_update(data)

    monkeypatch.setattr(trainer, "_update", sigterm_inside_a_library_on_second_batch)
    with pytest.raises(Terminated):
        trainer.train()
    assert len(calls) == 2, "stopped within the batch or at its end"
    assert f"terminated by SIGTERM at {saved_at} frames; saved" in caplog.text
    assert warning is None or warning in caplog.text
    resumed = Trainer(tiny_cfg("run.total_frames=384"), run)
    assert resumed.frames == saved_at and resumed.resumed_from is not None
    resumed.life.lock.release()


def test_a_second_sigterm_raises_until_the_trainer_is_stopping_then_waits_for_the_checkpoint(caplog):
    token = catch_sigterm()
    try:
        for _ in range(2):  # the first swallowed: the second raises again instead of being ignored
            with pytest.raises(Terminated):
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)
        assert token.fired and token.swallowed == 1
        assert "the first did not stop the run" in caplog.text
        token.stopping_now()  # the trainer writes its checkpoint: later SIGTERMs are logged and ignored
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
        assert "already stopping, finishing the checkpoint first" in caplog.text
        token.raise_if_fired()  # nothing left to raise once the trainer is stopping
    finally:
        restore_sigterm(token)


def test_cli_exits_143_on_sigterm(tmp_path, monkeypatch, capsys, caplog):
    real_update = Trainer._update

    def terminated(self, data):
        os.kill(os.getpid(), signal.SIGTERM)
        return real_update(self, data)

    monkeypatch.setattr(Trainer, "_update", terminated)
    assert cli.main(["train", str(TINY), "--run-dir", str(tmp_path / "r")]) == 143
    assert "terminated (SIGTERM): rerun the same command" in capsys.readouterr().err
    assert "terminated by SIGTERM at 0 frames; saved" in caplog.text
    assert latest_checkpoint(tmp_path / "r") is not None


# ----------------------------------------------------------------------------------------------------------------------
# 8. run names
# ----------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["../escape", "a/b", "/abs/path", "..", ".", "a..b", "x\ny", "a\\b"])
def test_run_name_cannot_escape_output_dir(name):
    override = f"run.name={json.dumps(name)}"  # a YAML double-quoted string: \n is a real newline
    with pytest.raises(ConfigError, match="run.name"):
        load_config(TINY, [override])
    from freamer_rl.health.config import load_health_config

    with pytest.raises(ConfigError, match="run.name"):
        load_health_config(None, [override])


def test_default_run_name_is_one_folder():
    cfg = tiny_cfg()
    for env_id in ("ALE/Pong-v5", "../../etc", "a\\b"):
        cfg.env.id = env_id
        name = default_run_name(cfg)
        assert run_name_problem(name) is None, name
    assert run_name_problem("MultiRoom-N2-S4-s0-20250101-000000") is None


# ----------------------------------------------------------------------------------------------------------------------
# 9. kill -9, then the same command
# ----------------------------------------------------------------------------------------------------------------------
def _train_cmd(run: Path, total: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "freamer_rl.cli",
        "train",
        str(TINY),
        "--run-dir",
        str(run),
        f"run.total_frames={total}",
        "logging.checkpoint_every_frames=128",
    ]


@pytest.mark.slow  # two real CLI processes (~8 s each on 2 cores)
def test_kill_9_then_same_command_resumes(tmp_path):
    run = tmp_path / "run"
    proc = subprocess.Popen(_train_cmd(run, 100_000), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    try:
        deadline = time.monotonic() + 120
        while not list_checkpoints(run / "checkpoints"):
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "no checkpoint within 120 s"
            time.sleep(0.05)
        time.sleep(random.uniform(0.0, 1.0))  # somewhere in the next batch, maybe mid-write
    finally:
        proc.kill()
        proc.wait()
    killed_at = load_checkpoint(latest_checkpoint(run))["frames"]
    total = killed_at + 256
    done = subprocess.run(_train_cmd(run, total), capture_output=True, text=True, timeout=300, env=ENV)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"at {killed_at} frames" in done.stderr and "resumed from" in done.stderr
    frames = progress_frames(run)
    assert len(frames) == len(set(frames)), f"duplicate frames rows: {frames}"
    assert frames == list(range(128, total + 1, 128))
    assert load_checkpoint(latest_checkpoint(run))["frames"] == total
    assert (run / "metrics" / "attempt_02").is_dir()


@pytest.mark.slow  # two real CLI processes
def test_kill_9_then_same_command_resumes_the_health_trainer(tmp_path):
    """The health trainer checkpoints after every iteration: kill -9 mid-run, rerun the same command, it continues."""
    from test_health_pipeline import TINY as HEALTH_TINY

    run = tmp_path / "run"
    recipe = Path(__file__).resolve().parents[2] / "recipes" / "health" / "health_mlp.yaml"
    cmd = [
        sys.executable,
        "-m",
        "freamer_rl.cli",
        "train",
        str(recipe),
        *HEALTH_TINY,
        "collect.iterations=6",
        "--run-dir",
        str(run),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    try:
        deadline = time.monotonic() + 120
        while len(list_checkpoints(run / "checkpoints")) < 2:  # prefill and at least one iteration saved
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "no second checkpoint within 120 s"
            time.sleep(0.05)
        time.sleep(random.uniform(0.0, 0.5))
    finally:
        proc.kill()
        proc.wait()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=ENV)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "resumed from" in done.stderr
    iterations = [line.split(",")[0] for line in (run / "progress.csv").read_text().splitlines()[1:]]
    assert iterations == [str(i) for i in range(7)], iterations  # prefill row 0, then 1..6, none repeated
