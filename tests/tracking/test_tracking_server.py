"""`tools/tracking_server.py`: an MLflow server on PostgreSQL with served artifacts, real and on loopback.

Stage runs from several processes at once (and, for comparison, into a SQLite file), the tokenizer registry and a
restart work against it; what it refuses
(a taken port, missing PostgreSQL programs, a directory the database account cannot enter) is one `error:` line,
before anything is created.
"""

import json
import multiprocessing
import os
import socket
import subprocess

import pytest
from mlflow import MlflowClient

from carp.tracking.registry import SHA_TAG, fetch_registered_tokenizer, point_alias, register_tokenizer
from carp.tracking.runs import find_runs, stage_run
from tests.services import service_directory, tool, tracking_server
from tests.tracking.test_registry import make_artifact, register


@pytest.fixture(scope="module")
def server():
    with service_directory("carp-tracking-") as directory, tracking_server(directory) as url:
        yield directory, url


def _write_runs(uri: str, writer: int, runs: int, barrier, results) -> None:
    barrier.wait()
    run_ids = []
    try:
        for index in range(runs):
            params = {"writer": str(writer), "index": str(index), "value": f"{writer}:{index}"}
            with stage_run(uri, "carp-writers", f"writer-{writer}", params, {"carp.dvc_stage": "bench"}) as run:
                for step in range(3):
                    run.log_metrics({"value": 100 * writer + index, "step": step}, step=step)
            run_ids.append(run.run_id)
        results.put((writer, run_ids))
    except Exception as error:  # reported to the test, which names it
        results.put((writer, f"{type(error).__name__}: {error}"))


def check_runs_logged_at_once(uri: str, writers: int, runs_per_writer: int) -> None:
    """``writers`` processes log runs into one new experiment at once; every run is kept with its own values."""
    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(writers), context.Queue()
    processes = [
        context.Process(target=_write_runs, args=(uri, writer, runs_per_writer, barrier, results))
        for writer in range(writers)
    ]
    for process in processes:
        process.start()
    reported = dict(results.get(timeout=600) for _ in processes)
    for process in processes:
        process.join(timeout=60)
    assert all(isinstance(ids, list) for ids in reported.values()), reported

    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("carp-writers")
    runs = client.search_runs([experiment.experiment_id], max_results=1000)
    assert len(runs) == writers * runs_per_writer
    assert {run.info.run_id for run in runs} == {run_id for ids in reported.values() for run_id in ids}
    seen = set()
    for run in runs:
        params = run.data.params
        writer, index = int(params["writer"]), int(params["index"])
        assert params["value"] == f"{writer}:{index}" and run.info.run_name == f"writer-{writer}"
        assert run.data.metrics == {"value": 100 * writer + index, "step": 2}
        assert run.info.status == "FINISHED" and run.info.run_id in reported[writer]
        seen.add((writer, index))
    assert seen == {(writer, index) for writer in range(writers) for index in range(runs_per_writer)}


@pytest.mark.slow
def test_runs_logged_by_two_processes_at_once_are_all_kept_with_their_own_params(server):
    # The experiment does not exist yet: both processes also race to create it.
    check_runs_logged_at_once(server[1], writers=2, runs_per_writer=6)


@pytest.mark.slow
def test_runs_logged_by_two_processes_at_once_into_sqlite_are_all_kept(tmp_path):
    # Two `dvc exp run --jobs 2` workers on the default store. Writers wait for each other's write locks through the
    # busy timeout MLflow sets on every SQLite session; without one, half the writes of two processes fail with
    # "database is locked".
    check_runs_logged_at_once(f"sqlite:///{tmp_path / 'mlflow.db'}", writers=2, runs_per_writer=15)


@pytest.mark.slow
def test_registered_tokenizer_is_stored_and_served_by_the_server(server, tmp_path):
    directory, url = server
    tokenizer_directory = tmp_path / "tokenizer"
    _, sha = make_artifact(tokenizer_directory)
    reference = register(url, tokenizer_directory, sha, alias="default")
    assert register(url, tokenizer_directory, sha, alias="default").version == reference.version

    artifact, fetched = fetch_registered_tokenizer(url, reference.uri)
    assert artifact.sha256 == sha and fetched.version == reference.version
    # The client wrote nothing itself: the run's artifacts went through the server into its destination.
    run = MlflowClient(tracking_uri=url).get_run(reference.run_id)
    assert run.info.artifact_uri.startswith("mlflow-artifacts:/")
    assert list((directory / "artifacts").rglob("tokenizer.pt"))
    assert not (tmp_path / "mlartifacts").exists() and not (tmp_path / "mlruns").exists()


def _register_at_once(uri: str, directory: str, sha: str, rounds: int, barrier, results) -> None:
    try:
        barrier.wait()
        with stage_run(uri, "carp-registrars", "register_tokenizer", {}, {}) as run:
            reference = register_tokenizer(uri, directory, "carp-tokenizer-race", "default", run.run_id, sha)
        client = MlflowClient(tracking_uri=uri)
        aliased = []
        for index in range(rounds):  # each round a new alias, set by every process at the same moment
            barrier.wait()
            aliased.append(
                str(point_alias(client, "carp-tokenizer-race", f"round{index}", reference.version, sha).version)
            )
        results.put((reference.version, aliased))
    except Exception as error:  # reported to the test, which names it
        barrier.abort()  # the others stop waiting for this process
        results.put(f"{type(error).__name__}: {error}")


