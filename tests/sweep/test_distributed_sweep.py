"""Several sweep workers on one study in a real PostgreSQL database, with a real MLflow server, on loopback.

The workers are separate processes (``tests/sweep/stub_worker.py``) running the library's sweep with a stub pipeline
that sleeps, so their trials overlap; each logs when it starts and ends a point. The tracking server (PostgreSQL with
the ``optuna`` database, and MLflow) is started once for the module; every test uses its own study.
"""

import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import optuna
import pandas as pd
import pytest
from mlflow import MlflowClient
from optuna.trial import TrialState

from carp.sweep.claims import ClaimStore
from carp.sweep.study import finished_trial_count
from tests.services import REPO, service_directory, tool, tracking_server

pytestmark = pytest.mark.slow

GRID_POINTS = 6  # the stub worker's default grid: 3 schedules x 2 codebook sizes
WORKER_SECONDS = 300


@pytest.fixture(scope="module")
def services():
    """(MLflow URL, the optuna database's URL, the pgpass file) of a tracking server for the module."""
    with service_directory("carp-sweep-") as directory, tracking_server(directory / "tracking") as url:
        storage = tool("tracking_server.py", "sweep-storage", "--dir", str(directory / "tracking"), timeout=60)
        assert storage.returncode == 0, storage.stdout + storage.stderr
        yield url, storage.stdout.strip(), directory / "tracking" / "pgpass"


@pytest.fixture(autouse=True)
def database_password(services, monkeypatch):
    """libpq (under Optuna and the claims) reads the database's password from the file PGPASSFILE names."""
    monkeypatch.setenv("PGPASSFILE", str(services[2]))


