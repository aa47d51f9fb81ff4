"""End to end on several machines' services, all real and on loopback, started by the project's own `tools/`.

One S3-compatible object store (SeaweedFS) and one MLflow tracking server on PostgreSQL whose artifacts live in that
store. The tiny pipeline runs once against the server (`tracking.uri: http://...`); the tests then check what the
server holds, reuse the registered tokenizer from it, run two queued experiments at once into it, and move data and
models through a DVC remote (a directory, and the object store) into a fresh clone whose `dvc repro` has nothing to
do. Every test works on its own copy of the run workspace.
"""

import json
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from mlflow import MlflowClient

from carp.tracking.registry import fetch_registered_tokenizer
from tests.pipeline.workspace import dvc, make_workspace, queue_status, run_queued_experiments, stages_run, tool_env
from tests.services import object_store, s3_keys, service_directory, tool, tracking_server

STAGES = {
    "collect@lift",
    "ingest@lift",
    "train_tokenizer",
    "register_tokenizer",
    "train_policy@lift-carp-0",
    "evaluate@lift-carp-0",
}
TIMEOUT_SECONDS = 1800
# What `dvc pull` must bring back: demos, processed data, tokenizer and policy.
RESTORED = (
    "data/raw/lift.hdf5",
    "data/processed/lift/normalization.json",
    "models/tokenizer/tokenizer.pt",
    "models/policy/lift/carp/seed0/policy.pt",
)


