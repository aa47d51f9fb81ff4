"""Stage runs under concurrency and after a hard kill: one store schema, no run left RUNNING by a dead process."""

import multiprocessing
import os
import signal
import socket
import subprocess
import sys

import pytest
from mlflow import MlflowClient

from carp.tracking.runs import HOST_TAG, PID_TAG, ensure_experiment, find_runs, stage_run

WRITERS = 4


def _create_experiment(uri: str, barrier, results) -> None:
    barrier.wait()
    try:
        results.put(ensure_experiment(uri, "carp-lift"))
    except Exception as error:  # reported to the test, which names it
        results.put(f"{type(error).__name__}: {error}")


@pytest.mark.slow
def test_processes_opening_a_new_store_at_once_all_get_the_same_experiment(tmp_path):
    # Without the lock, simultaneous first opens race in MLflow's schema migration or in the experiment's creation.
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(WRITERS), context.Queue()
    workers = [context.Process(target=_create_experiment, args=(uri, barrier, results)) for _ in range(WRITERS)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(timeout=120)
    ids = {results.get(timeout=5) for _ in workers}
    assert len(ids) == 1 and next(iter(ids)).isdigit(), ids
    assert (tmp_path / "mlflow.db.lock").exists()


KILLED_STAGE = """
import os, signal, sys
from carp.tracking.runs import stage_run
with stage_run(sys.argv[1], "carp-lift", "train_policy@lift", {"a": "1"}, {}):
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_run_of_a_killed_stage_is_marked_killed_when_the_stage_runs_again(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    killed = subprocess.run([sys.executable, "-c", KILLED_STAGE, uri], capture_output=True, text=True, timeout=120)
    assert killed.returncode == -signal.SIGKILL
    [orphan] = find_runs(uri, "carp-lift")
    assert orphan["status"] == "RUNNING" and orphan["tags"][HOST_TAG] == socket.gethostname()

    # A RUNNING run of the same stage in a live process (a parallel experiment) must be left alone.
    client = MlflowClient(tracking_uri=uri)
    live = client.create_run(
        orphan_experiment_id(uri),
        run_name="train_policy@lift",
        tags={HOST_TAG: socket.gethostname(), PID_TAG: str(os.getpid())},
    )
    with stage_run(uri, "carp-lift", "train_policy@lift", {"a": "1"}, {}):
        pass

    statuses = {run["run_id"]: run["status"] for run in find_runs(uri, "carp-lift")}
    assert statuses[orphan["run_id"]] == "KILLED"
    assert statuses[live.info.run_id] == "RUNNING"
    assert sorted(statuses.values()) == ["FINISHED", "KILLED", "RUNNING"]
    reason = client.get_run(orphan["run_id"]).data.tags["carp.end_reason"]
    assert orphan["tags"][PID_TAG] in reason


def orphan_experiment_id(uri: str) -> str:
    return MlflowClient(tracking_uri=uri).get_experiment_by_name("carp-lift").experiment_id


def test_experiment_created_by_another_client_after_our_lookup_is_used(tmp_path, monkeypatch):
    # A tracking server takes no creation lock: two stages starting at once on a fresh server both find no
    # experiment, both create it, and the server refuses the second. The lookup here answers as it did for the loser.
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    theirs = MlflowClient(tracking_uri=uri).create_experiment("carp-lift")
    lookups = []
    original = MlflowClient.get_experiment_by_name

    def first_lookup_misses(self, name):
        lookups.append(name)
        return None if len(lookups) == 1 else original(self, name)

    monkeypatch.setattr(MlflowClient, "get_experiment_by_name", first_lookup_misses)
    assert ensure_experiment(uri, "carp-lift") == theirs
    assert len(lookups) == 2
