"""Checkpoint files: one writer (atomic, rotated) and one safe reader for MiniGrid and health runs.

Layout of a MiniGrid run's checkpoints::

    <run_dir>/checkpoints/checkpoint_<frames:09d>.pt   the newest KEEP files (older ones are rotated away)
    <run_dir>/checkpoints/latest                       the file name of the newest one (one line)

Guarantees:

- A checkpoint file is either absent or complete: it is written to a unique temporary file in the same folder
  (``tempfile.mkstemp``), flushed with ``fsync`` and renamed over the target with ``os.replace`` (atomic on POSIX),
  then the folder is fsynced so that the rename survives a power loss. The ``latest`` marker is written the same way
  *after* the checkpoint, so it never names a partial file. A kill at any moment leaves the previous good checkpoint.
- Rotation never deletes the file just written nor the one ``latest`` names.
- Files are read with ``torch.load(weights_only=True)``: a checkpoint holds only tensors and plain data (dicts,
  lists, tuples, numbers, strings, None), so a crafted file cannot run code when loaded. :func:`to_plain` converts
  numpy values and other near-plain values at save time so our own payloads always load that way.
- The ``latest`` marker must be a bare ``checkpoint_*.pt`` file name inside the folder (no ``/``, no ``..``).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import pickle
import re
import tempfile
import warnings
from collections import OrderedDict, deque
from pathlib import Path, PurePath
from typing import Any

import torch

from freamer_rl.config.loader import merge_dicts
from freamer_rl.errors import CheckpointError, FreamerError

logger = logging.getLogger(__name__)

__all__ = [
    "FORMAT",
    "KEEP",
    "CheckpointError",
    "check_checkpoint_config",
    "latest_checkpoint",
    "list_checkpoints",
    "load_checkpoint",
    "read_checkpoint",
    "remove_stale_temps",
    "resume_checkpoint",
    "run_file_errors",
    "save_checkpoint",
    "to_plain",
    "structural_differences",
]

FORMAT = "freamer_rl/1"  # the "format" entry of a MiniGrid checkpoint
KEEP = 3  # checkpoints kept per run
CHECKPOINT_DIR = "checkpoints"
LATEST = "latest"
_NAME_RE = re.compile(r"checkpoint_[A-Za-z0-9_.-]*\.pt")
_TMP_PREFIX = ".tmp-"  # leading dot: never matches checkpoint_*.pt, so a stale temp is never loaded or rotated
_UMASK = os.umask(0o022)
os.umask(_UMASK)  # mkstemp creates 0600 files; checkpoints get the permissions an ordinary open() would give


# ----------------------------------------------------------------------------------------------------------------------
# payload conversion
# ----------------------------------------------------------------------------------------------------------------------
_TORCH_ATOMS = (torch.Tensor, torch.dtype, torch.device, torch.Size)
_BUILTIN_ATOMS = (str, bytes, bool, int, float, type(None))


def to_plain(obj: Any, where: str = "payload") -> Any:
    """``obj`` with numpy scalars/arrays, deques and paths turned into what ``weights_only`` loading accepts.

    Returns the object itself when nothing needed converting (state dicts keep their type and ``_metadata``).
    Anything else (an arbitrary object) raises ``TypeError`` naming its place, at save time rather than at load
    time when the run could no longer resume.
    """
    if isinstance(obj, _TORCH_ATOMS) or type(obj) in _BUILTIN_ATOMS:
        return obj
    if isinstance(obj, _BUILTIN_ATOMS[:-1]):  # subclasses (IntEnum, str enums) would need their class at load time
        base = next(t for t in (bool, int, float, str, bytes) if isinstance(obj, t))
        return base(obj)
    if type(obj).__module__ == "numpy":  # numpy is optional here: no import needed to recognise its types
        if hasattr(obj, "shape") and getattr(obj, "ndim", 0) > 0:
            return torch.from_numpy(obj.copy())
        return obj.item()
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, dict):
        items = {k: to_plain(v, f"{where}[{k!r}]") for k, v in obj.items()}
        if all(items[k] is obj[k] for k in obj):
            return obj
        out = OrderedDict(items) if isinstance(obj, OrderedDict) else dict(items)
        if hasattr(obj, "_metadata"):
            out._metadata = obj._metadata  # type: ignore[attr-defined]
        return out
    if isinstance(obj, (list, tuple, deque)):
        items = [to_plain(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        if isinstance(obj, deque):
            return items
        if all(a is b for a, b in zip(items, obj)):
            return obj
        return type(obj)(items) if type(obj) in (list, tuple) else list(items)
    raise TypeError(f"{where}: a checkpoint holds tensors and plain data only, got {type(obj).__qualname__}")


# ----------------------------------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------------------------------
def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (no-op where directories cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


#: errors of the file system rather than of the program: the disk is full, the quota spent, the folder read-only
_STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS})


@contextlib.contextmanager
def run_file_errors(path: str | Path):
    """Within the block, an OSError of the storage (disk full, no permission, read-only folder) becomes one
    :class:`FreamerError` line naming ``path`` and saying that a rerun resumes; other errors pass unchanged.

    Every run-file writer goes through it (checkpoints, summary.json, progress.csv, learning_curve.png): otherwise a
    disk that fills mid-run ends in a PIL or torch traceback. The atomic writers leave the previous file intact.
    """
    try:
        yield
    except OSError as err:
        if err.errno not in _STORAGE_ERRNOS:
            raise
        reason = err.strerror or errno.errorcode.get(err.errno, str(err.errno))
        raise FreamerError(
            f"cannot write {path}: {reason} ({errno.errorcode.get(err.errno, err.errno)}); free disk space or fix "
            "the folder's permissions, then rerun the same command: the run resumes from its latest checkpoint"
        ) from err


def _atomic_write(path: Path, write) -> None:
    """``write(binary_file)`` into a unique temporary file next to ``path``, fsync, then rename it over ``path``.

    A storage error (ENOSPC, EACCES, ...) is one FreamerError line naming ``path`` (:func:`run_file_errors`)."""
    with run_file_errors(path):
        _atomic_write_unchecked(path, write)


def _atomic_write_unchecked(path: Path, write) -> None:
    fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if hasattr(os, "fchmod"):  # POSIX (Windows has it from Python 3.13 only)
                os.fchmod(f.fileno(), 0o666 & ~_UMASK)
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:  # a failed or interrupted write leaves no temporary file and the old target intact
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    _fsync_dir(path.parent)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically (readers see the old or the new content, never a mix)."""
    _atomic_write(Path(path), lambda f: f.write(text.encode()))


