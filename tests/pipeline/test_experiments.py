"""End to end on tiny params: `dvc exp run -S` (workspace and --temp) and the Optuna sweep, killed and resumed.

The workspace template (repository copy with collected and ingested demos) is built once per module; every test
works in its own copy, so experiments, MLflow and Optuna stores never mix between tests. The killed and resumed
sweep runs once per module and serves two tests: how it resumes, and its trials and confirmation seen end to end.
"""

import fcntl
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pandas as pd
import pytest
import yaml
from mlflow import MlflowClient
from optuna.trial import TrialState

from carp.sweep.confirmation import arm_key
from carp.sweep.dvc_runner import DvcExperimentRunner
from carp.sweep.space import TrialSettings
from carp.sweep.study import ExperimentStoppedError
from tests.pipeline.workspace import (
    TINY_PARAMS,
    dvc,
    make_workspace,
    queue_status,
    run,
    run_queued_experiments,
    tool_env,
)
from tests.services import service_directory, tool, tracking_server

SWEEP = {
    "study_name": "tiny",
    "num_trials": 2,
    "scale_schedules": [[1, 4], [1, 2, 4]],
    # The workspace's own codebook_size (TINY_PARAMS) is off the grid, so the confirmation always has two arms.
    "codebook_sizes": [8, 32],
    "heartbeat_seconds": 1,
    # Candidates still report their validation through the progress file; no trial is stopped by chance.
    "pruner": "none",
    "validation_episodes": 2,
    # Two training seeds per arm, none of the trials' (seeds: [0]); comparison.min_seeds allows two (copy_workspace).
    "confirm_seeds": [1, 2],
}
DEFAULT_SETTINGS = TrialSettings(tuple(TINY_PARAMS["scales"]), TINY_PARAMS["codebook_size"])
TEST_SEEDS = range(100_000, 100_000 + TINY_PARAMS["eval"]["episodes"])  # eval.seed on, eval.episodes of them
VALIDATION_SEEDS = range(200_000, 200_000 + SWEEP["validation_episodes"])  # eval.validation_seed on
# Generous bounds for a loaded two-core machine; the waits end as soon as their condition holds.
TRIAL_TIMEOUT_SECONDS = 900


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    workspace = make_workspace(tmp_path_factory.mktemp("template") / "carp")
    for command in (dvc("repro", "ingest"), ["git", "add", "-A"], ["git", "commit", "-qm", "tiny demos"]):
        completed = run(command, workspace)
        assert completed.returncode == 0, completed.stderr[-3000:]
    return workspace


