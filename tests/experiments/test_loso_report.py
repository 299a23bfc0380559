"""The leave-one-subject-out section of a suite's summary.md (freamer_rl.experiments.health_table.loso_markdown),
from runs.csv-like rows with known values: fold means, the paired difference to the heart-rate rule, the fraction
of the oracle and the folds at or above the rule."""

import math

from freamer_rl.experiments.health_table import loso_markdown


def _run(encoder, fold, reward, rule, oracle, status="done", controller=None):
    return {
        "eval_ref_hr_controller_return": controller,
        "status": status,
        "label": f"{encoder}_fold{fold}",
        "encoder": encoder,
        "eval_subjects": str(fold),
        "eval_return_mean": reward,
        "eval_ref_hr_threshold_return": rule,
        "eval_ref_oracle_return": oracle,
    }


def _cells(lines, encoder):
    (row,) = [line for line in lines if line.startswith(f"| {encoder} |")]
    return [c.strip() for c in row.strip("|").split("|")]


def test_loso_row_gives_fold_means_paired_differences_and_folds_at_the_rule():
    results = [
        _run("mlp", 101, 50.0, 60.0, 100.0),
        _run("mlp", 101, 70.0, 60.0, 100.0),  # fold 101: mean 60 = the rule -> counts as at the rule
        _run("mlp", 102, 20.0, 40.0, 80.0),  # fold 102: 20 below the rule
        _run("mlp", 103, 99.0, 10.0, 100.0, status="failed"),  # not done: left out
    ]
    lines = loso_markdown(results)
    enc, folds, runs, reward, rule, oracle, vs_rule, vs_ctrl, of_oracle, at_rule, per_fold = _cells(lines, "mlp")
    assert (folds, runs, at_rule) == ("2", "3", "1/2")
    assert reward.startswith("40.0 [") and rule.startswith("50.0 [") and oracle.startswith("90.0 [")
    assert vs_rule.startswith("-10.0 [")  # (0 + -20) / 2: every fold weighs the same, whatever its seeds
    assert of_oracle.startswith("0.425 [")  # (0.6 + 0.25) / 2
    assert per_fold == "101: 60.0 / 60.0, 102: 20.0 / 40.0"
    low, high = (float(x) for x in vs_rule.split("[")[1].rstrip("]").split(","))
    assert low <= -10.0 <= high and low < high  # the folds are resampled: a real interval from two folds


def test_loso_section_needs_two_folds_and_tolerates_missing_references():
    assert loso_markdown([_run("mlp", 101, 50.0, 60.0, 100.0)]) == []  # one held-out set is not LOSO
    results = [_run("mlp", 101, 50.0, None, None), _run("mlp", 102, 30.0, None, math.nan)]
    enc, folds, runs, reward, rule, oracle, vs_rule, vs_ctrl, of_oracle, at_rule, per_fold = _cells(
        loso_markdown(results), "mlp"
    )
    assert reward.startswith("40.0 [") and (rule, oracle, vs_rule, of_oracle, at_rule) == ("", "", "", "", "")
    assert vs_ctrl == ""  # the controller was not scored
    assert per_fold == "101: 50.0, 102: 30.0"


def test_loso_row_gives_the_paired_difference_to_the_controller_where_scored():
    """A fold without the controller's return is left out of that column only."""
    results = [
        _run("mlp", 101, 70.0, 60.0, 100.0, controller=66.0),
        _run("mlp", 101, 60.0, 60.0, 100.0, controller=66.0),  # fold 101: mean 65 - 66 = -1
        _run("mlp", 102, 50.0, 40.0, 80.0, controller=45.0),  # fold 102: +5
        _run("mlp", 103, 30.0, 30.0, 80.0),  # not scored: in the rule's column, not the controller's
    ]
    cells = _cells(loso_markdown(results), "mlp")
    vs_rule, vs_ctrl = cells[6], cells[7]
    assert vs_rule.startswith("5.0 [")  # (5 + 10 + 0) / 3
    assert vs_ctrl.startswith("2.0 [")  # (-1 + 5) / 2