@pytest.mark.slow
def test_processes_registering_the_same_tokenizer_at_once_all_succeed_on_one_version(server, tmp_path):
    # Two sweep workers reach `register_tokenizer` together: both may add a version and both insert the same new
    # alias, which PostgreSQL refuses to one of them on the alias's primary key.
    url, writers, rounds = server[1], 3, 8
    directory = tmp_path / "tokenizer"
    _, sha = make_artifact(directory)
    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(writers), context.Queue()
    processes = [
        context.Process(target=_register_at_once, args=(url, str(directory), sha, rounds, barrier, results))
        for _ in range(writers)
    ]
    for process in processes:
        process.start()
    reported = [results.get(timeout=600) for _ in processes]
    for process in processes:
        process.join(timeout=60)
    assert all(isinstance(outcome, tuple) for outcome in reported), reported
    versions = {version for version, _ in reported}
    assert len(versions) == 1, reported
    (version,) = versions
    assert all(aliased == [version] * rounds for _, aliased in reported), reported

    client = MlflowClient(tracking_uri=url)
    for alias in ["default", *(f"round{index}" for index in range(rounds))]:
        pointed = client.get_model_version_by_alias("carp-tokenizer-race", alias)
        assert pointed.version == version and pointed.tags[SHA_TAG] == sha


@pytest.mark.slow
def test_start_again_changes_nothing_and_stop_then_start_keeps_the_runs(server):
    directory, url = server
    state = json.loads((directory / "tracking.json").read_text())
    again = tool("tracking_server.py", "start", "--dir", str(directory))
    assert again.returncode == 0, again.stderr
    assert again.stdout.strip() == f"MLflow tracking server already running at {url}"
    assert json.loads((directory / "tracking.json").read_text()) == state

    with stage_run(url, "carp-restart", "before-restart", {"a": "1"}, {}) as before:
        pass
    stopped = tool("tracking_server.py", "stop", "--dir", str(directory))
    assert stopped.returncode == 0, stopped.stderr
    assert stopped.stdout.strip() == "MLflow server stopped; PostgreSQL stopped"
    for port in (state["port"], state["db_port"]):
        with socket.socket() as probe:
            assert probe.connect_ex(("127.0.0.1", port)) != 0, f"port {port} still answers"
    twice = tool("tracking_server.py", "stop", "--dir", str(directory))
    assert twice.returncode == 0 and twice.stdout.strip() == "MLflow server was not running; PostgreSQL was not running"

    restarted = tool("tracking_server.py", "start", "--dir", str(directory))
    assert restarted.returncode == 0, restarted.stderr
    assert f"MLflow tracking server at {url} " in restarted.stdout
    assert [run["run_id"] for run in find_runs(url, "carp-restart")] == [before.run_id]


def _single_error(completed) -> str:
    assert completed.returncode == 1 and completed.stdout == ""
    lines = completed.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), completed.stderr
    return lines[0]


def test_a_taken_port_is_refused_before_anything_is_created(tmp_path):
    directory = tmp_path / "tracking"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        refused = tool("tracking_server.py", "start", "--dir", str(directory), "--port", str(port), timeout=60)
    line = _single_error(refused)
    assert f"port {port} on 127.0.0.1 is in use by another program" in line and "--port" in line
    assert not directory.exists()


def test_missing_postgres_programs_are_named(tmp_path):
    directory = tmp_path / "tracking"
    refused = tool("tracking_server.py", "start", "--dir", str(directory), "--pg-bin", str(tmp_path), timeout=60)
    line = _single_error(refused)
    assert f"initdb and pg_ctl not found in {tmp_path}" in line and "apt-get install postgresql" in line
    assert not directory.exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="only root runs the database as another account")
def test_a_directory_the_database_account_cannot_enter_is_refused(tmp_path):
    private = tmp_path / "private"
    private.mkdir(mode=0o700)
    refused = tool("tracking_server.py", "start", "--dir", str(private / "tracking"), "--port", "0", timeout=60)
    line = _single_error(refused)
    assert "cannot reach this directory" in line and "chmod o+x" in line
    assert not (private / "tracking").exists()


def test_stop_where_nothing_was_started_is_one_error_line(tmp_path):
    line = _single_error(tool("tracking_server.py", "stop", "--dir", str(tmp_path), timeout=60))
    assert line == f"error: --dir={tmp_path}: no tracking server was started there (no tracking.json)"


def test_stop_never_signals_a_process_that_only_reuses_the_recorded_pid(tmp_path):
    # After a reboot the saved pid may belong to an unrelated program (here a sleeping process of ours).
    unrelated = subprocess.Popen(["sleep", "300"], start_new_session=True)
    try:
        state = {"mlflow_pid": unrelated.pid, "port": 5000, "pg_bin": "/usr/lib/postgresql/15/bin", "db_user": None}
        (tmp_path / "tracking.json").write_text(json.dumps(state))
        stopped = tool("tracking_server.py", "stop", "--dir", str(tmp_path), timeout=60)
        assert stopped.returncode == 0, stopped.stderr
        assert stopped.stdout.strip() == "MLflow server was not running; PostgreSQL was not running"
        assert unrelated.poll() is None
    finally:
        unrelated.kill()
        unrelated.wait()