def copy_workspace(template: Path, directory: Path, sweep: dict | None = None, tracking: dict | None = None) -> Path:
    workspace = directory / "carp"
    # The template's MLflow store records absolute artifact locations inside the template: start a fresh one.
    shutil.copytree(template, workspace, symlinks=True, ignore=shutil.ignore_patterns("mlflow.db", "mlartifacts"))
    if sweep is not None:
        params = yaml.safe_load((workspace / "params.yaml").read_text())
        params["sweep"].update(sweep)
        params["comparison"]["min_seeds"] = len(params["sweep"]["confirm_seeds"])
        params["tracking"].update(tracking or {})
        (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        for command in (["git", "add", "params.yaml"], ["git", "commit", "-qm", "sweep settings"]):
            assert run(command, workspace).returncode == 0
    return workspace


def head(workspace: Path) -> str:
    return run(["git", "rev-parse", "HEAD"], workspace).stdout.strip()


def experiments(workspace: Path) -> dict[str, dict]:
    """`dvc exp show --json` as experiment name -> {rev, params, metrics} of params.yaml and the metrics files."""
    shown = run(dvc("exp", "show", "--json"), workspace)
    assert shown.returncode == 0, shown.stderr
    found = {}
    for baseline in json.loads(shown.stdout):
        for experiment in baseline.get("experiments") or []:
            data = experiment["revs"][0]["data"]
            metrics = {}
            for values in data["metrics"].values():
                metrics.update(values["data"])
            found[experiment["name"]] = {
                "rev": experiment["revs"][0]["rev"],
                "params": data["params"]["params.yaml"]["data"],
                "metrics": metrics,
            }
    return found


def mlflow_runs(workspace: Path) -> list:
    client = MlflowClient(tracking_uri=f"sqlite:///{workspace / 'mlflow.db'}")
    return client.search_runs([experiment.experiment_id for experiment in client.search_experiments()])


def study_trials(workspace: Path) -> list:
    return optuna.load_study(study_name="tiny", storage=f"sqlite:///{workspace / 'optuna.db'}").get_trials()


def sweep_command() -> list[str]:
    return [sys.executable, "pipeline/sweep.py"]


def committed_file(workspace: Path, rev: str, path: str) -> str:
    """A file as an experiment's commit holds it (its uncached outputs, metrics and plots)."""
    shown = run(["git", "show", f"{rev}:{path}"], workspace)
    assert shown.returncode == 0, shown.stderr
    return shown.stdout


def comment_lines(best_params: str) -> list[str]:
    """The ``#`` lines of best_params.txt without their ``# ``."""
    return [line.removeprefix("# ") for line in best_params.splitlines()[1:]]


@pytest.mark.slow
def test_invalid_set_values_are_refused_with_one_line(template, tmp_path):
    workspace = copy_workspace(template, tmp_path)
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
def test_two_queued_experiments_run_at_once_on_a_fresh_store_keep_every_run(template, tmp_path):
    # No mlflow.db yet: both workers' first stages open a store that does not exist (the schema-creation race).
    # Queued experiments run in temporary copies under .dvc/tmp, as `--temp` ones do: their runs must still land in
    # the workspace's store, under their experiment's name, and leave the workspace's params alone.
    workspace = copy_workspace(template, tmp_path)
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


@pytest.fixture(scope="module")
def killed_sweep(template, tmp_path_factory) -> dict:
    """A sweep killed during its second trial's training, then resumed to its end (confirmation included).

    Returns the workspace, the trials completed before the kill and the resumed sweep's completed process.
    """
    directory = tmp_path_factory.mktemp("killed-sweep")
    workspace = copy_workspace(template, directory, {**SWEEP, "prune_factor": 1000.0})
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


@pytest.mark.slow
def test_a_pruned_trial_stops_its_dvc_experiment_and_the_next_trial_runs(template, tmp_path):
    # The progress file and its stop file through a real `dvc exp run`: the evaluate stage reports each candidate (a
    # snapshot at epoch 1, the final policy at 2), stops when asked, and the failed experiment leaves the workspace
    # fit for the next trial.
    workspace = copy_workspace(template, tmp_path, SWEEP)
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


@pytest.mark.slow
def test_two_sweep_workers_share_a_postgresql_study_and_push_their_experiments(template, tmp_path, monkeypatch):
    # Two workspaces (clones of one commit) run `pipeline/sweep.py` at once on a two-point grid, sharing the study in
    # the tracking server's PostgreSQL, logging to its MLflow server and pushing their experiments to one git remote.
    with service_directory("carp-sweep-workers-") as services, tracking_server(services / "tracking") as url:
        printed = tool("tracking_server.py", "sweep-storage", "--dir", str(services / "tracking"), timeout=60)
        assert printed.returncode == 0, printed.stdout + printed.stderr
        storage = printed.stdout.strip()
        environment = {**tool_env(), "PGPASSFILE": str(services / "tracking" / "pgpass")}
        sweep = {**SWEEP, "codebook_sizes": [8], "prune_factor": 1000.0, "storage": storage, "git_remote": "origin"}
        first = copy_workspace(template, tmp_path / "first", sweep, tracking={"uri": url})
        remote = tmp_path / "remote.git"
        for command, directory in (
            (["git", "init", "-q", "--bare", str(remote)], tmp_path),
            (["git", "remote", "add", "origin", str(remote)], first),
            (["git", "push", "-q", "origin", "HEAD"], first),
        ):
            assert run(command, directory).returncode == 0
        second = tmp_path / "second" / "carp"
        shutil.copytree(first, second, symlinks=True)

        workers = []
        for workspace in (first, second):
            log = (workspace.parent / "sweep.log").open("w")
            workers.append(
                subprocess.Popen(sweep_command(), cwd=workspace, env=environment, stdout=log, stderr=subprocess.STDOUT)
            )
        for worker, workspace in zip(workers, (first, second)):
            assert worker.wait(timeout=2 * TRIAL_TIMEOUT_SECONDS) == 0, (workspace.parent / "sweep.log").read_text()[
                -3000:
            ]

        monkeypatch.setenv("PGPASSFILE", environment["PGPASSFILE"])
        trials = optuna.load_study(study_name="tiny", storage=storage).get_trials()
        assert [t.state for t in trials] == [TrialState.COMPLETE] * 2
        assert sorted(t.params["scales"] for t in trials) == ["[1,2,4]", "[1,4]"]  # each point once
        for workspace in (first, second):
            table = pd.read_csv(workspace / "reports/sweep/trials.csv")
            assert table["state"].tolist() == ["COMPLETE", "COMPLETE"]
        # Each trial's experiment exists in the workspace that ran it; one worker ran the confirmation's two
        # experiments, and the other says where. All of them reach any clone through the git remote.
        ran_here = [set(experiments(workspace)) for workspace in (first, second)]
        names = {f"sweep-tiny-t{t.number}" for t in trials}
        confirming = [index for index, ran in enumerate(ran_here) if ran - names]
        assert len(confirming) == 1, ran_here
        confirmations = ran_here[confirming[0]] - names
        assert len(confirmations) == 2 and all(name.startswith("sweep-tiny-confirm-") for name in confirmations)
        assert ran_here[0] | ran_here[1] == names | confirmations and not ran_here[0] & ran_here[1]
        confirmed, waited = (first, second) if confirming == [0] else (second, first)
        assert "against the default settings" in (confirmed / "reports/sweep/best_params.txt").read_text()
        assert (
            f"# not confirmed here: the confirmation runs in the workspace {socket.gethostname()}:{confirmed.resolve()}"
            in (waited / "reports/sweep/best_params.txt").read_text()
        )
        clone = tmp_path / "clone"
        assert run(["git", "clone", "-q", str(remote), str(clone)], tmp_path).returncode == 0
        pulled = run(dvc("exp", "pull", "origin", *sorted(names | confirmations)), clone)
        assert pulled.returncode == 0, pulled.stderr
        shown = experiments(clone)
        for trial in trials:
            experiment = shown[f"sweep-tiny-t{trial.number}"]
            assert experiment["params"]["scales"] == json.loads(trial.params["scales"])
            assert experiment["metrics"]["validation_success_rate"] == pytest.approx(
                trial.user_attrs["validation_success_rate"]
            )
        for name in confirmations:
            assert shown[name]["params"]["seeds"] == SWEEP["confirm_seeds"]

        client = MlflowClient(tracking_uri=url)
        runs = client.search_runs([experiment.experiment_id for experiment in client.search_experiments()])
        study_runs = [r for r in runs if r.data.tags.get("carp.sweep_study") == "tiny"]
        parents = [r for r in study_runs if "mlflow.parentRunId" not in r.data.tags]
        assert len(parents) == 1 and parents[0].info.status == "FINISHED"
        assert "carp.confirmation_verdict.lift" in parents[0].data.tags
        children = [r for r in study_runs if r.data.tags.get("mlflow.parentRunId") == parents[0].info.run_id]
        assert sorted(r.data.tags["carp.dvc_experiment"] for r in children) == sorted(names)
        for name in names:
            stages = {
                r.data.tags["carp.dvc_stage"]
                for r in runs
                if r.data.tags.get("carp.dvc_experiment") == name and "carp.dvc_stage" in r.data.tags
            }
            assert stages == {
                "train_tokenizer",
                "register_tokenizer",
                "train_policy@lift-carp-0",
                "evaluate@lift-carp-0",
            }


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
