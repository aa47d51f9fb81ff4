"""`mlflow server` on the project's SQLite store lists stage runs and registered tokenizers over its REST API."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest

from carp.tracking.runs import stage_run
from tests.tracking.test_registry import make_artifact, register

STARTUP_SECONDS = 180  # a cold start imports a lot on a busy two-core machine
REQUEST_SECONDS = 30


def free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def call(base: str, path: str, payload: dict | None = None) -> dict:
    """GET (no payload) or POST JSON to the server; returns the decoded answer."""
    data = None if payload is None else json.dumps(payload).encode()
    request = urllib.request.Request(f"{base}{path}", data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=REQUEST_SECONDS) as response:
        return json.loads(response.read() or b"{}")


def wait_until_answering(base: str, server: subprocess.Popen, log_path) -> None:
    deadline = time.monotonic() + STARTUP_SECONDS
    while True:
        assert server.poll() is None, f"mlflow server exited:\n{log_path.read_text()[-3000:]}"
        try:
            with urllib.request.urlopen(f"{base}/health", timeout=5) as response:
                if response.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        assert time.monotonic() < deadline, f"no answer within {STARTUP_SECONDS} s:\n{log_path.read_text()[-3000:]}"
        time.sleep(0.5)


def group_is_gone(group: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.killpg(group, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.2)
    return False


@pytest.mark.slow
def test_server_lists_runs_and_registered_tokenizer_and_dies_with_its_group(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tags = {"carp.dvc_stage": "train_policy@lift"}
    with stage_run(uri, "carp-lift", "train_policy@lift", {"policy.depth": "1"}, tags) as run:
        run.log_metrics({"loss": 0.5}, step=1)
    directory = tmp_path / "tokenizer"
    _, sha = make_artifact(directory)
    reference = register(uri, directory, sha, alias="default")

    port = free_loopback_port()
    base = f"http://127.0.0.1:{port}"
    log_path = tmp_path / "server.log"
    command = [
        sys.executable, "-m", "mlflow", "server",
        "--backend-store-uri", uri,
        "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
    ]  # fmt: skip
    with log_path.open("w") as log:
        server = subprocess.Popen(command, cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    group = os.getpgid(server.pid)
    try:
        wait_until_answering(base, server, log_path)

        experiments = call(base, "/api/2.0/mlflow/experiments/search", {"max_results": 100})["experiments"]
        by_name = {experiment["name"]: experiment["experiment_id"] for experiment in experiments}
        assert {"carp-lift", "carp-tokenizer"} <= set(by_name)

        runs = call(base, "/api/2.0/mlflow/runs/search", {"experiment_ids": [by_name["carp-lift"]]})["runs"]
        assert [r["info"]["run_id"] for r in runs] == [run.run_id]
        tags = {tag["key"]: tag["value"] for tag in runs[0]["data"]["tags"]}
        assert tags["carp.dvc_stage"] == "train_policy@lift" and "carp.params_hash" in tags
        assert {m["key"]: m["value"] for m in runs[0]["data"]["metrics"]} == {"loss": 0.5}
        tokenizer_runs = call(base, "/api/2.0/mlflow/runs/search", {"experiment_ids": [by_name["carp-tokenizer"]]})
        assert len(tokenizer_runs["runs"]) == 1

        models = call(base, "/api/2.0/mlflow/registered-models/search?max_results=100")["registered_models"]
        model = next(m for m in models if m["name"] == reference.name)
        assert {"alias": "default", "version": reference.version} in model["aliases"]
    finally:
        os.killpg(group, signal.SIGTERM)
        if not group_is_gone(group, timeout=15):
            os.killpg(group, signal.SIGKILL)
        server.wait(timeout=30)
    assert group_is_gone(group, timeout=30), f"processes of group {group} survived"
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(f"{base}/health", timeout=5)
