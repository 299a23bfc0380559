"""Streaming, bounded-memory reader of PAMAP2 ``subjectNNN.dat`` files (re-exported by :mod:`freamer_rl.data`).

The file is read in blocks of whole lines (:data:`BLOCK_BYTES` of text each); each block goes through numpy's C
text reader (``np.loadtxt``) and vectorised value checks, and is copied into one preallocated float64 ``[T, 54]``
matrix. Memory is therefore the output matrix plus ~10 MB of block temporaries, never a multiple of the file
(the former whole-file reader needed ~15x the file size to report an error near the end of a file):

- files up to :data:`VALIDATE_FIRST_BYTES`: one counting pass over the raw bytes (newlines only), then one parse
  pass that checks and stores each block. A malformed file stops at its first bad block, having used at most the
  float64 size of the rows before it (~1.2x that part of the file's text, about 2x its float32 size).
- larger files: a first parse pass checks every block and stores nothing (the row count falls out), then a second
  parse pass fills the matrix. A malformed file of any size is reported with ~15 MB of memory; a valid one
  costs a second parse (~8-12 s per GB of text on this project's 2-core machine).

A malformed file raises :class:`Pamap2FormatError` with one line naming the file, the 1-based line and, for field
errors, the 1-based column: the first bad line of the file (within a line, the first failing check in the order
columns, numbers, timestamp, activity, heart rate, infinities).
"""

from __future__ import annotations

import dataclasses
import io
import logging
import re
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from freamer_rl.data.pamap2_format import (
    _SITE_FIRST_COLUMN,
    _VALID_ID,
    ACTIVITY_NAMES,
    IMU_SITES,
    MAX_ACTIVITY_ID,
    N_COLUMNS,
    PROTOCOL_SUBJECTS,
    Pamap2FormatError,
    Pamap2Recording,
)

logger = logging.getLogger(__name__)

__all__ = ["load_pamap2_protocol", "load_pamap2_subject"]

#: Text read per block (whole lines; ~2,500 PAMAP2 rows). A block's temporaries (bytes, the reader's str and
#: StringIO copies, float64 rows) are ~10x this, which bounds the parser's memory beyond the output matrix; 1 MiB
#: was the fastest size measured (256 KiB: -30 % throughput, 4 MiB: -10 % and 4x the temporaries).
BLOCK_BYTES = 1 << 20
#: Files larger than this are checked completely before the output matrix is allocated (see the module docstring);
#: every real PAMAP2 protocol file (<= ~200 MB) is below it and is parsed once.
VALIDATE_FIRST_BYTES = 256 << 20
#: A line longer than this cannot be a 54-column row (real rows are ~450 bytes); refusing it keeps one unterminated
#: "line" (e.g. a binary file or CR-only line ends) from being buffered whole.
MAX_LINE_BYTES = 1 << 20

_EXPECTED = f"{N_COLUMNS} space-separated numeric columns"
_VALID_IDS_TEXT = ", ".join(str(a) for a in sorted(ACTIVITY_NAMES))


def _error(path: Path, line: int, message: str, column: int | None = None) -> Pamap2FormatError:
    """``"<path>: line <line>[: column <column>]: <message>"`` (1-based) with the matching attributes."""
    where = f"line {line}" if column is None else f"line {line}: column {column}"
    return Pamap2FormatError(f"{path}: {where}: {message}", path=path, line=line, column=column)


class _BlockReader:
    """Iterates over ``(line0, block)``: ``block`` holds whole lines without the final newline, ``line0`` is the
    0-based index of its first line. The partial line after the last newline read is kept in ``carry``."""

    def __init__(self, path: Path, f: BinaryIO, block_bytes: int) -> None:
        self.path, self.f, self.block_bytes = path, f, block_bytes
        self.carry = b""
        self.line0 = 0

    def __iter__(self) -> Iterator[tuple[int, bytes]]:
        while chunk := self.f.read(self.block_bytes):
            data = self.carry + chunk
            cut = data.rfind(b"\n")
            if cut < 0:
                self.carry = data
                if len(data) > MAX_LINE_BYTES:
                    msg = f"line longer than {MAX_LINE_BYTES} bytes (expected rows of {_EXPECTED})"
                    raise _error(self.path, self.line0 + 1, msg)
                continue
            block, self.carry = data[:cut], data[cut + 1 :]
            yield self.line0, block
            self.line0 += block.count(b"\n") + 1
        if self.carry:
            block, self.carry = self.carry, b""
            yield self.line0, block

    def rest_is_blank(self) -> bool:
        """Whether everything after the current block is whitespace (reads the rest of the file, block by block)."""
        if self.carry.strip():
            return False
        while chunk := self.f.read(self.block_bytes):
            if chunk.strip():
                return False
        return True


