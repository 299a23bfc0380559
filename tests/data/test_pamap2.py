"""PAMAP2 loader, features and synthetic generator (freamer_rl.data)."""

from __future__ import annotations

import numpy as np
import pytest

from freamer_rl.data import (
    ACTIVITY_GROUP_NAMES,
    ACTIVITY_GROUP_OF,
    ACTIVITY_MET,
    ACTIVITY_NAMES,
    HR_FEATURE_NAMES,
    IMU_FEATURE_NAMES,
    IMU_SITES,
    N_COLUMNS,
    Pamap2FormatError,
    hr_zone,
    load_pamap2_protocol,
    load_pamap2_subject,
    pamap2_features,
    synthetic_recording,
    write_synthetic_pamap2,
)

SUBJECTS = (101, 102, 103)
DURATION_S = 120.0


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("pamap2")
    pdir = write_synthetic_pamap2(root, subjects=SUBJECTS, duration_s=DURATION_S, seed=0)
    return root, pdir


@pytest.fixture(scope="module")
def long_recording():
    return synthetic_recording(101, duration_s=600.0, seed=0)


# ----------------------------------------------------------------------------------------------------------------------
# file format and loader
# ----------------------------------------------------------------------------------------------------------------------
def test_written_files_have_the_pamap2_layout(dataset):
    _, pdir = dataset
    for s in SUBJECTS:
        lines = (pdir / f"subject{s}.dat").read_text().splitlines()
        assert len(lines) == int(DURATION_S * 100)
        counts = {len(line.split(" ")) for line in lines}
        assert counts == {N_COLUMNS}
        first = lines[0].split(" ")
        assert first[2] != "NaN" and float(first[2]) == int(float(first[2]))  # integer bpm on the first row
        assert any(line.split(" ")[2] == "NaN" for line in lines[:20])
        for site_col in (16, 33, 50):  # orientation columns (0-based) of hand, chest, ankle
            assert first[site_col : site_col + 4] == ["1", "0", "0", "0"]


def test_loader_shapes_nan_pattern_and_ids(dataset):
    root, _ = dataset
    recs = load_pamap2_protocol(root)
    assert list(recs) == list(SUBJECTS)
    valid = set(ACTIVITY_NAMES)
    for s, rec in recs.items():
        T = int(DURATION_S * 100)
        assert rec.subject == s and len(rec) == T
        assert rec.timestamp.shape == (T,) and rec.activity.shape == (T,) and rec.heart_rate.shape == (T,)
        assert rec.activity.dtype == np.int64
        assert set(rec.imu) == set(IMU_SITES)
        assert all(rec.imu[site].shape == (T, 17) for site in IMU_SITES)
        np.testing.assert_allclose(np.diff(rec.timestamp), 0.01, atol=1e-6)
        nan_frac = np.isnan(rec.heart_rate).mean()
        assert 0.88 < nan_frac < 0.93  # HR on ~9 rows in 100
        gaps = np.diff(np.flatnonzero(~np.isnan(rec.heart_rate)))
        assert gaps.min() >= 10 and gaps.max() <= 12
        assert set(np.unique(rec.activity).tolist()) <= valid
        assert 0 in set(rec.activity.tolist())  # transient gaps are present
        for site in IMU_SITES:
            temp = rec.imu[site][:, 0]
            assert 28.0 <= temp.min() and temp.max() <= 37.0
            acc = np.linalg.norm(rec.imu[site][:, 1:4], axis=1)
            assert 8.0 < np.median(acc[rec.activity == 1]) < 11.5  # gravity while lying


def test_loader_roundtrip_matches_in_memory_generator(dataset):
    _, pdir = dataset
    rec = load_pamap2_subject(pdir / "subject102.dat")
    ref = synthetic_recording(102, duration_s=DURATION_S, seed=0)
    a, b = rec.to_array(), ref.to_array()
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a[:, 0], b[:, 0], atol=5e-3)
    np.testing.assert_allclose(np.nan_to_num(a[:, 1:]), np.nan_to_num(b[:, 1:]), rtol=1e-5, atol=1e-4)


def test_protocol_accepts_the_protocol_folder_itself(dataset):
    _, pdir = dataset
    assert list(load_pamap2_protocol(pdir, subjects=[103])) == [103]


def test_protocol_names_a_missing_subject_file(dataset):
    root, _ = dataset
    with pytest.raises(Pamap2FormatError, match=r"subject105\.dat: file not found"):
        load_pamap2_protocol(root, subjects=[101, 105])


def test_protocol_refuses_a_subject_outside_the_dataset(dataset):
    root, _ = dataset
    with pytest.raises(ValueError, match="subjects"):
        load_pamap2_protocol(root, subjects=[99])


def test_protocol_names_a_missing_folder(tmp_path):
    missing = tmp_path / "no_such_folder"
    with pytest.raises(Pamap2FormatError, match="PAMAP2 folder not found") as info:
        load_pamap2_protocol(missing)
    assert str(missing) in str(info.value)


