"""Block-streaming details of the PAMAP2 reader (``freamer_rl.data.pamap2_parse``).

Tiny block sizes put block boundaries everywhere, so that results and error positions must not depend on where
the file is cut; both modes (one pass, validate-first) must agree.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from test_pamap2 import _edit  # the same line editor as the loader's error tests

from freamer_rl.data import Pamap2FormatError, load_pamap2_subject, pamap2_parse, write_synthetic_pamap2

BLOCKS = (600, 5000, pamap2_parse.BLOCK_BYTES)  # < one row, a few rows, the default


@pytest.fixture(scope="module")
def lines(tmp_path_factory) -> list[str]:
    pdir = write_synthetic_pamap2(tmp_path_factory.mktemp("pamap2_lines"), subjects=(101,), duration_s=8.0, seed=0)
    return (pdir / "subject101.dat").read_text().splitlines()


def _parse_all_ways(path, monkeypatch) -> list:
    """Parse with every block size, in both modes; each result is an array or the error message."""
    results = []
    for validate_first in (False, True):
        monkeypatch.setattr(pamap2_parse, "VALIDATE_FIRST_BYTES", 0 if validate_first else 1 << 40)
        for block in BLOCKS:
            monkeypatch.setattr(pamap2_parse, "BLOCK_BYTES", block)  # read at call time
            try:
                results.append(load_pamap2_subject(path).to_array())
            except Pamap2FormatError as err:
                results.append(str(err))
    return results


def test_values_do_not_depend_on_block_size_or_mode(lines, tmp_path, monkeypatch):
    path = tmp_path / "subject101.dat"
    path.write_text("\r\n".join(lines) + "\r\n\n \n")  # CRLF and trailing blank lines
    ref = np.loadtxt(path)
    for arr in _parse_all_ways(path, monkeypatch):
        assert isinstance(arr, np.ndarray)
        np.testing.assert_array_equal(arr, ref)


@pytest.mark.parametrize(
    "case",
    ["blank_run_then_data", "value_before_non_numeric", "non_numeric_before_column_count", "truncated_last_row"],
)
def test_error_names_the_first_bad_line_whatever_the_blocks(lines, tmp_path, monkeypatch, case):
    n = len(lines)
    if case == "blank_run_then_data":  # blank lines spanning several small blocks, then more rows
        text, expected = "\n".join(lines[:300] + [""] * 40 + lines[300:]), "line 301: blank line"
    elif case == "value_before_non_numeric":  # the earlier line wins over the kind of error
        bad = _edit(_edit(lines, 500, 7, "xyz"), 200, 1, "8")
        text, expected = "\n".join(bad), "line 201: column 2: invalid activity id 8"
    elif case == "non_numeric_before_column_count":
        bad = _edit(lines, 100, 3, "1,5")
        bad[400] += " 1"
        text, expected = "\n".join(bad), "line 101: column 4: non-numeric value '1,5'"
    else:  # the short last row is followed by blank lines that fall into later blocks
        text = "\n".join(lines[:-1] + [lines[-1][:30]]) + "\n" * 50
        expected = f"line {n}: truncated last row"
    path = tmp_path / "subject101.dat"
    path.write_text(text)
    for msg in _parse_all_ways(path, monkeypatch):
        assert isinstance(msg, str) and msg.startswith(f"{path}: {expected}"), msg


def test_overlong_line_is_refused_without_buffering_it(lines, tmp_path):
    path = tmp_path / "subject101.dat"
    path.write_text(lines[0] + "\n" + "1.5 " * (pamap2_parse.MAX_LINE_BYTES // 4 + 10))
    with pytest.raises(Pamap2FormatError, match=r"line 2: line longer than \d+ bytes") as info:
        load_pamap2_subject(path)
    assert info.value.line == 2


def test_decreasing_timestamps_warn_once_across_blocks(lines, tmp_path, monkeypatch, caplog):
    path = tmp_path / "subject101.dat"
    path.write_text("\n".join(lines[:300] + lines[100:400]))  # one step back, at line 301
    monkeypatch.setattr(pamap2_parse, "BLOCK_BYTES", 5000)
    with caplog.at_level(logging.WARNING, logger="freamer_rl.data.pamap2_parse"):
        rec = load_pamap2_subject(path)
    assert len(rec) == 600
    warnings = [r.getMessage() for r in caplog.records if "timestamps decrease" in r.getMessage()]
    assert warnings == [f"{path}: timestamps decrease at 1 places (first at line 301); the rows are kept in file order"]
