"""End to end on tiny params: the Optuna sweep killed during its second trial and resumed to its end, seen from how
it resumes and from its trials and confirmation.

The sweep runs once per module, in a copy of the shared demos workspace (``lift_demos``), and serves both tests.
"""

import io
import json
import os
import signal
import subprocess
import time

import pandas as pd
import pytest
from optuna.trial import TrialState

from carp.sweep.confirmation import arm_key
from carp.sweep.space import TrialSettings
from tests.pipeline.experiments_support import (
    DEFAULT_SETTINGS,
    SWEEP,
    TEST_SEEDS,
    TRIAL_TIMEOUT_SECONDS,
    VALIDATION_SEEDS,
    comment_lines,
    committed_file,
    copy_workspace,
    experiments,
    head,
    mlflow_runs,
    study_trials,
    sweep_command,
)
from tests.pipeline.workspace import run, tool_env


@pytest.fixture(scope="module")
def killed_sweep(lift_demos, tmp_path_factory) -> dict:
    """A sweep killed during its second trial's training, then resumed to its end (confirmation included).

    Returns the workspace, the trials completed before the kill and the resumed sweep's completed process.
    """
    directory = tmp_path_factory.mktemp("killed-sweep")
    workspace = copy_workspace(lift_demos, directory, {**SWEEP, "prune_factor": 1000.0})
    log_path = directory / "sweep.log"
    with log_path.open("w") as log:
        sweep = subprocess.Popen(
            sweep_command(), cwd=workspace, env=tool_env(), stdout=log, stderr=subprocess.STDOUT, start_new_session=True
        )
    group = os.getpgid(sweep.pid)
    try:
        # Kill while the second trial's `dvc exp run` is running a stage: the worst moment for the workspace.
        deadline = time.monotonic() + 2 * TRIAL_TIMEOUT_SECONDS
        while not _second_trial_is_training(log_path.read_text()):
            assert sweep.poll() is None, log_path.read_text()[-3000:]
            assert time.monotonic() < deadline, "the second trial never started"
            time.sleep(1.0)
        completed_before = [t for t in study_trials(workspace) if t.state == TrialState.COMPLETE]
        assert [t.number for t in completed_before] == [0]
    finally:
        os.killpg(group, signal.SIGKILL)
        sweep.wait(timeout=60)
    _wait_until_group_is_gone(group)
    assert [t.state for t in study_trials(workspace)] == [TrialState.COMPLETE, TrialState.RUNNING]

    # The trials' evaluations and the confirmation's two arms of two training seeds each.
    resumed = run(sweep_command(), workspace, timeout=4 * TRIAL_TIMEOUT_SECONDS)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    return {"workspace": workspace, "completed_before": completed_before, "resumed": resumed}