def save_checkpoint(run_dir: str | Path, payload: dict, keep: int = KEEP, *, filename: str | None = None) -> Path:
    """Write ``payload`` (a dict with a ``"format"`` entry) atomically; returns the file written.

    Default: ``<run_dir>/checkpoints/checkpoint_<payload["frames"]:09d>.pt``, then the ``latest`` marker, then
    rotation to the newest ``keep`` files. With ``filename`` (the health run's single ``checkpoint.pt``):
    ``<run_dir>/<filename>`` replaced atomically, no marker, no rotation.
    """
    run_dir = Path(run_dir)
    if not isinstance(payload, dict) or not isinstance(payload.get("format"), str):
        raise ValueError("a checkpoint payload is a dict with a 'format' string entry")
    payload = to_plain(payload)
    if filename is not None:
        if _bad_file_name(filename):
            raise ValueError(f"checkpoint file name must be a bare file name, got {filename!r}")
        with run_file_errors(run_dir):
            run_dir.mkdir(parents=True, exist_ok=True)
        path = run_dir / filename
        _atomic_write(path, lambda f: torch.save(payload, f))
        return path
    ckpt_dir = run_dir / CHECKPOINT_DIR
    with run_file_errors(ckpt_dir):
        ckpt_dir.mkdir(parents=True, exist_ok=True)
    path = ckpt_dir / f"checkpoint_{int(payload['frames']):09d}.pt"
    _atomic_write(path, lambda f: torch.save(payload, f))
    atomic_write_text(ckpt_dir / LATEST, path.name + "\n")
    _rotate(ckpt_dir, keep, protect={path.name})
    return path


def _rotate(ckpt_dir: Path, keep: int, protect: set[str]) -> None:
    try:
        named = _marker_name(ckpt_dir)
    except CheckpointError:
        named = None
    if named:
        protect = protect | {named}
    files = list_checkpoints(ckpt_dir)
    for old in files[: max(len(files) - keep, 0)]:
        if old.name not in protect:
            try:
                old.unlink()
            except FileNotFoundError:
                pass


def list_checkpoints(ckpt_dir: str | Path) -> list[Path]:
    """``checkpoint_*.pt`` files of a checkpoint folder, oldest first (zero-padded frame counts sort by name)."""
    ckpt_dir = Path(ckpt_dir)
    if not ckpt_dir.is_dir():
        return []
    return sorted(p for p in ckpt_dir.glob("checkpoint_*.pt") if p.is_file())


