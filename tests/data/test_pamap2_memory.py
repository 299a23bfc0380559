"""The PAMAP2 parser works in bounded memory (``freamer_rl.data.pamap2_parse``).

Each parse runs in a fresh subprocess that reports the growth of its peak resident memory
(``VmHWM`` of ``/proc/self/status``, i.e. ``ru_maxrss`` without what Linux inherits from the parent, after the
parse minus before it) and numpy's peak traced allocation (``tracemalloc``). The file is a
~60 MB PAMAP2 text generated in ``tmp_path``; the float32 size of its data is the yardstick.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from freamer_rl.data import N_COLUMNS, write_synthetic_pamap2

MB = 1 << 20
TARGET_BYTES = 60 * MB

_CHILD = r"""
import json, resource, sys, tracemalloc
from freamer_rl.data import pamap2_parse
from freamer_rl.data import Pamap2FormatError, load_pamap2_subject

path, validate_first = sys.argv[1], sys.argv[2] == "1"
if validate_first:  # force the two-pass mode (normally only for files > VALIDATE_FIRST_BYTES)
    pamap2_parse.VALIDATE_FIRST_BYTES = 0


def peak_rss():
    # VmHWM: this process's own high-water mark. ru_maxrss would do on a fresh process, but Linux carries the
    # parent's peak over fork + exec into it (here: pytest's, with the generated file's text)
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


before = peak_rss()
tracemalloc.start()
try:
    rows, error, line = len(load_pamap2_subject(path)), None, None
except Pamap2FormatError as err:
    rows, error, line = None, str(err), err.line
traced_peak = tracemalloc.get_traced_memory()[1]
tracemalloc.stop()
after = peak_rss()
print(json.dumps({"rss_increase": after - before, "traced_peak": traced_peak, "rows": rows, "error": error,
                  "line": line}))
"""


@pytest.fixture(scope="module")
def big_files(tmp_path_factory) -> dict:
    """A valid ~60 MB file and the same with a non-numeric field 100 lines before the end."""
    root = tmp_path_factory.mktemp("pamap2_big")
    # one minute of real-looking rows, repeated with continuing timestamps (formatting every row would be slow)
    minute = write_synthetic_pamap2(root / "minute", subjects=(101,), duration_s=60.0, seed=0) / "subject101.dat"
    rows = [line.split(" ", 1)[1] for line in minute.read_text().splitlines()]
    n = TARGET_BYTES // (sum(map(len, rows)) // len(rows) + 8)
    lines = [f"{10.0 + 0.01 * i:.2f} {rows[i % len(rows)]}" for i in range(n)]
    valid = root / "subject101.dat"
    valid.write_text("\n".join(lines) + "\n")
    bad_row = n - 100
    toks = lines[bad_row].split(" ")
    toks[20] = "1.2.3"
    lines[bad_row] = " ".join(toks)
    malformed = root / "subject102.dat"
    malformed.write_text("\n".join(lines) + "\n")
    return {"valid": valid, "malformed": malformed, "rows": n, "bad_line": bad_row + 1}


def _parse_in_subprocess(path: Path, validate_first: bool) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path), "1" if validate_first else "0"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def _float32_bytes(rows: int) -> int:
    return rows * N_COLUMNS * np.dtype(np.float32).itemsize


@pytest.mark.parametrize("validate_first", [False, True], ids=["one_pass", "validate_first"])
def test_malformed_big_file_errors_in_bounded_memory(big_files, validate_first):
    res = _parse_in_subprocess(big_files["malformed"], validate_first)
    line = big_files["bad_line"]
    assert res["line"] == line and res["error"].endswith(
        f"line {line}: column 21: non-numeric value '1.2.3' (expected a number or NaN)"
    )
    read_so_far = _float32_bytes(line - 1)
    size = big_files["malformed"].stat().st_size
    for key in ("rss_increase", "traced_peak"):
        # one pass: the float64 rows before the error (2x float32) plus ~10 MB of block temporaries
        assert res[key] < 4 * read_so_far, (key, res[key] / MB)
        assert res[key] < 2 * size, (key, res[key] / MB)  # the old reader needed > 10x the file size
        if validate_first:  # nothing is stored before the whole file has been checked: blocks only
            assert res[key] < 32 * MB, (key, res[key] / MB)


def test_valid_big_file_memory_is_proportional_to_its_data(big_files):
    res = _parse_in_subprocess(big_files["valid"], validate_first=False)
    assert res["error"] is None and res["rows"] == big_files["rows"]
    data = _float32_bytes(big_files["rows"])
    for key in ("rss_increase", "traced_peak"):
        # the float64 result (2x its float32 size) plus a few blocks, not a multiple of the text
        assert res[key] < 3 * data, (key, res[key] / MB, data / MB)