def start_worker(services, study: str, trials: int, log: Path, reports: Path, seconds: float) -> subprocess.Popen:
    url, storage, pgpass = services
    command = [
        sys.executable, "-m", "tests.sweep.stub_worker",
        "--storage", storage,
        "--study", study,
        "--trials", str(trials),
        "--reports", str(reports),
        "--log", str(log),
        "--seconds", str(seconds),
        "--tracking-uri", url,
    ]  # fmt: skip
    output = reports.with_suffix(".out").open("w")
    return subprocess.Popen(
        command,
        cwd=REPO,
        env={**os.environ, "PGPASSFILE": str(pgpass)},
        stdout=output,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def finish(worker: subprocess.Popen, reports: Path) -> None:
    assert worker.wait(timeout=WORKER_SECONDS) == 0, reports.with_suffix(".out").read_text()[-3000:]


def events(log: Path) -> list[tuple[str, str, int]]:
    """(event, point, pid) of every line the workers logged."""
    found = []
    for line in log.read_text().splitlines():
        event, scales, size, pid = line.split()
        found.append((event, f"{scales} {size}", int(pid)))
    return found


def load_trials(services, study: str) -> list:
    return optuna.load_study(study_name=study, storage=services[1]).get_trials()


def sweep_runs(services, study: str) -> list:
    client = MlflowClient(tracking_uri=services[0])
    experiment = client.get_experiment_by_name("carp-sweep")
    runs = client.search_runs([experiment.experiment_id])
    return [run for run in runs if run.data.tags.get("carp.sweep_study") == study]


def test_three_workers_run_every_grid_point_once(services, tmp_path):
    log = tmp_path / "events.log"
    workers = [
        (
            start_worker(services, "whole-grid", 50, log, tmp_path / f"reports-{index}", 1.0),
            tmp_path / f"reports-{index}",
        )
        for index in range(3)
    ]
    for worker, reports in workers:
        finish(worker, reports)

    ran = events(log)
    starts = Counter(point for event, point, _ in ran if event == "start")
    assert len(starts) == GRID_POINTS and set(starts.values()) == {1}, starts
    assert len({pid for _, _, pid in ran}) >= 2  # the points were shared out, not run by one worker
    trials = load_trials(services, "whole-grid")
    assert [t.state for t in trials] == [TrialState.COMPLETE] * GRID_POINTS
    assert len({(t.params["scales"], t.params["codebook_size"]) for t in trials}) == GRID_POINTS
    for _, reports in workers:  # every worker waited for the others and reports the whole study
        table = pd.read_csv(reports / "trials.csv")
        assert table["state"].tolist() == ["COMPLETE"] * GRID_POINTS

    runs = sweep_runs(services, "whole-grid")
    parents = [run for run in runs if "mlflow.parentRunId" not in run.data.tags]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    assert parents[0].data.tags["carp.finished_trials"] == str(GRID_POINTS)
    children = [run for run in runs if run.data.tags.get("mlflow.parentRunId") == parents[0].info.run_id]
    assert sorted(int(run.data.tags["carp.trial_number"]) for run in children) == list(range(GRID_POINTS))
    assert {run.info.status for run in children} == {"FINISHED"}


def test_budget_holds_across_workers(services, tmp_path):
    log = tmp_path / "events.log"
    budget = 4
    workers = [
        (
            start_worker(services, "budget", budget, log, tmp_path / f"reports-{index}", 0.5),
            tmp_path / f"reports-{index}",
        )
        for index in range(3)
    ]
    for worker, reports in workers:
        finish(worker, reports)
    starts = Counter(point for event, point, _ in events(log) if event == "start")
    assert len(starts) == budget and set(starts.values()) == {1}
    trials = load_trials(services, "budget")
    assert len(trials) == budget and finished_trial_count(trials) == budget

    # A worker started later with the same budget finds it spent and runs nothing.
    late = start_worker(services, "budget", budget, log, tmp_path / "reports-late", 0.0)
    finish(late, tmp_path / "reports-late")
    assert len(load_trials(services, "budget")) == budget


def test_trial_of_a_killed_worker_is_retried_by_another(services, tmp_path):
    log = tmp_path / "events.log"
    doomed = start_worker(services, "killed", 50, log, tmp_path / "reports-doomed", WORKER_SECONDS)
    try:
        deadline = time.monotonic() + 120
        while not (log.exists() and log.read_text()):
            assert doomed.poll() is None, (tmp_path / "reports-doomed.out").read_text()[-3000:]
            assert time.monotonic() < deadline, "the first worker never started a trial"
            time.sleep(0.2)
        survivor = start_worker(services, "killed", 50, log, tmp_path / "reports-survivor", 0.2)
        # The survivor starts and claims other points while the doomed worker is mid-trial.
        while len(events(log)) < 2:
            assert survivor.poll() is None, (tmp_path / "reports-survivor.out").read_text()[-3000:]
            time.sleep(0.2)
    finally:
        os.killpg(doomed.pid, signal.SIGKILL)
        doomed.wait(timeout=60)
    finish(survivor, tmp_path / "reports-survivor")

    ran = events(log)
    (killed_point,) = [point for event, point, pid in ran if pid == doomed.pid]
    ends = Counter(point for event, point, _ in ran if event == "end")
    assert len(ends) == GRID_POINTS and set(ends.values()) == {1}  # every point completed once, the killed one too
    assert [(event, pid) for event, point, pid in ran if point == killed_point] == [
        ("start", doomed.pid),
        ("start", survivor.pid),
        ("end", survivor.pid),
    ]

    trials = load_trials(services, "killed")
    failed = [t for t in trials if t.state == TrialState.FAIL]
    assert len(failed) == 1 and len(trials) == GRID_POINTS + 1
    retry = next(t for t in trials if t.system_attrs.get("failed_trial") == failed[0].number)
    assert retry.state == TrialState.COMPLETE and retry.params == failed[0].params
    assert finished_trial_count(trials) == GRID_POINTS
    runs = {
        int(run.data.tags["carp.trial_number"]): run
        for run in sweep_runs(services, "killed")
        if run.data.tags.get("carp.trial_number")
    }
    assert runs[failed[0].number].info.status == "FAILED"  # closed by the survivor
    assert runs[retry.number].info.status == "FINISHED"


def test_threads_racing_on_postgresql_claim_each_point_once(services):
    points = [f"point-{index}" for index in range(20)]
    workers = [ClaimStore(services[1], study_id=10_000) for _ in range(8)]
    won: list[str] = []
    lock = threading.Lock()
    start = threading.Barrier(len(workers))

    def work(store: ClaimStore) -> None:
        start.wait()
        while (point := store.claim(points, num_slots=15, stale_seconds=60)) is not None:
            with lock:
                won.append(point)

    threads = [threading.Thread(target=work, args=(store,)) for store in workers]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for store in workers:
        store.close()
    assert len(won) == 15 and len(set(won)) == 15
