"""End to end on tiny params: `dvc exp run -S` (refused values, queued experiments), a pruned trial's experiment, and
the sweep's refusals.

Every test works in its own copy of the shared demos workspace (``lift_demos``: a repository copy with collected and
ingested demos, built once per test run), so experiments, MLflow and Optuna stores never mix between tests. The
sweep killed and resumed is in test_sweep_resume.py, the two sweep workers in test_sweep_workers.py.
"""

import fcntl
import json

import pytest
import yaml

from carp.sweep.dvc_runner import DvcExperimentRunner
from carp.sweep.space import TrialSettings
from carp.sweep.study import ExperimentStoppedError
from tests.pipeline.experiments_support import (
    SWEEP,
    TRIAL_TIMEOUT_SECONDS,
    copy_workspace,
    experiments,
    head,
    mlflow_runs,
    sweep_command,
)
from tests.pipeline.workspace import dvc, make_workspace, queue_status, run, run_queued_experiments, tool_env


@pytest.mark.slow
def test_invalid_set_values_are_refused_with_one_line(lift_demos, tmp_path):
    workspace = copy_workspace(lift_demos, tmp_path)
    for value, message in (
        ("codebook_size=1", "codebook_size=1: must be >= 2"),
        ("scales=[1,3,2]", "scales=[1, 3, 2]: every schedule must be positive, strictly increasing and end at most"),
    ):
        refused = run(dvc("exp", "run", "-S", value), workspace)
        assert refused.returncode != 0
        errors = [line for line in (refused.stdout + refused.stderr).splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and message in errors[0], refused.stdout[-2000:] + refused.stderr[-2000:]
        assert run(["git", "checkout", "--", "params.yaml"], workspace).returncode == 0
    assert experiments(workspace) == {}


@pytest.mark.slow
def test_two_queued_experiments_run_at_once_on_a_fresh_store_keep_every_run(lift_demos, tmp_path):
    # No mlflow.db yet: both workers' first stages open a store that does not exist (the schema-creation race).
    # Queued experiments run in temporary copies under .dvc/tmp, as `--temp` ones do: their runs must still land in
    # the workspace's store, under their experiment's name, and leave the workspace's params alone.
    workspace = copy_workspace(lift_demos, tmp_path)
    assert not (workspace / "mlflow.db").exists()
    params_before = (workspace / "params.yaml").read_text()
    settings = {"tiny-a": ("[2,4]", 8), "tiny-b": ("[1,2,4]", 16)}
    for name, (scales, size) in settings.items():
        command = dvc("exp", "run", "--queue", "-n", name, "-S", f"scales={scales}", "-S", f"codebook_size={size}")
        queued = run(command, workspace)
        assert queued.returncode == 0, queued.stderr[-3000:]
    run_queued_experiments(workspace, jobs=2, timeout=2 * TRIAL_TIMEOUT_SECONDS)
    assert queue_status(workspace)[0] == {"Success": 2}, run(dvc("queue", "status"), workspace).stdout
    assert (workspace / "params.yaml").read_text() == params_before

    shown = experiments(workspace)
    assert set(shown) == set(settings), run(dvc("queue", "status"), workspace).stdout
    stages = {"train_tokenizer", "register_tokenizer", "train_policy@lift-carp-0", "evaluate@lift-carp-0"}
    for name, (scales, size) in settings.items():
        assert shown[name]["params"]["scales"] == json.loads(scales) and shown[name]["params"]["codebook_size"] == size
        for metric in (
            "success_rate",
            "rmse_percent_range/mean",
            "latency_predict_ms_median",
            "latency_decode_ms_median",
        ):
            assert isinstance(shown[name]["metrics"][metric], float), (name, metric)
        tagged = [r for r in mlflow_runs(workspace) if r.data.tags.get("carp.dvc_experiment") == name]
        assert sorted(r.data.tags["carp.dvc_stage"] for r in tagged) == sorted(stages), name
        assert {r.info.status for r in tagged} == {"FINISHED"}, name
        assert {r.data.params["codebook_size"] for r in tagged} == {str(size)}, name
        assert {r.data.tags["carp.git_commit"] for r in tagged} == {head(workspace)}, name
        for r in tagged:
            assert r.info.artifact_uri.startswith((workspace / "mlartifacts").as_uri()), name
    assert not list((workspace / ".dvc" / "tmp").rglob("mlflow.db"))


@pytest.mark.slow
def test_a_pruned_trial_stops_its_dvc_experiment_and_the_next_trial_runs(lift_demos, tmp_path):
    # The progress file and its stop file through a real `dvc exp run`: the evaluate stage reports each candidate (a
    # snapshot at epoch 1, the final policy at 2), stops when asked, and the failed experiment leaves the workspace
    # fit for the next trial.
    workspace = copy_workspace(lift_demos, tmp_path, SWEEP)
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    params["training"]["snapshot_every"] = 1
    (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    assert run(["git", "commit", "-qam", "snapshots"], workspace).returncode == 0
    runner = DvcExperimentRunner(
        workspace,
        workspace / "reports/tokenizer/metrics.json",
        lambda task, policy, seed: workspace / "reports/eval" / task / policy / f"seed{seed}.json",
        ["lift"],
        ["carp"],
        [0],
        "",
        tool_env(),
        SWEEP["validation_episodes"],
    )
    settings = TrialSettings((1, 4), 8)
    stopped, completed = [], []
    runner.train_tokenizer("sweep-tiny-t0", settings)
    with pytest.raises(ExperimentStoppedError):
        runner.run_experiment("sweep-tiny-t0", settings, lambda candidate: stopped.append(candidate) or True)
    # The stop takes effect after the candidate being validated when the stage sees it: the first or the second.
    assert [candidate.epoch for candidate in stopped][:1] == [1] and len(stopped) <= 2
    assert "sweep-tiny-t0" not in experiments(workspace)

    runner.train_tokenizer("sweep-tiny-t1", settings)
    result = runner.run_experiment("sweep-tiny-t1", settings, lambda candidate: completed.append(candidate) or False)
    assert [(candidate.evaluation, candidate.epoch) for candidate in completed] == [
        ("lift/carp/seed0", 1),
        ("lift/carp/seed0", 2),
    ]
    assert result.validation_success_rate == pytest.approx(max(candidate.success_rate for candidate in completed))
    assert set(experiments(workspace)) == {"sweep-tiny-t1"}


@pytest.mark.slow
def test_a_second_sweep_in_the_same_workspace_is_refused(tmp_path):
    workspace = make_workspace(tmp_path / "carp")
    lock_path = workspace / ".dvc" / "tmp" / "sweep.lock"
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with lock_path.open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as a running sweep holds it
        refused = run(sweep_command(), workspace, timeout=300)
    assert refused.returncode == 1 and refused.stdout == ""
    assert refused.stderr.strip() == (
        f"error: {lock_path}: another sweep is running in this workspace; start each sweep worker in its own clone"
    )
    assert not (workspace / "optuna.db").exists() and not (workspace / "reports" / "sweep").exists()


@pytest.mark.slow
def test_a_confirmation_that_would_reuse_a_trial_seed_is_refused(tmp_path):
    workspace = make_workspace(tmp_path / "carp", {"seeds": [0, 1], "sweep": {"confirm_seeds": [1, 2, 3]}})
    refused = run(sweep_command(), workspace, timeout=300)
    assert refused.returncode == 1 and refused.stdout == ""
    assert refused.stderr.strip() == (
        f"error: {workspace.resolve() / 'params.yaml'}: sweep.confirm_seeds=[1, 2, 3]: must not include the trials' "
        "training seeds seeds=[0, 1] (both hold [1])"
    )
    assert not (workspace / "optuna.db").exists() and not (workspace / "reports" / "sweep").exists()
