"""End to end on tiny params: two sweep workers in two clones share one study in the tracking server's PostgreSQL,
log to its MLflow server and push their experiments to one git remote.

The workers start from a copy of the shared demos workspace (``lift_demos``).
"""

import json
import shutil
import socket
import subprocess

import optuna
import pandas as pd
import pytest
from mlflow import MlflowClient
from optuna.trial import TrialState

from tests.pipeline.experiments_support import (
    SWEEP,
    TRIAL_TIMEOUT_SECONDS,
    copy_workspace,
    experiments,
    sweep_command,
)
from tests.pipeline.workspace import dvc, run, tool_env
from tests.services import service_directory, tool, tracking_server


@pytest.mark.slow
def test_two_sweep_workers_share_a_postgresql_study_and_push_their_experiments(lift_demos, tmp_path, monkeypatch):
    # Two workspaces (clones of one commit) run `pipeline/sweep.py` at once on a two-point grid, sharing the study in
    # the tracking server's PostgreSQL, logging to its MLflow server and pushing their experiments to one git remote.
    with service_directory("carp-sweep-workers-") as services, tracking_server(services / "tracking") as url:
        printed = tool("tracking_server.py", "sweep-storage", "--dir", str(services / "tracking"), timeout=60)
        assert printed.returncode == 0, printed.stdout + printed.stderr
        storage = printed.stdout.strip()
        environment = {**tool_env(), "PGPASSFILE": str(services / "tracking" / "pgpass")}
        sweep = {**SWEEP, "codebook_sizes": [8], "prune_factor": 1000.0, "storage": storage, "git_remote": "origin"}
        first = copy_workspace(lift_demos, tmp_path / "first", sweep, tracking={"uri": url})
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