@pytest.mark.slow
def test_killed_sweep_resumes_keeps_completed_trial_and_retries_the_interrupted_one(killed_sweep):
    workspace, completed_before, resumed = (killed_sweep[key] for key in ("workspace", "completed_before", "resumed"))
    trials = study_trials(workspace)
    assert [t.state for t in trials] == [TrialState.COMPLETE, TrialState.FAIL, TrialState.COMPLETE]
    kept, interrupted, retry = trials
    assert kept.user_attrs == completed_before[0].user_attrs and kept.values == completed_before[0].values
    assert retry.params == interrupted.params and retry.system_attrs["failed_trial"] == 1
    assert "2/2 trials finished" in resumed.stdout

    # The sweep's outputs describe every trial, the interrupted one included, and point at the best finished one.
    table = pd.read_csv(workspace / "reports/sweep/trials.csv")
    assert table["trial"].tolist() == [0, 1, 2] and table["state"].tolist() == ["COMPLETE", "FAIL", "COMPLETE"]
    shown = experiments(workspace)
    for trial, row in zip(trials, table.itertuples()):
        assert row.scales == trial.params["scales"] and row.codebook_size == trial.params["codebook_size"]
        assert row.num_scales == len(json.loads(trial.params["scales"]))
        if trial.state == TrialState.COMPLETE:
            assert row.tokenizer_rmse_percent == pytest.approx(trial.user_attrs["tokenizer_rmse_percent"])
            experiment = shown[f"sweep-tiny-t{trial.number}"]
            assert experiment["params"]["scales"] == json.loads(trial.params["scales"])
            assert experiment["params"]["codebook_size"] == trial.params["codebook_size"]
            metrics = experiment["metrics"]
            assert metrics["validation_success_rate"] == pytest.approx(row.validation_success_rate)
            assert metrics["validation_score"] == pytest.approx(row.validation_score)
            assert row.latency_ms == pytest.approx(
                metrics["latency_predict_ms_median"] + metrics["latency_decode_ms_median"]
            )
            # The only candidate (no snapshots) of the only evaluation reached the pruner through the progress file.
            assert row.validated_candidates == 1
            assert trial.intermediate_values == {1: pytest.approx(row.validation_score)}
        else:
            assert pd.isna(row.validation_success_rate)
    best = table[table["state"] == "COMPLETE"].sort_values(
        ["validation_score", "validation_success_rate", "latency_ms", "trial"], ascending=[False, False, True, True]
    )
    best_row = best.iloc[0]
    best_params = (workspace / "reports/sweep/best_params.txt").read_text()
    assert best_params.splitlines()[0] == f"-S 'scales={best_row.scales}' -S codebook_size={best_row.codebook_size}"

    runs = mlflow_runs(workspace)
    parents = [
        r for r in runs if r.data.tags.get("carp.sweep_study") == "tiny" and "mlflow.parentRunId" not in r.data.tags
    ]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"  # the resume reused the parent
    children = {r.data.tags["carp.trial_number"]: r for r in runs if "carp.trial_number" in r.data.tags}
    assert {number: r.info.status for number, r in children.items()} == {
        "0": "FINISHED",
        "1": "FAILED",
        "2": "FINISHED",
    }
    assert {r.data.tags["mlflow.parentRunId"] for r in children.values()} == {parents[0].info.run_id}
    assert {r.data.tags["carp.git_commit"] for r in children.values()} == {head(workspace)}
    # Every stage run of the first trial, the tokenizer stage (run by `dvc repro`) included, carries its name.
    first = [
        r for r in runs if r.data.tags.get("carp.dvc_experiment") == "sweep-tiny-t0" and "carp.dvc_stage" in r.data.tags
    ]
    assert {r.data.tags["carp.dvc_stage"] for r in first} == {
        "train_tokenizer",
        "register_tokenizer",
        "train_policy@lift-carp-0",
        "evaluate@lift-carp-0",
    }

    # The budget is spent and the confirmation saved: a third start runs no experiment and reports the same.
    again = run(sweep_command(), workspace, timeout=300)
    assert again.returncode == 0 and len(study_trials(workspace)) == 3, again.stderr[-2000:]
    assert "Running stage" not in again.stdout and set(experiments(workspace)) == set(shown)
    assert (workspace / "reports/sweep/best_params.txt").read_text() == best_params


