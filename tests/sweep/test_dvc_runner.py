import json
import logging
import shutil
import subprocess
from pathlib import Path

import pandas as pd
import pytest
import yaml
from dvc.utils.hydra import apply_overrides

from carp.config import load_params
from carp.evaluation.progress import PROGRESS_VARIABLE, ProgressFile, ValidatedCandidate
from carp.sweep import dvc_runner
from carp.sweep.dvc_runner import (
    TOKENIZER_ERROR_KEY,
    DvcExperimentRunner,
    eval_arguments,
)
from carp.sweep.space import TrialSettings
from carp.sweep.study import ExperimentFailedError, ExperimentStoppedError

REPO = Path(__file__).resolve().parents[2]
SETTINGS = TrialSettings((1, 2, 4), 16)


class RecordedDvc:
    """Stands in for `subprocess.run`: records each dvc command and its environment, fails the chosen ones."""

    def __init__(self, failing: str = "") -> None:
        self.calls: list[tuple[list[str], dict | None]] = []
        self.failing = failing

    def __call__(self, command, cwd, env):
        arguments = command[3:]  # after `python -m dvc`
        self.calls.append((arguments, env))
        return subprocess.CompletedProcess(command, 1 if self.failing and self.failing in arguments else 0)


class FakeExperiment:
    """Stands in for `subprocess.Popen` of `dvc exp run`: validates one candidate per `wait`, as the evaluate stage
    does, appending it to the progress file the environment names and stopping once a stop file appears."""

    launched: list["FakeExperiment"] = []
    epochs = (2, 4, 6)
    exit_status = 0

    def __init__(self, command, cwd, env):
        self.arguments = command[3:]
        self.env = env
        self.progress = ProgressFile(Path(env[PROGRESS_VARIABLE]))
        self.pending = list(self.epochs)
        self.returncode = None
        FakeExperiment.launched.append(self)

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        return False

    def wait(self, timeout=None):
        if self.progress.stop_requested():
            self.returncode = 1  # the stage fails with "stopped ...", and DVC with it
        elif self.pending:
            epoch = self.pending.pop(0)
            self.progress.append(ValidatedCandidate("lift/carp/seed0", epoch, epoch / 10, epoch / 10))
            raise subprocess.TimeoutExpired(self.arguments, timeout)
        else:
            self.returncode = self.exit_status
        return self.returncode


@pytest.fixture
def fake_experiment(monkeypatch):
    FakeExperiment.launched = []
    FakeExperiment.exit_status = 0
    monkeypatch.setattr(dvc_runner.subprocess, "Popen", FakeExperiment)
    monkeypatch.setattr(dvc_runner, "POLL_SECONDS", 0.0)
    return FakeExperiment


def _report(tmp_path, task, policy, seed):
    return tmp_path / "eval" / task / policy / f"seed{seed}.json"


def _runner(tmp_path, git_remote="", environment=None, seeds=(0, 1)):
    return DvcExperimentRunner(
        tmp_path,
        tmp_path / "tokenizer.json",
        lambda task, policy, seed: _report(tmp_path, task, policy, seed),
        ["lift"],
        ["carp"],
        seeds,
        git_remote,
        environment or {},
        validation_episodes=5,
    )


def _workspace(tmp_path):
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"scales": [1, 2], "codebook_size": 8, "other": 3}))
    (tmp_path / "tokenizer.json").write_text(json.dumps({TOKENIZER_ERROR_KEY: 2.5}))
    # Validation-only summaries, as the evaluate stage writes them for a trial.
    for seed, (success, predict, decode, score) in enumerate([(0.5, 1.0, 2.0, 0.8), (1.0, 3.0, 4.0, 1.0)]):
        report = _report(tmp_path, "lift", "carp", seed)
        report.parent.mkdir(parents=True, exist_ok=True)
        summary = {
            "validation_success_rate": success,
            "validation_score": score,
            "latency_predict_ms_median": predict,
            "latency_decode_ms_median": decode,
            "test_episodes": 0,
        }
        report.write_text(json.dumps(summary))


def test_tokenizer_stage_runs_with_the_trial_values_and_its_experiment_name(tmp_path, monkeypatch):
    dvc = RecordedDvc()
    monkeypatch.setattr(dvc_runner.subprocess, "run", dvc)
    _workspace(tmp_path)
    runner = _runner(tmp_path, environment={"HOME": "/h"})
    assert runner.train_tokenizer("sweep-s-t0", SETTINGS) == 2.5
    assert dvc.calls == [(["repro", "train_tokenizer"], {"HOME": "/h", "DVC_EXP_NAME": "sweep-s-t0"})]
    assert yaml.safe_load((tmp_path / "params.yaml").read_text()) == {
        "scales": [1, 2, 4],
        "codebook_size": 16,
        "other": 3,
    }