def _loadtxt(text: bytes) -> np.ndarray:
    """float64 ``[rows, cols]`` from numpy's C reader (whitespace-separated; it skips blank lines)."""
    return np.loadtxt(io.StringIO(text.decode("latin-1")), dtype=np.float64, comments=None, ndmin=2)


def _parses(text: bytes, n_values: int) -> bool:
    """Whether the block reader accepts ``text`` as exactly ``n_values`` numbers."""
    try:
        return _loadtxt(text).size == n_values
    except ValueError:
        return False


def _first_unparseable(path: Path, lines: list[bytes], line0: int) -> Pamap2FormatError | None:
    """The first field the reader rejects in ``lines`` (each with 54 tokens), or ``None`` if all parse.

    Sub-blocks of 256 lines, then lines, then tokens: a few hundred reader calls instead of one per line.
    """
    sub = 256
    for b0 in range(0, len(lines), sub):
        chunk = lines[b0 : b0 + sub]
        if _parses(b"\n".join(chunk), N_COLUMNS * len(chunk)):
            continue
        for i, line in enumerate(chunk, start=line0 + b0 + 1):
            if _parses(line, N_COLUMNS):
                continue
            for j, tok in enumerate(line.split(), start=1):
                if not _parses(tok, 1):
                    text = tok.decode("latin-1")
                    text = text[:37] + "..." if len(text) > 40 else text
                    return _error(path, i, f"non-numeric value {text!r} (expected a number or NaN)", j)
            # every token parses alone but not the line: a separator the reader does not split on (e.g. \f)
            return _error(path, i, f"could not parse the line (expected {_EXPECTED})")
    return None


def _column_count_error(path: Path, line_no: int, n_tokens: int, is_last: bool) -> Pamap2FormatError:
    """Error for a line with ``n_tokens`` != 54 (``line_no`` 1-based; ``is_last``: last non-blank line of the file)."""
    if n_tokens == 0:
        return _error(path, line_no, f"blank line (expected {_EXPECTED})")
    if is_last and n_tokens < N_COLUMNS:
        return _error(path, line_no, f"truncated last row: {n_tokens} of {N_COLUMNS} columns")
    return _error(path, line_no, f"expected {N_COLUMNS} columns, found {n_tokens}")


def _block_error(path: Path, body: bytes, line0: int, reader: _BlockReader, reason: str) -> Pamap2FormatError:
    """Locate the first problem of a block the fast path rejected (``body``: its lines up to the last non-blank).

    The lines before the first wrong column count are parsed and value-checked too, so that the error names the
    first bad line whatever its kind.
    """
    lines = body.split(b"\n")
    counts = (len(line.split()) for line in lines)
    bad = next((i for i, n in enumerate(counts) if n != N_COLUMNS), len(lines))
    err = _first_unparseable(path, lines[:bad], line0)
    stop = bad if err is None else err.line - 1 - line0  # the lines before the first unreadable one
    if stop:
        err = _value_error(path, _loadtxt(b"\n".join(lines[:stop])), line0) or err
    if err is None and bad < len(lines):
        # the last line of ``body`` is the file's last non-blank line only if nothing but whitespace follows
        is_last = bad == len(lines) - 1 and reader.rest_is_blank()
        err = _column_count_error(path, line0 + bad + 1, len(lines[bad].split()), is_last)
    return err or _error(path, line0 + 1, f"could not parse the numeric data in this block ({reason})")


def _first_row(mask: np.ndarray) -> int | None:
    bad = np.flatnonzero(mask)
    return int(bad[0]) if bad.size else None


def _value_error(path: Path, arr: np.ndarray, line0: int) -> Pamap2FormatError | None:
    """The first bad value of a parsed block ``[n, 54]`` whose first row is line ``line0 + 1``, or ``None``.

    Earliest row wins; within a row, the order of the checks below.
    """
    ts, act, hr = arr[:, 0], arr[:, 1], arr[:, 2]
    act_ok = (act == np.round(act)) & (act >= 0) & (act <= MAX_ACTIVITY_ID)
    act_ok[act_ok] = _VALID_ID[act[act_ok].astype(np.int64)]
    inf_rows = np.isinf(arr).any(axis=1)
    checks = (
        (~np.isfinite(ts), 1, lambda r: f"timestamp must be a finite number, got {float(ts[r]):g}"),
        (~np.isfinite(act), 2, lambda r: f"activity id must be a finite integer, got {float(act[r]):g}"),
        (~act_ok, 2, lambda r: f"invalid activity id {act[r]:g} (valid ids: {_VALID_IDS_TEXT})"),
        (
            ~np.isnan(hr) & ~((hr > 0) & (hr <= 300)),
            3,
            lambda r: f"implausible heart rate {hr[r]:g} bpm (expected (0, 300] or NaN)",
        ),
        (inf_rows, None, lambda r: "infinite value (expected a finite number or NaN)"),
    )
    found = [(row, k) for k, (mask, _, _) in enumerate(checks) if (row := _first_row(mask)) is not None]
    if not found:
        return None
    row, k = min(found)
    _, col, what = checks[k]
    if col is None:  # the infinity check names the first infinite column of the row
        col = int(np.flatnonzero(np.isinf(arr[row]))[0]) + 1
    return _error(path, line0 + row + 1, what(row), col)


