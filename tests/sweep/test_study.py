import dataclasses
import subprocess
import sys
import warnings
from pathlib import Path

import optuna
import pandas as pd
import pytest
from optuna.exceptions import ExperimentalWarning
from optuna.trial import TrialState

from carp.sweep.outcome import TrialRecord
from carp.sweep.space import TrialSettings, parse_schedule_label
from carp.sweep.study import SweepResult, SweepStateError, experiment_name, run_sweep
from tests.sweep.conftest import FakeRunner, expected_success

REPO = Path(__file__).resolve().parents[2]


def load_trials(config):
    return optuna.load_study(study_name=config.study_name, storage=config.storage).get_trials()


def test_budget_pruning_and_reports(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 25.0})  # V=8 is 2.5x worse than V=4
    config = dataclasses.replace(sweep_config, num_trials=6)
    result = run_sweep(config, runner, tmp_path / "reports")

    assert result.finished_trials == 6 and len(result.records) == 6
    tried = {record.settings for record in result.records}
    assert len(tried) == 6  # brute force never repeats a grid point
    for record in result.records:
        if record.settings.codebook_size == 8 and record.state == "PRUNED":
            assert record.validation_success_rate is None and record.tokenizer_rmse_percent == 25.0
    pruned = [r for r in result.records if r.state == "PRUNED"]
    # V=8 is pruned whenever a V=4 trial ran before it.
    first_small = min(r.number for r in result.records if r.settings.codebook_size == 4)
    assert {r.number for r in pruned} == {
        r.number for r in result.records if r.settings.codebook_size == 8 and r.number > first_small
    }
    ran = {settings for _, settings in runner.experiment_calls}
    assert all(r.settings not in ran for r in pruned)
    for name, settings in runner.experiment_calls:
        number = next(r.number for r in result.records if r.settings == settings)
        assert name == experiment_name("unit", number) == f"sweep-unit-t{number}"

    best = result.best
    assert best.validation_success_rate == 1.0
    # [1,4] and [1,2,4] tie on success (fake caps at K=2); the lower latency ([1,4]) wins.
    assert best.settings.scales == (1, 4)
    table = pd.read_csv(tmp_path / "reports" / "trials.csv")
    assert len(table) == 6 and set(table["state"]) <= {"COMPLETE", "PRUNED"}
    best_params = (tmp_path / "reports" / "best_params.txt").read_text().splitlines()
    assert best_params[0] == best.settings.command_line()
    assert best_params[1:] == ["# not confirmed on the test seeds (the sweep ran without a confirmation)"]


def test_budget_holds_across_resumes_and_grid_exhaustion(sweep_config, tmp_path):
    runner = FakeRunner()
    run_sweep(dataclasses.replace(sweep_config, num_trials=2), runner, tmp_path)
    again = run_sweep(dataclasses.replace(sweep_config, num_trials=2), runner, tmp_path)
    assert again.finished_trials == 2 and len(runner.tokenizer_calls) == 2
    more = run_sweep(dataclasses.replace(sweep_config, num_trials=3), runner, tmp_path)
    assert more.finished_trials == 3 and len(runner.tokenizer_calls) == 3
    # The grid has 6 points: a larger budget stops when every point was tried.
    everything = run_sweep(dataclasses.replace(sweep_config, num_trials=50), runner, tmp_path)
    assert everything.finished_trials == 6 and len(set(runner.tokenizer_calls)) == 6


def test_interrupted_trial_is_retried_with_same_params(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 10.0}, interrupt_on_experiment=2)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(sweep_config, runner, tmp_path)
    interrupted = [t for t in load_trials(sweep_config) if t.state == TrialState.FAIL]
    assert len(interrupted) == 1 and interrupted[0].user_attrs["interrupted"] is True
    # Written on the way out, with the retry the interrupted worker queued before exiting.
    assert pd.read_csv(tmp_path / "trials.csv")["state"].tolist() == ["COMPLETE", "FAIL", "WAITING"]

    runner.interrupt_on_experiment = None
    result = run_sweep(sweep_config, runner, tmp_path)
    trials = load_trials(sweep_config)
    retry = next(t for t in trials if t.system_attrs.get("failed_trial") == interrupted[0].number)
    assert retry.state == TrialState.COMPLETE and retry.params == interrupted[0].params
    assert retry.user_attrs["interrupted"] is None  # not inherited from the interrupted attempt
    assert result.finished_trials == 3  # the interrupted attempt does not count
    assert sum(t.state == TrialState.COMPLETE for t in trials) == 3 and len(trials) == 4