def test_protocol_refuses_a_folder_without_subject_files(tmp_path):
    (tmp_path / "empty_protocol" / "Protocol").mkdir(parents=True)
    with pytest.raises(Pamap2FormatError, match="no subjectNNN.dat"):
        load_pamap2_protocol(tmp_path / "empty_protocol")


def _edit(lines: list[str], row: int, col: int, value: str) -> list[str]:
    out = list(lines)
    toks = out[row].split(" ")
    toks[col] = value
    out[row] = " ".join(toks)
    return out


def _malformed_cases(lines: list[str]):
    n = len(lines)
    drop = list(lines)
    drop[41] = " ".join(drop[41].split(" ")[:53])
    extra = list(lines)
    extra[7] = extra[7] + " 0.5"
    blank = lines[:30] + [""] + lines[30:]
    return {
        # name: (text, expected 1-based line, expected 1-based column or None, message fragment)
        "too_few_columns": ("\n".join(drop), 42, None, "expected 54 columns, found 53"),
        "too_many_columns": ("\n".join(extra), 8, None, "expected 54 columns, found 55"),
        "non_numeric": ("\n".join(_edit(lines, 99, 12, "abc")), 100, 13, "non-numeric value 'abc'"),
        "non_numeric_hr": ("\n".join(_edit(lines, 5, 2, "fast")), 6, 3, "non-numeric value 'fast'"),
        "glued_numbers": ("\n".join(_edit(lines, 1500, 30, "1.5-2")), 1501, 31, "non-numeric"),
        "truncated_last_row": (
            "\n".join(lines[:-1] + [" ".join(lines[-1].split(" ")[:17])]),
            n,
            None,
            "truncated last row",
        ),
        "truncated_last_row_newline": ("\n".join(lines[:-1] + [lines[-1][:25]]) + "\n", n, None, "truncated"),
        "empty_file": ("", 1, None, "empty file"),
        "blank_line": ("\n".join(blank), 31, None, "blank line"),
        "invalid_activity": ("\n".join(_edit(lines, 10, 1, "8")), 11, 2, "invalid activity id 8"),
        "nan_timestamp": ("\n".join(_edit(lines, 3, 0, "NaN")), 4, 1, "timestamp"),
        "infinite_value": ("\n".join(_edit(lines, 20, 44, "inf")), 21, 45, "infinite"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "too_few_columns",
        "too_many_columns",
        "non_numeric",
        "non_numeric_hr",
        "glued_numbers",
        "truncated_last_row",
        "truncated_last_row_newline",
        "empty_file",
        "blank_line",
        "invalid_activity",
        "nan_timestamp",
        "infinite_value",
    ],
)
def test_malformed_files_raise_one_line_error_with_file_and_line(dataset, tmp_path, case):
    _, pdir = dataset
    lines = (pdir / "subject101.dat").read_text().splitlines()[:2000]
    text, line, column, fragment = _malformed_cases(lines)[case]
    path = tmp_path / "subject101.dat"
    path.write_text(text)
    with pytest.raises(Pamap2FormatError) as info:
        load_pamap2_subject(path)
    err = info.value
    msg = str(err)
    assert "\n" not in msg
    assert msg.startswith(f"{path}: line {line}")
    assert fragment in msg
    assert err.line == line and err.path == str(path)
    if column is not None:
        assert f"column {column}" in msg and err.column == column


def test_missing_file_error_names_the_file(tmp_path):
    with pytest.raises(Pamap2FormatError, match="file not found") as info:
        load_pamap2_subject(tmp_path / "subject101.dat")
    assert str(tmp_path / "subject101.dat") in str(info.value)


def test_crlf_and_trailing_blank_lines_are_accepted(dataset, tmp_path):
    _, pdir = dataset
    lines = (pdir / "subject101.dat").read_text().splitlines()[:300]
    path = tmp_path / "crlf.dat"
    path.write_bytes(("\r\n".join(lines) + "\r\n\r\n").encode())
    assert len(load_pamap2_subject(path)) == 300


# ----------------------------------------------------------------------------------------------------------------------
# features
# ----------------------------------------------------------------------------------------------------------------------
def test_activity_groups_cover_all_ids():
    assert len(ACTIVITY_GROUP_NAMES) == 8
    assert set(ACTIVITY_GROUP_OF) == set(ACTIVITY_NAMES) == set(ACTIVITY_MET)
    assert set(ACTIVITY_GROUP_OF.values()) == set(range(8))
    assert ACTIVITY_GROUP_OF[0] == ACTIVITY_GROUP_NAMES.index("transient_other")
    assert len(ACTIVITY_NAMES) == 19  # 18 activities + transient


def test_hr_zone_edges():
    np.testing.assert_array_equal(hr_zone([60, 109.9, 110, 134.9, 135, 160, 160.1, 200]), [0, 0, 1, 1, 2, 2, 3, 3])