@dataclasses.dataclass
class _ScanState:
    """What one pass carries from block to block."""

    rows: int = 0
    pending_blank: int | None = None  # 0-based first line of a blank run not yet known to be the file's tail
    last_ts: float | None = None
    n_back: int = 0  # places where the timestamp decreases
    first_back: int | None = None  # 1-based line of the first one


def _track_timestamps(st: _ScanState, ts: np.ndarray, line0: int) -> None:
    """Count decreasing timestamps, across block boundaries too (warned once at the end: real files have some)."""
    prev = ts[:1] if st.last_ts is None else np.array([st.last_ts])
    back = np.flatnonzero(np.diff(np.concatenate([prev, ts])) < 0)
    if back.size:
        st.first_back = st.first_back if st.first_back is not None else line0 + int(back[0]) + 1
        st.n_back += int(back.size)
    st.last_ts = float(ts[-1])


def _scan(path: Path, out: np.ndarray | None, validate: bool, block_bytes: int) -> int:
    """One pass over the file: parse every block, check it if ``validate``, copy it into ``out`` if given.

    Returns:
        the number of data rows (trailing blank lines and whitespace excluded).
    """
    st = _ScanState()
    with _open(path) as f:
        reader = _BlockReader(path, f, block_bytes)
        for line0, block in reader:
            body = block.rstrip()  # trailing whitespace / blank lines are fine at the end of the file only
            if not body:
                st.pending_blank = line0 if st.pending_blank is None else st.pending_blank
                continue
            if st.pending_blank is not None:
                raise _column_count_error(path, st.pending_blank + 1, 0, False)
            n = body.count(b"\n") + 1
            if n < block.count(b"\n") + 1:
                st.pending_blank = line0 + n
            arr = _parse_block(path, body, n, line0, reader)
            if validate:
                if (err := _value_error(path, arr, line0)) is not None:
                    raise err
                _track_timestamps(st, arr[:, 0], line0)
            if out is not None:
                if st.rows + n > out.shape[0]:
                    raise _error(path, line0 + n, "the file grew while it was being read")
                out[st.rows : st.rows + n] = arr
            st.rows += n
    if st.rows == 0:
        raise _error(path, 1, f"empty file (expected rows of {_EXPECTED})")
    if st.n_back:
        logger.warning(
            "%s: timestamps decrease at %d places (first at line %d); the rows are kept in file order",
            path,
            st.n_back,
            st.first_back,
        )
    return st.rows


def _parse_block(path: Path, body: bytes, n: int, line0: int, reader: _BlockReader) -> np.ndarray:
    """float64 ``[n, 54]`` of a block's ``n`` lines, or the located error (the reader skips blank lines, hence
    the shape check)."""
    try:
        arr = _loadtxt(body)
    except ValueError as err:
        raise _block_error(path, body, line0, reader, str(err)) from None
    if arr.shape != (n, N_COLUMNS):
        raise _block_error(path, body, line0, reader, f"parsed shape {arr.shape}, expected ({n}, {N_COLUMNS})")
    return arr


def _open(path: Path) -> BinaryIO:
    try:
        return open(path, "rb")  # noqa: SIM115 - closed by the caller's ``with``
    except FileNotFoundError:
        raise Pamap2FormatError(f"{path}: file not found", path=path) from None
    except OSError as err:
        raise Pamap2FormatError(f"{path}: cannot read file ({err.strerror or err})", path=path) from None


def _count_lines(path: Path, block_bytes: int) -> int:
    """Upper bound of the number of rows: newlines + 1 (a cheap pass over the raw bytes)."""
    n = 1
    with _open(path) as f:
        while chunk := f.read(block_bytes):
            n += chunk.count(b"\n")
    return n


