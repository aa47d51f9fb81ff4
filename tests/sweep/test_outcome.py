import math

import pandas as pd
import pytest

from carp.sweep.outcome import (
    TRIALS_COLUMNS,
    TrialRecord,
    best_record,
    best_tokenizer_error,
    pareto_front,
    ranking_key,
    should_prune,
    write_trials_csv,
)
from carp.sweep.space import TrialSettings

SETTINGS = TrialSettings((1, 2, 4), 64)


def record(number, state="COMPLETE", success=None, latency=None, error=None, settings=SETTINGS, score=None):
    experiment = f"sweep-s-t{number}" if success is not None else ""
    return TrialRecord(number, state, settings, success, latency, error, experiment, score)


def test_prune_decision():
    assert not should_prune(30.0, None, 2.0)  # the first trial has nothing to compare with
    assert not should_prune(20.0, 10.0, 2.0)  # exactly at the factor is kept
    assert should_prune(20.01, 10.0, 2.0)
    assert not should_prune(5.0, 10.0, 2.0)
    assert should_prune(math.nan, None, 2.0)  # a diverged tokenizer never trains a policy


def test_best_tokenizer_error_ignores_current_missing_and_nan():
    records = [record(0, error=12.0), record(1, "PRUNED", error=8.0), record(2, "FAIL"), record(3, error=math.nan)]
    assert best_tokenizer_error(records) == 8.0
    assert best_tokenizer_error(records, exclude_number=1) == 12.0
    assert best_tokenizer_error([record(2, "RUNNING")]) is None


def test_objective_tie_break_success_then_latency_then_number():
    records = [
        record(0, success=0.5, latency=3.0),
        record(1, success=0.75, latency=9.0),
        record(2, success=0.75, latency=4.0),
        record(3, success=0.75, latency=4.0),
        record(4, "PRUNED", error=99.0),
        record(5, "FAIL"),
    ]
    assert best_record(records).number == 2
    ordered = sorted((r for r in records if r.validation_success_rate is not None), key=ranking_key)
    assert [r.number for r in ordered] == [2, 3, 1, 0]
    assert best_record(records[4:]) is None


def test_the_validation_score_ranks_first_and_validation_success_breaks_its_ties():
    # Push-T-like trials: rarely a success, but the coverage they reach tells them apart.
    records = [
        record(0, success=0.0, latency=1.0, score=0.55),
        record(1, success=0.1, latency=2.0, score=0.70),
        record(2, success=0.0, latency=1.0, score=0.70),
        record(3, success=0.2, latency=1.0, score=0.40),
    ]
    assert [r.number for r in sorted(records, key=ranking_key)] == [1, 2, 0, 3]
    # A record without a score (an arm task's, or one stored before scores) ranks by its success rate.
    assert record(4, success=0.3, latency=1.0).objective == 0.3


def test_the_pareto_front_keeps_the_trials_no_other_beats_on_score_and_latency_at_once():
    records = [
        record(0, success=0.8, latency=5.0),  # the best score
        record(1, success=0.6, latency=2.0),  # faster than 0, worse score: on the front
        record(2, success=0.6, latency=3.0),  # beaten by 1
        record(3, success=0.4, latency=1.0),  # the fastest
        record(4, success=0.8, latency=5.0),  # equal to 0: neither beats the other
        record(5, "PRUNED", error=9.0),
    ]
    assert [r.number for r in pareto_front(records)] == [0, 4, 1, 3]


def test_trials_csv_has_the_report_columns(tmp_path):
    path = tmp_path / "sweep" / "trials.csv"
    records = [
        record(1, "PRUNED", error=40.0, settings=TrialSettings((4,), 8)),
        record(0, success=0.5, latency=3.25, error=10.0),
        TrialRecord(2, "RUNNING", None),
    ]
    write_trials_csv(records, path)
    table = pd.read_csv(path)
    assert tuple(table.columns) == TRIALS_COLUMNS
    assert table["trial"].tolist() == [0, 1, 2]
    assert table.loc[0, "scales"] == "[1,2,4]" and table.loc[0, "num_scales"] == 3
    assert table.loc[0, "validation_success_rate"] == pytest.approx(0.5)
    assert table.loc[0, "latency_ms"] == pytest.approx(3.25)
    assert table.loc[0, "validation_score"] == pytest.approx(0.5)  # no score of its own: the success rate
    assert table.loc[1, "state"] == "PRUNED" and math.isnan(table.loc[1, "validation_success_rate"])
    assert table["pareto"].tolist() == [True, False, False]
    assert table.loc[1, "tokenizer_rmse_percent"] == pytest.approx(40.0)
    assert table.loc[0, "dvc_experiment"] == "sweep-s-t0"