def run(command: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run a command in ``cwd`` with the test interpreter first on PATH and ``env`` added; fails on non-zero exit."""
    completed = subprocess.run(
        command, cwd=cwd, env={**tool_env(), **(env or {})}, capture_output=True, text=True, timeout=TIMEOUT_SECONDS
    )
    assert completed.returncode == 0, f"{command}:\n{completed.stdout[-2000:]}\n{completed.stderr[-3000:]}"
    return completed


@pytest.fixture(scope="module")
def services():
    with service_directory("carp-services-") as directory, object_store(directory / "s3") as s3:
        with tracking_server(directory / "tracking", "--artifacts-destination", "s3://carp/mlflow", env=s3) as url:
            yield SimpleNamespace(url=url, s3=s3, directory=directory)


@pytest.fixture(scope="module")
def pipeline(services, tmp_path_factory) -> Path:
    """The tiny pipeline run once against the server, committed as a lab would before sharing it."""
    workspace = make_workspace(tmp_path_factory.mktemp("shared") / "carp", {"tracking": {"uri": services.url}})
    run(dvc("repro"), workspace)
    run(["git", "add", "-A"], workspace)
    run(["git", "commit", "-qm", "tiny run"], workspace)
    return workspace


def copy_workspace(workspace: Path, directory: Path) -> Path:
    copy = directory / "carp"
    shutil.copytree(workspace, copy, symlinks=True)
    return copy


def set_params(workspace: Path, change) -> None:
    path = workspace / "params.yaml"
    params = yaml.safe_load(path.read_text())
    change(params)
    path.write_text(yaml.safe_dump(params, sort_keys=False))


def server_runs(url: str) -> list:
    client = MlflowClient(tracking_uri=url)
    return client.search_runs([e.experiment_id for e in client.search_experiments()], max_results=1000)


@pytest.mark.slow
def test_every_stage_run_and_the_registered_tokenizer_live_on_the_server(pipeline, services):
    runs = [r for r in server_runs(services.url) if not r.data.tags.get("carp.dvc_experiment")]
    assert sorted(r.data.tags["carp.dvc_stage"] for r in runs) == sorted(STAGES)
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert {r.data.params["tracking.uri"] for r in runs} == {services.url}
    assert all(r.info.artifact_uri.startswith("mlflow-artifacts:/") for r in runs)
    assert not (pipeline / "mlflow.db").exists() and not (pipeline / "mlartifacts").exists()

    reference = json.loads((pipeline / "models/tokenizer_ref.json").read_text())
    client = MlflowClient(tracking_uri=services.url)
    version = client.get_model_version_by_alias(reference["name"], reference["alias"])
    assert version.version == reference["version"] and version.tags["carp.sha256"] == reference["sha256"]
    # The artifacts sit in the object store, and the server serves them to a client that has no S3 credentials.
    keys = s3_keys(services.s3, "carp", "mlflow/")
    assert any(key.endswith("/tokenizer.pt") for key in keys) and any(key.endswith("/MLmodel") for key in keys)
    artifact, _ = fetch_registered_tokenizer(services.url, f"models:/{reference['name']}@{reference['alias']}")
    assert artifact.sha256 == reference["sha256"]


@pytest.mark.slow
def test_a_tokenizer_registered_on_the_server_is_reused_without_training(pipeline, services, tmp_path):
    workspace = copy_workspace(pipeline, tmp_path)
    reference = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    uri = f"models:/{reference['name']}@{reference['alias']}"
    set_params(workspace, lambda params: params["tokenizer"].update(source=uri))
    completed = run(dvc("repro", "train_tokenizer"), workspace)
    assert "Running stage 'train_tokenizer'" in completed.stdout

    metadata = json.loads((workspace / "models/tokenizer/tokenizer.json").read_text())
    assert metadata["sha256"] == reference["sha256"]
    latest = max(
        (r for r in server_runs(services.url) if r.data.tags.get("carp.dvc_stage") == "train_tokenizer"),
        key=lambda r: r.info.start_time,
    )
    assert latest.data.tags["carp.tokenizer_source"] == uri and "train_loss" not in latest.data.metrics


@pytest.mark.slow
def test_two_queued_experiments_run_at_once_log_every_run_into_the_server(pipeline, services, tmp_path):
    workspace = copy_workspace(pipeline, tmp_path)
    sizes = {"shared-a": 8, "shared-b": 32}
    for name, size in sizes.items():
        run(dvc("exp", "run", "--queue", "-n", name, "-S", f"codebook_size={size}"), workspace)
    run_queued_experiments(workspace, jobs=2)
    assert queue_status(workspace)[0] == {"Success": 2}, run(dvc("queue", "status"), workspace).stdout

    runs = server_runs(services.url)
    for name, size in sizes.items():
        tagged = [r for r in runs if r.data.tags.get("carp.dvc_experiment") == name]
        stages = sorted(r.data.tags["carp.dvc_stage"] for r in tagged)
        assert stages == sorted(
            {"train_tokenizer", "register_tokenizer", "train_policy@lift-carp-0", "evaluate@lift-carp-0"}
        ), name
        assert {r.info.status for r in tagged} == {"FINISHED"}, name
        assert {r.data.params["codebook_size"] for r in tagged} == {str(size)}, name


@pytest.mark.slow
def test_object_store_start_again_changes_nothing(services):
    again = tool("object_store.py", "start", "--dir", str(services.directory / "s3"), timeout=120)
    assert again.returncode == 0, again.stderr
    assert again.stdout.strip() == f"object store already running at {services.s3['AWS_ENDPOINT_URL_S3']} (bucket carp)"


def push_then_pull_into_a_fresh_clone(workspace: Path, clone: Path, env: dict | None = None) -> None:
    """Commit the remote's config, `dvc push`, clone with git, `dvc pull`; the clone's `dvc repro` does nothing."""
    run(["git", "add", ".dvc/config"], workspace)
    run(["git", "commit", "-qm", "shared DVC remote"], workspace)
    run(dvc("push"), workspace, env)
    run(["git", "clone", "-q", str(workspace), str(clone)], clone.parent)
    assert not (clone / "models/policy/lift/carp/seed0/policy.pt").exists()
    run(dvc("pull"), clone, env)
    for output in RESTORED:
        assert (clone / output).read_bytes() == (workspace / output).read_bytes(), output

    repro = run(dvc("repro"), clone, env)
    assert stages_run(repro.stdout) == {"check_inputs"}, repro.stdout
    status = run(dvc("status", "--json"), clone, env)
    assert json.loads(status.stdout) == {"check_inputs": ["always changed"]}


@pytest.mark.slow
def test_directory_remote_restores_data_and_models_in_a_fresh_clone(pipeline, tmp_path):
    workspace = copy_workspace(pipeline, tmp_path)
    remote = tmp_path / "share" / "carp-dvc"
    configured = tool("dvc_remote.py", str(remote), "--project", str(workspace), timeout=120)
    assert configured.returncode == 0, configured.stderr
    assert (tmp_path / "share").is_dir()
    push_then_pull_into_a_fresh_clone(workspace, tmp_path / "clone")
    assert any(path.is_file() for path in remote.rglob("*"))


@pytest.mark.slow
def test_s3_remote_restores_data_and_models_in_a_fresh_clone(pipeline, services, tmp_path):
    workspace = copy_workspace(pipeline, tmp_path)
    endpoint = services.s3["AWS_ENDPOINT_URL_S3"]
    configured = tool("dvc_remote.py", "s3://carp/dvc", "--endpoint-url", endpoint, "--project", str(workspace))
    assert configured.returncode == 0, configured.stderr
    config = (workspace / ".dvc/config").read_text()
    assert "s3://carp/dvc" in config and endpoint in config
    assert services.s3["AWS_SECRET_ACCESS_KEY"] not in config  # credentials stay in each machine's environment
    credentials = {key: value for key, value in services.s3.items() if key != "AWS_ENDPOINT_URL_S3"}
    push_then_pull_into_a_fresh_clone(workspace, tmp_path / "clone", credentials)
    assert s3_keys(services.s3, "carp", "dvc/")