def remove_stale_temps(folder: str | Path) -> int:
    """Delete temporary files left by writes that were killed; call only while holding the run-dir lock."""
    removed = 0
    folder = Path(folder)
    if folder.is_dir():
        for tmp in folder.glob(f"{_TMP_PREFIX}*.tmp"):
            try:
                tmp.unlink()
                removed += 1
            except OSError:
                pass
    if removed:
        logger.info("removed %d temporary file(s) left by an interrupted write in %s", removed, folder)
    return removed


# ----------------------------------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------------------------------
def _bad_file_name(name: str) -> bool:
    return not name or name in (".", "..") or "/" in name or "\\" in name or "\0" in name or Path(name).is_absolute()


def _marker_name(ckpt_dir: Path) -> str | None:
    """The file name in ``ckpt_dir/latest`` (None without a marker); CheckpointError if it is not a bare name."""
    marker = ckpt_dir / LATEST
    if not marker.is_file():
        return None
    try:
        raw = marker.read_bytes()[:512].decode("utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise CheckpointError(f"cannot read checkpoint marker {marker}: {err}") from err
    name = raw.strip()
    if _bad_file_name(name) or ".." in name or not _NAME_RE.fullmatch(name):
        raise CheckpointError(
            f"checkpoint marker {marker} must name a checkpoint_*.pt file in {ckpt_dir}, got {name[:80]!r}"
        )
    return name


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The checkpoint a rerun resumes from: the one ``checkpoints/latest`` names, else the newest by name.

    The fallback covers a kill between writing a checkpoint and its marker (the file itself is complete).
    A marker that is not a bare ``checkpoint_*.pt`` name, or names a missing file, raises CheckpointError.
    """
    ckpt_dir = Path(run_dir) / CHECKPOINT_DIR
    name = _marker_name(ckpt_dir)
    if name is None:
        files = list_checkpoints(ckpt_dir)
        if files:
            logger.warning("no 'latest' marker in %s: using the newest file %s", ckpt_dir, files[-1].name)
        return files[-1] if files else None
    path = ckpt_dir / name
    if not path.is_file():
        raise CheckpointError(f"checkpoint marker {ckpt_dir / LATEST} names {name}, which does not exist")
    newer = [p for p in list_checkpoints(ckpt_dir) if p.name > name]
    if newer:  # killed after the checkpoint rename, before the marker's: the newer file is complete
        logger.warning("%s is newer than the 'latest' marker (%s): using it", newer[-1].name, name)
        return newer[-1]
    return path


def resume_checkpoint(run_dir: str | Path, resume: bool, refusal_hint: str) -> Path | None:
    """Clean a run dir up and pick the checkpoint a run resumes from (None: start fresh); call holding its lock.

    Deletes the temporary files of killed writes in ``run_dir`` and its checkpoint folder, then returns
    :func:`latest_checkpoint`. With ``resume`` False a run dir that holds any checkpoint raises :class:`FreamerError`
    ending in ``refusal_hint`` (starting over would rotate the old checkpoints away; nothing is ever deleted here).
    """
    run_dir = Path(run_dir)
    ckpt_dir = run_dir / CHECKPOINT_DIR
    for folder in (run_dir, ckpt_dir):  # temporary files of killed writes (we hold the lock: no writer)
        remove_stale_temps(folder)
    path = latest_checkpoint(run_dir)
    if not resume and (path is not None or list_checkpoints(ckpt_dir)):
        raise FreamerError(f"run dir {run_dir} already holds checkpoints; use another run.name or {refusal_hint}")
    return path


def _first_line(err: BaseException) -> str:
    """One line of a (possibly multi-line) torch.load error, preferring the line that names the culprit."""
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    for ln in lines:
        if "unsupported global" in ln.lower() or "unsupported operand" in ln.lower():
            return ln[:200]
    return (lines[0] if lines else "empty or truncated file")[:200]


def read_checkpoint(path: str | Path, fmt: str | None = None) -> dict:
    """Load a checkpoint dict with ``weights_only=True``; every failure is one CheckpointError line naming the file.

    ``fmt``: the ``"format"`` entry the file must carry (None: any).
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        with warnings.catch_warnings():  # a raw pickle triggers a protocol warning: the error below says it all
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        line = _first_line(err)
        if "global" in line.lower():  # weights_only refused a Python object: possibly a crafted file
            raise CheckpointError(
                f"refusing to load checkpoint {path}: it holds a Python object, not only tensors and plain data "
                f"({line})"
            ) from err
        raise CheckpointError(
            f"cannot read checkpoint {path}: not a torch checkpoint of tensors and plain data ({line})"
        ) from err
    except Exception as err:  # torch.load raises many types (zip, EOF, OS); report the file, keep the cause
        raise CheckpointError(
            f"cannot read checkpoint {path}: {type(err).__name__}: {_first_line(err)} (damaged, truncated or not a "
            f"torch file)"
        ) from err
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a freamer_rl checkpoint (it holds a {type(ckpt).__name__})")
    if fmt is not None and ckpt.get("format") != fmt:
        raise CheckpointError(f"{path} is not a {fmt} checkpoint (format {ckpt.get('format')!r})")
    return ckpt


def load_checkpoint(path: str | Path) -> dict:
    """A MiniGrid run's checkpoint (see :func:`read_checkpoint`), checked for its ``model``/``config`` entries."""
    path = Path(path)
    ckpt = read_checkpoint(path)
    if "model" not in ckpt or "config" not in ckpt:
        raise CheckpointError(f"{path} is not a freamer_rl checkpoint (no 'model'/'config' entries)")
    if ckpt.get("format", FORMAT) != FORMAT:
        fmt = ckpt.get("format")
        raise CheckpointError(f"{path} is not a MiniGrid checkpoint (format {fmt!r}, expected {FORMAT!r})")
    return ckpt


def _structural_diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    diffs = []
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        name = f"{prefix}.{key}" if prefix else key
        if key == "gate_init":  # initial values only: the weights carry what was learnt from them
            continue
        if isinstance(va, dict) and isinstance(vb, dict):
            diffs += _structural_diff(va, vb, name)
        elif va != vb:
            diffs.append(f"{name}: checkpoint {va!r} vs now {vb!r}")
    return diffs


def _section(config: dict, dotted: str) -> Any:
    node: Any = config
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


def structural_differences(
    saved: dict, current: dict, structural: tuple[str, ...], defaults: dict | None = None
) -> list[str]:
    """``"name: checkpoint X vs now Y"`` for every difference of the ``structural`` entries (sections such as
    ``model``, or single fields such as ``dreamer.deter``) between a saved config mapping and the current one.
    ``defaults`` (the schema's default mapping) fills fields a later release added into the saved sections: a
    checkpoint written before ``model.flow.adaptive_steps`` existed was trained with it off (the default)."""
    diffs = []
    for name in structural:
        old, new = _section(saved, name), _section(current, name)
        default = _section(defaults or {}, name)
        if isinstance(old, dict) and isinstance(default, dict):
            old = merge_dicts(default, old)
        if isinstance(old, dict) and isinstance(new, dict):
            diffs += _structural_diff(old, new, name)
        elif old != new:
            diffs.append(f"{name}: checkpoint {old!r} vs now {new!r}")
    return diffs


def check_checkpoint_config(
    saved: dict, current: dict, path: Path, structural: tuple[str, ...], defaults: dict | None = None
) -> None:
    """CheckpointError when a ``structural`` entry differs (the weights would not fit or mean something else);
    a trainer declares its structural sections in its registry entry."""
    if not isinstance(saved, dict):
        raise CheckpointError(f"checkpoint {path} holds no readable config (its 'config' entry is not a mapping)")
    diffs = structural_differences(saved, current, structural, defaults)
    if diffs:
        raise CheckpointError(f"checkpoint {path} comes from another config ({'; '.join(diffs[:4])})")


def read_transfer_source(
    source: str | Path, current: dict, defaults: dict, sections: tuple[str, ...]
) -> tuple[dict, Path]:
    """``(model state, checkpoint file)`` of ``run.init_from``'s source (a run directory, whose ``latest`` checkpoint
    is used, or a checkpoint file), after checking that its config's ``sections`` (those that shape the weights:
    ``model`` for FreamerV1, ``network`` for the TorchRL baselines) equal ``current``'s; CheckpointError naming the
    field otherwise. The env may differ as long as the weights fit."""
    source = Path(source)
    path = latest_checkpoint(source) if source.is_dir() else source
    if path is None:
        raise CheckpointError(f"run.init_from: {source} holds no checkpoint (checkpoints/latest is missing)")
    if not path.is_file():
        raise CheckpointError(f"run.init_from: no such checkpoint file: {path}")
    ckpt = load_checkpoint(path)
    saved = ckpt.get("config") if isinstance(ckpt.get("config"), dict) else None
    missing = [s for s in sections if saved is None or not isinstance(saved.get(s), dict)]
    if missing or not isinstance(ckpt.get("model"), dict):
        raise CheckpointError(
            f"run.init_from: checkpoint {path} holds no {', '.join(missing) or 'model'} section to transfer from "
            "(a run of another trainer?)"
        )
    diffs = structural_differences(saved, current, sections, defaults)
    if diffs:
        raise CheckpointError(
            f"run.init_from: checkpoint {path} has another {'/'.join(sections)} ({'; '.join(diffs[:4])})"
        )
    return ckpt["model"], path
