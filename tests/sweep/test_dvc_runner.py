import json
import logging
import subprocess

import pytest
import yaml

from carp.sweep import dvc_runner
from carp.sweep.dvc_runner import TOKENIZER_ERROR_KEY, DvcExperimentRunner
from carp.sweep.space import TrialSettings
from carp.sweep.study import ExperimentFailedError

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


def _workspace(tmp_path):
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"scales": [1, 2], "codebook_size": 8, "other": 3}))
    (tmp_path / "tokenizer.json").write_text(json.dumps({TOKENIZER_ERROR_KEY: 2.5}))
    reports = []
    # The second summary predates the recorded score: its success rate stands in.
    for index, (success, predict, decode, score) in enumerate([(0.5, 1.0, 2.0, 0.8), (1.0, 3.0, 4.0, None)]):
        report = tmp_path / f"eval{index}.json"
        summary = {"success_rate": success, "latency_predict_ms_median": predict, "latency_decode_ms_median": decode}
        if score is not None:
            summary["score"] = score
        report.write_text(json.dumps(summary))
        reports.append(report)
    return reports


def test_tokenizer_stage_runs_with_the_trial_values_and_its_experiment_name(tmp_path, monkeypatch):
    dvc = RecordedDvc()
    monkeypatch.setattr(dvc_runner.subprocess, "run", dvc)
    runner = DvcExperimentRunner(tmp_path, tmp_path / "tokenizer.json", _workspace(tmp_path), "", {"HOME": "/h"})
    assert runner.train_tokenizer("sweep-s-t0", SETTINGS) == 2.5
    assert dvc.calls == [(["repro", "train_tokenizer"], {"HOME": "/h", "DVC_EXP_NAME": "sweep-s-t0"})]
    assert yaml.safe_load((tmp_path / "params.yaml").read_text()) == {
        "scales": [1, 2, 4],
        "codebook_size": 16,
        "other": 3,
    }


def test_experiment_metrics_are_averaged_over_every_evaluation_and_a_failed_push_only_warns(
    tmp_path, monkeypatch, caplog
):
    dvc = RecordedDvc(failing="push")
    monkeypatch.setattr(dvc_runner.subprocess, "run", dvc)
    runner = DvcExperimentRunner(tmp_path, tmp_path / "tokenizer.json", _workspace(tmp_path), "origin", {})
    with caplog.at_level(logging.WARNING):
        result = runner.run_experiment("sweep-s-t1", SETTINGS)
    assert (result.success_rate, result.latency_ms, result.tokenizer_rmse_percent) == pytest.approx((0.75, 5.0, 2.5))
    assert result.objective == pytest.approx(0.9)
    assert [arguments for arguments, _ in dvc.calls] == [
        ["exp", "run", "--name", "sweep-s-t1", "-S", "scales=[1,2,4]", "-S", "codebook_size=16"],
        ["exp", "push", "origin", "sweep-s-t1"],
    ]
    assert all(env is None for _, env in dvc.calls)  # the experiment inherits this process's environment
    assert "push it later with: dvc exp push origin sweep-s-t1" in caplog.text


def test_a_failed_experiment_fails_the_trial_with_the_command_and_status(tmp_path, monkeypatch):
    monkeypatch.setattr(dvc_runner.subprocess, "run", RecordedDvc(failing="run"))
    runner = DvcExperimentRunner(tmp_path, tmp_path / "tokenizer.json", _workspace(tmp_path), "", {})
    with pytest.raises(
        ExperimentFailedError, match=r"`dvc exp run --name t2 -S scales=\[1,2,4\] .*` exited with status 1"
    ):
        runner.run_experiment("t2", SETTINGS)
