"""Labelled anomalies: injection changes the signal exactly inside the labels, seeded; the labels file's checks."""

import numpy as np
import pytest

from freamer_rl.data import load_pamap2_subject, synthetic_recording
from freamer_rl.data.anomaly_labels import (
    ANOMALY_KINDS,
    DEFAULT_ANOMALIES,
    AnomalyLabelsError,
    inject_anomalies,
    read_labels,
    recording_time_range,
    write_anomaly_scenario,
    write_labels,
)


@pytest.fixture(scope="module")
def base():
    return synthetic_recording(101, duration_s=4 * 3600.0, seed=0, row_rate_hz=1.0)


@pytest.fixture(scope="module")
def injected(base):
    return inject_anomalies(base, seed=3, per_kind=2)


def rows(rec, a):
    return (rec.timestamp >= a.start_s - 1e-6) & (rec.timestamp < a.end_s - 1e-6)


def test_labels_are_sorted_disjoint_and_counted(injected):
    rec, labels = injected
    assert sorted(a.kind for a in labels) == sorted(ANOMALY_KINDS * 2)
    starts = [a.start_s for a in labels]
    assert starts == sorted(starts)
    for prev, cur in zip(labels, labels[1:]):
        assert cur.start_s >= prev.end_s + 600.0 - 1e-6  # min_gap_s
    assert labels[0].start_s >= rec.timestamp[0] + 1800.0  # lead_s
    for a in labels:
        assert a.end_s - a.start_s == pytest.approx(DEFAULT_ANOMALIES[a.kind].duration_s)
    assert rec.info["anomalies"] == [(a.start_s, a.end_s, a.kind) for a in labels]


def test_signal_changes_only_inside_the_labels(base, injected):
    rec, labels = injected
    inside = np.zeros(len(rec), dtype=bool)
    for a in labels:
        inside |= rows(rec, a)
    np.testing.assert_array_equal(rec.heart_rate[~inside], base.heart_rate[~inside])
    for site in rec.imu:
        np.testing.assert_array_equal(rec.imu[site][~inside], base.imu[site][~inside])
    np.testing.assert_array_equal(rec.activity, base.activity)
    assert not np.isnan(base.heart_rate).any()  # at 1 Hz every row has a heart rate
    for a in labels:
        r = rows(rec, a)
        diff = rec.heart_rate[r] - base.heart_rate[r]
        if a.kind == "dropout":
            assert np.isnan(rec.heart_rate[r]).all() and all(np.isnan(v[r]).all() for v in rec.imu.values())
            continue
        for site in rec.imu:  # the heart-rate kinds leave the IMUs alone
            np.testing.assert_array_equal(rec.imu[site][r], base.imu[site][r])
        size = DEFAULT_ANOMALIES[a.kind].size
        if a.kind == "hr_spike":  # a rise of `size` bpm (ramped over 10 s) during one rest segment
            assert np.isin(base.activity[r], (1, 2, 3)).all() and len(set(base.activity[r])) == 1
            assert np.abs(diff[15:-15] - size).max() <= 1.0  # rounding to integer bpm
        elif a.kind == "drift":  # 0 -> size, linear
            t = np.arange(diff.shape[0]) / diff.shape[0]
            assert np.abs(diff - size * t).max() <= 1.0
        else:  # arrhythmia: a new N(0, size) offset every second
            assert 0.6 * size < diff.std() < 1.4 * size


def test_injection_is_seeded(base, injected):
    again = inject_anomalies(base, seed=3, per_kind=2)
    assert again[1] == injected[1]
    np.testing.assert_array_equal(again[0].heart_rate, injected[0].heart_rate)
    assert inject_anomalies(base, seed=4, per_kind=2)[1] != injected[1]
    with pytest.raises(ValueError, match="per_kind: no room"):
        inject_anomalies(base, seed=0, per_kind=40)
    with pytest.raises(ValueError, match="kinds"):
        inject_anomalies(base, kinds=["spike"])


def test_scenario_round_trip(tmp_path):
    dat, lab = write_anomaly_scenario(tmp_path, hours=3.0, seed=2, per_kind=1)
    assert dat == tmp_path / "Protocol" / "subject101.dat" and lab == tmp_path / "labels.csv"
    rec = load_pamap2_subject(dat)
    assert len(rec) == 10800 and np.diff(rec.timestamp).max() == pytest.approx(1.0)
    got = read_labels(lab, time_range=recording_time_range(rec))
    assert sorted(a.kind for a in got) == sorted(ANOMALY_KINDS)
    assert lab.read_text().splitlines()[0] == "start_s,end_s,kind"
    assert [a.line for a in got] == [2, 3, 4, 5]
    # the dropout's rows are NaN in the written file too
    drop = next(a for a in got if a.kind == "dropout")
    assert np.isnan(rec.imu["ankle"][rows(rec, drop)]).all()


GOOD = "start_s,end_s,kind\n100,200,hr_spike\n300,400,drift\n"


@pytest.mark.parametrize(
    "text, line, what",
    [
        ("start,end,kind\n100,200,hr_spike\n", 1, "expected the header"),
        ("", 1, "expected the header"),
        (GOOD + "500,600\n", 4, "expected 3 comma-separated fields"),
        (GOOD + "5e2,abc,drift\n", 4, "end_s: not a finite number"),
        (GOOD + "nan,600,drift\n", 4, "start_s: not a finite number"),
        (GOOD + "600,500,drift\n", 4, "end_s 500 must be greater than start_s 600"),
        (GOOD + "500,600,spike\n", 4, "unknown kind 'spike'"),
        (GOOD + "500,1200,dropout\n", 4, "outside the recording"),
        (GOOD + "150,160,dropout\n", 4, "overlaps line 2"),
        ("start_s,end_s,kind\n350,360,dropout\n300,400,drift\n", 3, "overlaps line 2"),
    ],
)
def test_labels_errors_name_file_and_line(tmp_path, text, line, what):
    path = tmp_path / "labels.csv"
    path.write_text(text)
    with pytest.raises(AnomalyLabelsError) as err:
        read_labels(path, time_range=(0.0, 1000.0))
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{path}: line {line}: ") and what in msg
    assert err.value.line == line and err.value.path == str(path)


def test_labels_reader_accepts_blank_lines_and_no_events(tmp_path):
    path = tmp_path / "labels.csv"
    path.write_text("start_s, end_s, kind\n\n300,400,drift\n100,200,hr_spike\n\n")
    got = read_labels(path, time_range=(0.0, 1000.0))
    assert [(a.start_s, a.kind, a.line) for a in got] == [(100.0, "hr_spike", 4), (300.0, "drift", 3)]
    write_labels([], path)
    assert read_labels(path) == []
    with pytest.raises(AnomalyLabelsError, match="labels file not found"):
        read_labels(tmp_path / "missing.csv")