def test_failed_experiment_fails_the_trial_and_counts(sweep_config, tmp_path):
    runner = FakeRunner(errors={4: 10.0, 8: 10.0}, fail_on_experiment=1)
    result = run_sweep(sweep_config, runner, tmp_path)
    assert [r.state for r in result.records] == ["FAIL", "COMPLETE", "COMPLETE"]
    assert result.finished_trials == 3
    # A real failure is not retried on resume.
    assert run_sweep(sweep_config, runner, tmp_path).finished_trials == 3 and len(runner.experiment_calls) == 3


def test_changed_search_space_is_refused(sweep_config, tmp_path):
    run_sweep(dataclasses.replace(sweep_config, num_trials=1), FakeRunner(), tmp_path)
    changed = dataclasses.replace(sweep_config, codebook_sizes=(4, 16))
    with pytest.raises(SweepStateError, match="use a new sweep.study_name"):
        run_sweep(changed, FakeRunner(), tmp_path)


@pytest.mark.slow
def test_trial_of_a_killed_sweep_is_retried_after_its_heartbeat_expires(sweep_config, tmp_path):
    # Leave a RUNNING trial with a heartbeat behind, as a sweep killed with SIGKILL would.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        storage = optuna.storages.RDBStorage(sweep_config.storage, heartbeat_interval=1)
        study = optuna.create_study(study_name="unit", storage=storage, direction="maximize")
        warnings.simplefilter("ignore", UserWarning)  # asking outside optimize() is the point here
        orphan = study.ask()
    orphan.suggest_categorical("scales", ["[4]", "[1,4]", "[1,2,4]"])
    orphan.suggest_categorical("codebook_size", [4, 8])
    storage.record_heartbeat(orphan._trial_id)

    runner = FakeRunner(errors={4: 10.0, 8: 10.0})
    result = run_sweep(sweep_config, runner, tmp_path)
    trials = load_trials(sweep_config)
    assert trials[orphan.number].state == TrialState.FAIL
    retry = next(t for t in trials if t.system_attrs.get("failed_trial") == orphan.number)
    assert retry.state == TrialState.COMPLETE and retry.params == orphan.params
    assert result.finished_trials == 3 and len(trials) == 4
    # The orphan's point ran once, as the retry (claimed for the orphan, so never handed out as a new point).
    orphan_settings = TrialSettings(parse_schedule_label(orphan.params["scales"]), orphan.params["codebook_size"])
    assert runner.tokenizer_calls.count(orphan_settings) == 1 and len(set(runner.tokenizer_calls)) == 3
    assert retry.user_attrs["validation_success_rate"] == expected_success(orphan_settings)


@pytest.mark.slow
def test_two_worker_processes_share_an_sqlite_study_on_one_machine(tmp_path):
    # The claims work the same in SQLite: two processes sharing one absolute path split the grid, each point once.
    log = tmp_path / "events.log"
    command = [sys.executable, "-m", "tests.sweep.stub_worker", "--storage", f"sqlite:///{tmp_path / 'optuna.db'}"]
    workers = [
        subprocess.Popen(
            [*command, "--study", "shared", "--trials", "50", "--reports", str(tmp_path / f"reports-{index}"),
             "--log", str(log), "--seconds", "0.5"],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for index in range(2)
    ]  # fmt: skip
    for worker in workers:
        _, errors = worker.communicate(timeout=300)
        assert worker.returncode == 0, errors[-3000:]
    starts = [line.split()[1:3] for line in log.read_text().splitlines() if line.startswith("start ")]
    assert len(starts) == 6 and len({tuple(point) for point in starts}) == 6
    trials = optuna.load_study(study_name="shared", storage=f"sqlite:///{tmp_path / 'optuna.db'}").get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 6


def test_summary_names_the_best_trial_and_how_to_fetch_it(sweep_config):
    best = TrialRecord(3, "COMPLETE", TrialSettings((1, 2), 8), 0.75, 1.25, 2.0, "sweep-s-t3")
    records = [best, TrialRecord(4, "PRUNED", TrialSettings((1, 2), 4)), TrialRecord(5, "COMPLETE", None)]
    config = dataclasses.replace(sweep_config, num_trials=4, git_remote="origin")
    lines = SweepResult(records, best, 3, ("confirmation line",)).summary_lines(config)
    assert lines == [
        f"study {config.study_name}: 3/4 trials finished {{'COMPLETE': 2, 'PRUNED': 1}}",
        "best: trial 3 (sweep-s-t3), validation score 0.750, validation success 75.0%, latency 1.25 ms; reproduce "
        "with: dvc exp run -S 'scales=[1,2]' -S codebook_size=8",
        "in any workspace: dvc exp pull origin sweep-s-t3 && dvc exp apply sweep-s-t3",
        "confirmation line",
    ]
    no_remote = dataclasses.replace(config, git_remote="")
    assert SweepResult(records, None, 3).summary_lines(no_remote) == lines[:1]
