"""The sweep's trials never run a test episode; its closing confirmation does, and its verdict is the result."""

import dataclasses

import optuna

from carp.sweep.confirmation import ConfirmationPlan
from carp.sweep.space import TrialSettings
from carp.sweep.study import CONFIRMATION_ATTR, run_sweep
from tests.sweep.conftest import EVAL, FakeRunner

DEFAULT = TrialSettings((4,), 4)  # one scale: the fake's weakest settings


def plan(default=DEFAULT, worker="here"):
    return ConfirmationPlan(default=default, seeds=(0, 1, 2), margin=0.05, alpha=0.05, worker=worker)


def test_no_trial_runs_a_test_seed_and_the_confirmation_tests_both_arms(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 10.0})
    result = run_sweep(dataclasses.replace(sweep_config, num_trials=6), runner, tmp_path, confirmation=plan())

    test_seeds = set(EVAL.test_seeds())
    trial_names = {name for name, _ in runner.experiment_calls}
    trial_seeds = [seeds for name, _, seeds in runner.episode_seeds if name in trial_names]
    assert trial_seeds and all(not set(seeds) & test_seeds for seeds in trial_seeds)
    assert all(set(seeds) <= set(EVAL.validation_seeds()) for seeds in trial_seeds)
    confirmation_seeds = [seeds for name, _, seeds in runner.episode_seeds if name not in trial_names]
    assert EVAL.test_seeds() in confirmation_seeds

    best = result.best
    assert [(settings, seeds) for _, settings, seeds in runner.confirmation_calls] == [
        (best.settings, (0, 1, 2)),
        (DEFAULT, (0, 1, 2)),
    ]
    lines = (tmp_path / "best_params.txt").read_text().splitlines()
    assert lines[0] == best.settings.command_line()
    assert lines[1].startswith(f"# trial {best.number} ({best.dvc_experiment}), selected on the validation seeds")
    assert "validation score 1.000, validation success 100.0%" in lines[1]
    assert "against the default settings -S 'scales=[4]' -S codebook_size=4" in lines[2]
    # The winner reached 100% on validation; its test figure comes from the confirmation, side by side.
    assert lines[3].startswith("# lift: validation success 100.0% | test success ")
    assert "% selected, " in lines[3] and "% default: selected better." in lines[3]
    assert result.confirmation[-1] == lines[3].removeprefix("# ")


def test_the_default_settings_as_winner_train_once_and_say_so(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 10.0})
    config = dataclasses.replace(sweep_config, scale_schedules=((1, 4),), codebook_sizes=(4,), num_trials=1)
    result = run_sweep(config, runner, tmp_path, confirmation=plan(default=TrialSettings((1, 4), 4)))
    assert len(runner.confirmation_calls) == 1
    assert "the selected settings are the default ones, trained once; nothing to compare" in result.confirmation[1]
    assert result.confirmation[2].startswith("lift: validation success 100.0% | test success")


def test_a_resumed_sweep_keeps_the_confirmed_arms(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 10.0})
    first = run_sweep(sweep_config, runner, tmp_path, confirmation=plan())
    again = run_sweep(sweep_config, runner, tmp_path, confirmation=plan())
    assert len(runner.confirmation_calls) == 2  # both arms once, not again on resume
    assert again.confirmation == first.confirmation


def test_one_worker_confirms_and_the_others_report_its_verdict(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 10.0})
    elsewhere = run_sweep(sweep_config, runner, tmp_path / "a", confirmation=plan(worker="host:/a"))
    other = FakeRunner(errors={4: 10.0, 8: 10.0})
    here = run_sweep(sweep_config, other, tmp_path / "b", confirmation=plan(worker="host:/b"))
    assert other.confirmation_calls == [] and here.confirmation == elsewhere.confirmation
    stored = optuna.load_study(study_name="unit", storage=sweep_config.storage).user_attrs[CONFIRMATION_ATTR]
    assert stored["lines"] == list(elsewhere.confirmation)