def test_feature_dims_and_documented_ranges(long_recording):
    f = pamap2_features(long_recording, rate_hz=1.0)
    N = 600
    assert len(IMU_FEATURE_NAMES) == 36 and len(HR_FEATURE_NAMES) == 16
    assert f.imu.shape == (N, 36) and f.imu.dtype == np.float32
    assert f.hr_features.shape == (N, 16) and f.hr_features.dtype == np.float32
    assert f.activity.shape == (N,) and f.heart_rate.shape == (N,)
    assert np.isfinite(f.imu).all() and np.isfinite(f.hr_features).all()
    h = f.hr_features
    np.testing.assert_allclose(h[:, 0], f.heart_rate / 200.0, rtol=1e-6)
    np.testing.assert_array_equal(h[:, 1:9].sum(axis=1), 1.0)
    np.testing.assert_array_equal(h[:, 1:9].argmax(axis=1), f.group)
    assert set(np.round(h[:, 9] * 3).astype(int).tolist()) <= {0, 1, 2, 3}
    np.testing.assert_allclose(h[:, 9] * 3, hr_zone(f.heart_rate), atol=1e-6)
    assert (h[:, 10] >= 0).all() and (h[:, 10] <= 1.5).all()
    assert (h[:, 11] >= 0).all() and (h[:, 11] <= 1.5).all()
    assert (h[:, 12] >= 0).all() and (h[:, 12] <= 5).all()
    assert (np.abs(h[:, 13]) <= 3).all() and h[0, 13] == 0
    assert (np.diff(h[:, 14]) >= 0).all() and h[0, 14] >= 0
    np.testing.assert_allclose(h[:, 15], f.met / 12.0, rtol=1e-6)
    # fatigue accumulates during exercise and recovers afterwards
    assert h[:, 11].max() > 0.1
    # IMU scaling: accelerations in g (|acc| ~ 1 while lying), magnetometer in 50 uT units
    lying = f.activity == 1
    chest_acc = np.linalg.norm(f.imu[lying][:, 12:15], axis=1)
    assert np.all(np.abs(chest_acc - 1.0) < 0.1)
    mag = np.linalg.norm(f.imu[:, 9:12], axis=1)
    assert 0.7 < np.median(mag) < 1.3


def test_feature_rates_reduce_modes_and_transient_option(long_recording):
    f10 = pamap2_features(long_recording, rate_hz=10.0)
    assert f10.imu.shape == (6000, 36) and f10.rate_hz == pytest.approx(10.0)
    fm = pamap2_features(long_recording, rate_hz=1.0, imu_reduce="mean")
    fl = pamap2_features(long_recording, rate_hz=1.0)
    assert fm.imu.std(axis=0).mean() < fl.imu.std(axis=0).mean()  # window means smooth out the movement
    fd = pamap2_features(long_recording, rate_hz=1.0, drop_transient=True)
    assert 0 not in fd.activity and 0 < len(fd) < len(fl)
    with pytest.raises(ValueError, match="rate_hz"):
        pamap2_features(long_recording, rate_hz=0.0)
    with pytest.raises(ValueError, match="rate_hz"):
        pamap2_features(long_recording, rate_hz=1000.0)
    with pytest.raises(ValueError, match="imu_reduce"):
        pamap2_features(long_recording, imu_reduce="max")


def test_synthetic_movement_statistics_follow_activity(long_recording):
    rec = long_recording
    ankle = np.linalg.norm(rec.imu["ankle"][:, 1:4], axis=1)
    spread = {a: ankle[rec.activity == a].std() for a in (1, 4, 5, 24)}
    assert spread[1] < spread[4] < spread[5] < spread[24]
    hr = {a: np.nanmean(rec.heart_rate[rec.activity == a]) for a in (1, 4, 24)}
    assert hr[1] < hr[4] < hr[24]


def _ffill(x: np.ndarray) -> np.ndarray:
    idx = np.where(~np.isnan(x), np.arange(x.shape[0]), 0)
    np.maximum.accumulate(idx, out=idx)
    return x[idx]


@pytest.mark.parametrize("subject", SUBJECTS)
def test_heart_rate_lags_movement_by_several_seconds(subject):
    rec = synthetic_recording(subject, duration_s=600.0, seed=0)
    acc = np.linalg.norm(rec.imu["ankle"][:, 1:4], axis=1)
    n = acc.shape[0] // 100
    intensity = acc[: n * 100].reshape(n, 100).std(axis=1)  # movement per second
    hr = _ffill(rec.heart_rate)[99::100][:n]
    x = (intensity - intensity.mean()) / intensity.std()
    y = (hr - hr.mean()) / hr.std()
    lags = np.arange(-60, 61)
    cc = [np.mean(x[max(0, -k) : n - max(0, k)] * y[max(0, k) : n - max(0, -k)]) for k in lags]
    best = int(lags[int(np.argmax(cc))])
    assert 3 <= best <= 40, f"cross-correlation peaks at lag {best} s"
    assert max(cc) > 0.5
    assert cc[list(lags).index(best)] > cc[list(lags).index(0)]


def test_synthetic_generator_is_seeded():
    a = synthetic_recording(101, duration_s=30.0, seed=3).to_array()
    b = synthetic_recording(101, duration_s=30.0, seed=3).to_array()
    c = synthetic_recording(101, duration_s=30.0, seed=4).to_array()
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(np.nan_to_num(a), np.nan_to_num(c))