def test_a_trial_evaluates_on_validation_seeds_only_reports_each_candidate_and_averages_validation_figures(
    tmp_path, monkeypatch, fake_experiment, caplog
):
    dvc = RecordedDvc(failing="push")
    monkeypatch.setattr(dvc_runner.subprocess, "run", dvc)
    _workspace(tmp_path)
    runner = _runner(tmp_path, git_remote="origin", environment={"HOME": "/h"})
    reported = []
    with caplog.at_level(logging.WARNING):
        result = runner.run_experiment("sweep-s-t1", SETTINGS, lambda candidate: reported.append(candidate) and False)
    (experiment,) = fake_experiment.launched
    assert experiment.arguments == [
        "exp", "run", "--name", "sweep-s-t1", "-S", "scales=[1,2,4]", "-S", "codebook_size=16",
        "-S", "eval.run_test=false", "-S", "eval.selection=best_validation", "-S", "eval.validation_episodes=5",
        "-S", "seeds=[0,1]", "evaluate",
    ]  # fmt: skip
    assert experiment.env == {"HOME": "/h", PROGRESS_VARIABLE: str(runner.progress.path)}
    assert [candidate.epoch for candidate in reported] == [2, 4, 6]
    assert (result.validation_success_rate, result.latency_ms, result.tokenizer_rmse_percent) == pytest.approx(
        (0.75, 5.0, 2.5)
    )
    assert result.objective == pytest.approx(0.9)
    assert [arguments for arguments, _ in dvc.calls] == [["exp", "push", "origin", "sweep-s-t1"]]
    assert "push it later with: dvc exp push origin sweep-s-t1" in caplog.text


def test_a_pruned_trial_stops_its_experiment_after_the_candidate_that_decided_it(tmp_path, fake_experiment):
    _workspace(tmp_path)
    reported = []

    def prune_at_the_second(candidate):
        reported.append(candidate.epoch)
        return len(reported) == 2

    with pytest.raises(ExperimentStoppedError):
        _runner(tmp_path).run_experiment("sweep-s-t2", SETTINGS, prune_at_the_second)
    # The third candidate never ran: the stage saw the stop file after the second.
    assert reported == [2, 4] and fake_experiment.launched[0].pending == [6]


def test_a_failed_experiment_fails_the_trial_with_the_command_and_status(tmp_path, fake_experiment):
    _workspace(tmp_path)
    fake_experiment.exit_status = 1
    with pytest.raises(
        ExperimentFailedError, match=r"`dvc exp run --name t2 -S scales=\[1,2,4\] .*` exited with status 1"
    ):
        _runner(tmp_path).run_experiment("t2", SETTINGS, lambda candidate: False)


def test_the_confirmation_trains_its_seeds_and_reads_the_test_evaluations(tmp_path, monkeypatch):
    dvc = RecordedDvc()
    monkeypatch.setattr(dvc_runner.subprocess, "run", dvc)
    for seed in (3, 4):
        report = _report(tmp_path, "lift", "carp", seed)
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(json.dumps({"success_rate": 0.5, "score": 0.5}))
        pd.DataFrame({"seed": [100_000, 100_001], "success": [True, False], "steps": [50, 400]}).to_csv(
            report.with_name(f"seed{seed}_episodes.csv"), index=False
        )
    runs = _runner(tmp_path).run_confirmation("sweep-s-confirm", SETTINGS, (3, 4))
    assert dvc.calls[0][0] == [
        "exp", "run", "--name", "sweep-s-confirm", "-S", "scales=[1,2,4]", "-S", "codebook_size=16",
        "-S", "eval.run_test=true", "-S", "eval.selection=best_validation", "-S", "eval.validation_episodes=5",
        "-S", "seeds=[3,4]", "evaluate",
    ]  # fmt: skip
    assert list(runs) == ["lift"] and sorted(runs["lift"]) == [3, 4]
    assert runs["lift"][3].episodes["seed"].tolist() == [100_000, 100_001]


def test_the_overrides_make_valid_params_of_the_defaults_that_keep_trials_off_the_test_seeds(tmp_path):
    # The repository's params have no validation episodes: the sweep's own count makes them valid experiments.
    shutil.copy(REPO / "params.yaml", tmp_path / "params.yaml")
    assert load_params(tmp_path / "params.yaml").eval.validation_episodes == 0
    runner = _runner(tmp_path)
    apply_overrides(str(tmp_path / "params.yaml"), eval_arguments(runner.trial_eval_settings()))
    trial = load_params(tmp_path / "params.yaml").eval
    assert (trial.run_test, trial.selection, trial.validation_episodes) == (False, "best_validation", 5)
    apply_overrides(str(tmp_path / "params.yaml"), eval_arguments(runner.confirmation_eval_settings()))
    assert load_params(tmp_path / "params.yaml").eval.run_test is True
