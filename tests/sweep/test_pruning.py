import dataclasses

import optuna
import pytest

from carp.evaluation.progress import ProgressFile, ValidatedCandidate
from carp.sweep.pruning import ValidationCurve, make_pruner
from carp.sweep.study import run_sweep
from tests.sweep.conftest import EPOCHS, FakeRunner


def test_the_pruner_param_picks_optunas_pruner(sweep_config):
    kinds = {
        "successive_halving": optuna.pruners.SuccessiveHalvingPruner,
        "hyperband": optuna.pruners.HyperbandPruner,
        "none": optuna.pruners.NopPruner,
    }
    for name, kind in kinds.items():
        assert isinstance(make_pruner(dataclasses.replace(sweep_config, pruner=name)), kind)


def test_the_curve_is_the_mean_of_each_evaluations_best_validation_so_far():
    curve = ValidationCurve()
    values = [
        curve.add(ValidatedCandidate(evaluation, epoch, score, score))
        for evaluation, epoch, score in [("a", 2, 0.4), ("a", 4, 0.2), ("a", 6, 0.6), ("b", 2, 0.2), ("b", 4, 0.4)]
    ]
    assert values == [(1, 0.4), (2, 0.4), (3, 0.6), (4, pytest.approx(0.4)), (5, pytest.approx(0.5))]


def test_the_progress_file_hands_over_complete_lines_only(tmp_path):
    progress = ProgressFile(tmp_path / "progress.jsonl")
    progress.append(ValidatedCandidate("lift/carp/seed0", 2, 0.5, 0.5))
    with progress.path.open("a") as handle:
        handle.write('{"evaluation": "lift/carp/seed0", "ep')  # a line still being written
    read, offset = progress.read(0)
    assert read == [ValidatedCandidate("lift/carp/seed0", 2, 0.5, 0.5)]
    assert progress.read(offset) == ([], offset)
    assert not progress.stop_requested()
    progress.request_stop()
    assert progress.stop_requested()
    progress.clear()
    assert not progress.path.exists() and not progress.stop_requested()


def test_successive_halving_prunes_a_trial_behind_at_a_rung_and_stops_its_validation(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 10.0})
    config = dataclasses.replace(sweep_config, num_trials=6, pruner="successive_halving")
    result = run_sweep(config, runner, tmp_path)
    pruned = [record for record in result.records if record.state == "PRUNED"]
    assert pruned, "one-scale trials score half the others at every snapshot"
    for record in pruned:
        assert record.settings.num_scales == 1  # the weak settings, and only they
        # Stopped before its last candidate: the later validation episodes never ran.
        assert runner.validated[record_name(record)] < len(EPOCHS)
        assert record.validated_candidates == runner.validated[record_name(record)]
    assert result.best.settings.num_scales == 2


def record_name(record):
    return f"sweep-unit-t{record.number}"