def _parse_dat(path: Path, block_bytes: int | None = None) -> np.ndarray:
    """The checked float64 ``[T, 54]`` matrix of one file (see the module docstring for the passes)."""
    block_bytes = block_bytes or BLOCK_BYTES  # looked up at call time, so that tests can shrink it
    try:
        size = path.stat().st_size
    except OSError:
        size = 0  # let the open below report the file as missing / unreadable
    validate_first = size > VALIDATE_FIRST_BYTES
    if validate_first:
        n_max = _scan(path, None, True, block_bytes)
    else:
        # a row needs >= 108 bytes (54 one-character fields, 53 separators, a newline): this caps the allocation
        # for files of many short lines, whose newline count alone could exceed the machine's address space
        n_max = min(_count_lines(path, block_bytes), size // (2 * N_COLUMNS) + 1)
    # np.empty only reserves address space: pages become resident as blocks are written, so an early error
    # leaves little behind and the few spare rows of the newline count cost nothing
    out = np.empty((n_max, N_COLUMNS), dtype=np.float64)
    n = _scan(path, out, not validate_first, block_bytes)
    return out[:n]


def _recording_from_array(
    arr: np.ndarray, *, subject: int | None, source: str | None, info: dict | None = None
) -> Pamap2Recording:
    imu = {}
    for site in IMU_SITES:
        c = _SITE_FIRST_COLUMN[site]
        imu[site] = arr[:, c : c + 17]
    return Pamap2Recording(
        timestamp=arr[:, 0],
        activity=arr[:, 1].astype(np.int64),
        heart_rate=arr[:, 2],
        imu=imu,
        subject=subject,
        source=source,
        info=dict(info or {}),
    )


_SUBJECT_RE = re.compile(r"subject(\d{3})\.dat$")


def load_pamap2_subject(path: str | Path) -> Pamap2Recording:
    """Read one ``subjectNNN.dat`` file (54 space-separated columns, ``NaN`` for missing values).

    Memory: the float64 output plus ~10 MB of block temporaries (see the module docstring).

    Returns:
        :class:`Pamap2Recording` with ``T`` rows; ``imu[site]`` are views of one ``[T, 54]`` float64 matrix.

    Raises:
        Pamap2FormatError: missing/unreadable/empty file, a line without exactly 54 columns (a short last line is
            reported as a truncated row), a non-numeric field, an infinite value, a NaN timestamp or activity, an
            activity id outside :data:`ACTIVITY_NAMES`, or a heart rate outside (0, 300] bpm. One line naming the
            file, the 1-based line and (for field errors) the 1-based column.
    """
    path = Path(path)
    t0 = time.perf_counter()
    arr = _parse_dat(path)
    elapsed = time.perf_counter() - t0
    logger.debug("%s: %d rows in %.3f s (%.0f rows/s)", path, arr.shape[0], elapsed, arr.shape[0] / max(elapsed, 1e-9))
    m = _SUBJECT_RE.search(path.name)
    return _recording_from_array(arr, subject=int(m.group(1)) if m else None, source=str(path))


def _protocol_dir(folder: str | Path) -> Path:
    folder = Path(folder)
    if not folder.is_dir():
        raise Pamap2FormatError(f"{folder}: PAMAP2 folder not found", path=folder)
    if (folder / "Protocol").is_dir():
        return folder / "Protocol"
    return folder


def load_pamap2_protocol(folder: str | Path, subjects: Iterable[int] | None = None) -> dict[int, Pamap2Recording]:
    """Read ``Protocol/subjectNNN.dat`` for the given subjects (101-109).

    Args:
        folder: the dataset root (holding ``Protocol/``) or the ``Protocol`` folder itself.
        subjects: subject numbers; ``None`` = every ``subject101.dat`` .. ``subject109.dat`` present.

    Returns:
        ``{subject: Pamap2Recording}`` in ascending subject order.

    Raises:
        Pamap2FormatError: missing folder, no subject file, a requested subject's file missing, or a malformed file.
        ValueError: a subject number outside 101-109.
    """
    pdir = _protocol_dir(folder)
    if subjects is None:
        chosen = [s for s in PROTOCOL_SUBJECTS if (pdir / f"subject{s}.dat").is_file()]
        if not chosen:
            raise Pamap2FormatError(
                f"{pdir}: no subjectNNN.dat files (expected subject101.dat .. subject109.dat)", path=pdir
            )
    else:
        chosen = sorted({int(s) for s in subjects})
        wrong = [s for s in chosen if s not in PROTOCOL_SUBJECTS]
        if wrong or not chosen:
            raise ValueError(f"subjects: expected numbers in 101..109, got {list(subjects)!r}")
    return {s: load_pamap2_subject(pdir / f"subject{s}.dat") for s in chosen}