@pytest.mark.slow
def test_the_confirmation_step_runs_end_to_end_on_tiny_params_with_2_seeds(killed_sweep):
    # The same sweep seen from its statistics: trials chose on the validation seeds alone; the confirmation trained
    # the winner's and the default settings on 2 training seeds each and tested both on exactly the test seeds.
    workspace = killed_sweep["workspace"]
    shown = experiments(workspace)
    table = pd.read_csv(workspace / "reports/sweep/trials.csv")
    completed = table[table["state"] == "COMPLETE"]
    assert len(completed) == 2
    for row in completed.itertuples():
        rev = shown[row.dvc_experiment]["rev"]
        assert shown[row.dvc_experiment]["params"]["eval"]["run_test"] is False
        evaluation = "reports/eval/lift/carp/seed0"
        summary = json.loads(committed_file(workspace, rev, f"{evaluation}.json"))
        assert summary["test_episodes"] == 0 and "success_rate" not in summary
        assert pd.read_csv(io.StringIO(committed_file(workspace, rev, f"{evaluation}_episodes.csv"))).empty
        validation = pd.read_csv(io.StringIO(committed_file(workspace, rev, f"{evaluation}_validation.csv")))
        assert sorted(set(validation["seed"])) == list(VALIDATION_SEEDS)
        assert not set(validation["seed"]) & set(TEST_SEEDS)

    best_row = completed.sort_values(
        ["validation_score", "validation_success_rate", "latency_ms", "trial"], ascending=[False, False, True, True]
    ).iloc[0]
    selected = TrialSettings(tuple(json.loads(best_row.scales)), int(best_row.codebook_size))
    seeds = SWEEP["confirm_seeds"]
    test_rates = {}
    for arm, settings in (("selected", selected), ("default", DEFAULT_SETTINGS)):
        directory = workspace / "reports/sweep/confirmation" / arm_key(settings, seeds)
        name = json.loads((directory / "arm.json").read_text())["experiment"]
        params = shown[name]["params"]
        assert (params["scales"], params["codebook_size"]) == (list(settings.scales), settings.codebook_size)
        assert params["seeds"] == seeds and params["eval"]["run_test"] is True
        episodes = [pd.read_csv(directory / "lift" / f"seed{seed}_episodes.csv") for seed in seeds]
        for table_of_seed in episodes:
            assert table_of_seed["seed"].tolist() == list(TEST_SEEDS)
        successes = sum(int(table_of_seed["success"].astype(bool).sum()) for table_of_seed in episodes)
        test_rates[arm] = successes / (len(seeds) * len(TEST_SEEDS))
    assert sorted(path.name for path in (workspace / "reports/sweep/confirmation").iterdir()) == sorted(
        arm_key(settings, seeds) for settings in (selected, DEFAULT_SETTINGS)
    )

    lines = comment_lines((workspace / "reports/sweep/best_params.txt").read_text())
    assert lines[0] == (
        f"trial {best_row.trial} ({best_row.dvc_experiment}), selected on the validation seeds: validation score "
        f"{best_row.validation_score:.3f}, validation success {100 * best_row.validation_success_rate:.1f}%"
    )
    assert lines[1].startswith("confirmation (") and f"training seeds {seeds}) against the default settings" in lines[1]
    figures = (
        f"lift: validation success {100 * best_row.validation_success_rate:.1f}% | test success "
        f"{100 * test_rates['selected']:.1f}% selected, {100 * test_rates['default']:.1f}% default: "
    )
    (parent,) = [
        r
        for r in mlflow_runs(workspace)
        if r.data.tags.get("carp.sweep_study") == "tiny" and "mlflow.parentRunId" not in r.data.tags
    ]
    verdict = parent.data.tags["carp.confirmation_verdict.lift"]
    assert len(lines) == 3 and lines[2].startswith(f"{figures}{verdict}. "), (lines, verdict)
    # Two training seeds per arm meet comparison.min_seeds: a verdict, not "not decided (2 training seeds)".
    assert verdict in ("selected better", "default better", "not decided") or verdict.startswith("on par"), verdict
    assert parent.data.tags["carp.confirmation"] == "\n".join(lines)
    assert parent.data.metrics["confirmed_test_success_rate"] == pytest.approx(test_rates["selected"])
    assert parent.data.metrics["default_test_success_rate"] == pytest.approx(test_rates["default"])
    assert parent.data.metrics["best_validation_success_rate"] == pytest.approx(best_row.validation_success_rate)


def _second_trial_is_training(log: str) -> bool:
    marker = "dvc exp run --name sweep-tiny-t1"
    return marker in log and "Running stage 'train_policy@lift-carp-0'" in log.split(marker, 1)[1]


def _wait_until_group_is_gone(group: int) -> None:
    deadline = time.monotonic() + 60
    while True:
        try:
            os.killpg(group, 0)
        except ProcessLookupError:
            return
        assert time.monotonic() < deadline, f"process group {group} survived SIGKILL"
        time.sleep(0.2)
