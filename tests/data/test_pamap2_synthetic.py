"""The seeded synthetic PAMAP2 generator and the feature code give the numbers of the original single-file module.

The reference values below were computed with ``freamer_rl/data/pamap2.py`` as it was before it was split into
``pamap2_format`` / ``pamap2_parse`` / ``pamap2_observation`` / ``pamap2_synthetic`` (same machine, numpy 2.4):
the split must not change a single generated number. Integer-valued columns (timestamps, activity, heart rate,
1/16 C temperatures) are compared exactly; float sums to 1e-10 relative.
"""

from __future__ import annotations

import numpy as np
import pytest

from freamer_rl.data import pamap2_features, synthetic_recording

# (subject, duration_s, seed, activities) -> reference numbers of the original module
CASES = {
    "protocol_timeline": (101, 30.0, 3, None),
    "explicit_activities": (102, 20.0, 1, [(5, 8.0), (0, 3.0), (24, 9.0)]),
}
REFERENCE = {
    "protocol_timeline": {
        "shape": (3000, 54),
        "n_nan": 2728,
        "exact_cols": {0: 74565.0, 1: 2900.0, 2: 17581.0, 3: 96937.5, 51: 0.0},
        "float_cols": {4: 7582.461918475919, 12: 0.6812987274115169, 24: 1390.6524646349371, 40: 19211.40213467103},
        "weighted": 1265681.3286737455,  # nansum(a * [1..54])
        "squares": 34829346.83921816,
        "physiology": (58.39365581569149, 10.998790504489062, 17.481453326546756),
        "segments": [(0, 4.0), (1, 15.0), (0, 4.0), (2, 15.0)],
        "features": (139.54441548869363, 54.49088794384443, 323.7858955630072),
    },
    "explicit_activities": {
        "shape": (2000, 54),
        "n_nan": 1818,
        "exact_cols": {0: 37730.0, 1: 25600.0, 2: 24987.0, 3: 64760.25, 51: 0.0},
        "float_cols": {4: 4809.202133391018, 12: 7.359269630883805, 24: 511.7593484944736, 40: -186.30198025095063},
        "weighted": 3264836.1278661396,
        "squares": 27484029.341660555,
        "physiology": (58.26037302615678, 12.046070565347346, 13.029565167950048),
        "segments": [(5, 8.0), (0, 3.0), (24, 9.0)],
        "features": (103.76418243988883, 78.09264616167638, 716.8392622930696),
    },
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_seeded_recording_matches_the_original_generator(case):
    subject, duration_s, seed, activities = CASES[case]
    ref = REFERENCE[case]
    rec = synthetic_recording(subject, duration_s=duration_s, seed=seed, activities=activities)
    a = rec.to_array()
    assert a.shape == ref["shape"]
    assert int(np.isnan(a).sum()) == ref["n_nan"]
    for col, total in ref["exact_cols"].items():
        assert float(np.nansum(a[:, col])) == total, f"column {col}"
    for col, total in ref["float_cols"].items():
        assert float(np.nansum(a[:, col])) == pytest.approx(total, rel=1e-10), f"column {col}"
    assert float(np.nansum(a * np.arange(1, 55))) == pytest.approx(ref["weighted"], rel=1e-10)
    assert float(np.nansum(a**2)) == pytest.approx(ref["squares"], rel=1e-10)
    assert (rec.info["hr_rest"], rec.info["hr_gain"], rec.info["tau_hr"]) == ref["physiology"]
    assert rec.info["segments"] == ref["segments"]


@pytest.mark.parametrize("case", sorted(CASES))
def test_features_of_seeded_recording_match_the_original(case):
    subject, duration_s, seed, activities = CASES[case]
    imu_sum, hr_sum, hr_weighted = REFERENCE[case]["features"]
    f = pamap2_features(synthetic_recording(subject, duration_s=duration_s, seed=seed, activities=activities))
    h = f.hr_features.astype(np.float64)
    assert float(f.imu.astype(np.float64).sum()) == pytest.approx(imu_sum, rel=1e-10)
    assert float(h.sum()) == pytest.approx(hr_sum, rel=1e-10)
    assert float((h * np.arange(1, 17)).sum()) == pytest.approx(hr_weighted, rel=1e-10)


def test_lower_row_rate_samples_the_same_session():
    """``row_rate_hz`` keeps the timeline and physiology of the seed and samples the same models more sparsely."""
    full = synthetic_recording(103, duration_s=900.0, seed=5)
    sparse = synthetic_recording(103, duration_s=900.0, seed=5, row_rate_hz=1.0)
    assert len(full) == 90_000 and len(sparse) == 900
    assert np.diff(sparse.timestamp) == pytest.approx(np.ones(899))
    assert sparse.info["segments"] == full.info["segments"] and sparse.info["row_rate_hz"] == 1.0
    assert (sparse.info["hr_rest"], sparse.info["tau_hr"]) == (full.info["hr_rest"], full.info["tau_hr"])
    assert not np.isnan(sparse.heart_rate).any()  # below ~9 Hz every row has a heart rate
    # the same activity at the same second, and a heart rate that follows the same lag model (noise differs)
    assert (sparse.activity == full.activity[::100]).mean() > 0.98  # rows at the segment edges may round apart
    hr_full = pamap2_features(full, rate_hz=0.2).heart_rate
    hr_sparse = pamap2_features(sparse, rate_hz=0.2).heart_rate
    assert hr_full.shape == hr_sparse.shape == (180,)
    assert abs(float(hr_full.mean() - hr_sparse.mean())) < 2.0
    assert np.corrcoef(hr_full, hr_sparse)[0, 1] > 0.9


@pytest.mark.parametrize("rate", [0.0, 3.0, 150.0])
def test_row_rate_must_divide_100(rate):
    with pytest.raises(ValueError, match="row_rate_hz"):
        synthetic_recording(101, duration_s=10.0, row_rate_hz=rate)
