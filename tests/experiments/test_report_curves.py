"""The suite's curve bands: seeds that stop at their success target hold their last value, unfinished runs cut the
grid (experiments/report.py ``band_curves``)."""

import numpy as np
import pytest

from freamer_rl.experiments.report import band_curves


def _run(points: list[tuple[int, float | None]], finished: bool) -> dict:
    return {"rows": [{"frames": f, "success_rate": v} for f, v in points], "finished": finished}


def test_a_seed_stopped_at_its_target_holds_its_last_value_to_the_longest_run():
    early = _run([(0, 0.0), (50, 0.96)], finished=True)
    late = _run([(0, 0.0), (100, 1.0)], finished=True)
    grid, ys = band_curves([early, late], "success_rate", points=11)
    assert grid[-1] == 100
    np.testing.assert_allclose(ys[0, grid >= 50], 0.96)  # held past its stop
    np.testing.assert_allclose(ys[1], np.linspace(0.0, 1.0, 11))
    np.testing.assert_allclose(np.mean(ys, axis=0)[-1], 0.98)  # the mean reaches the longest run's end


def test_an_unfinished_run_ends_the_grid_where_it_ends():
    running = _run([(0, 0.0), (60, 0.3)], finished=False)
    done = _run([(0, 0.0), (100, 1.0)], finished=True)
    grid, ys = band_curves([running, done], "success_rate", points=7)
    assert grid[-1] == 60  # no value is invented for frames the unfinished run has not seen
    np.testing.assert_allclose(ys[1], np.linspace(0.0, 0.6, 7))


@pytest.mark.parametrize("finished", [True, False])
def test_rows_without_the_metric_are_skipped_and_a_run_without_any_is_nan(finished):
    gap = _run([(0, 0.0), (40, None), (80, 0.8)], finished=finished)
    empty = _run([(0, None), (80, None)], finished=finished)
    grid, ys = band_curves([gap, empty], "success_rate", points=5)
    np.testing.assert_allclose(ys[0], grid / 100.0)  # interpolated across the missing row
    assert np.isnan(ys[1]).all()
