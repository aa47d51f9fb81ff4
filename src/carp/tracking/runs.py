"""MLflow runs for pipeline stages: the only module (with the registry and the sweep) that imports mlflow.

One run per stage execution, tagged with the git commit, the DVC stage, the DVC experiment name (when run under
``dvc exp run``), a hash of the params and the host and process that ran it; params are logged flattened
(``policy.depth``). A run whose process was killed (``kill -9``) cannot end itself: the next execution of the same
stage on the same host marks it ``KILLED``.
"""

import fcntl
import hashlib
import json
import logging
import os
import socket
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import mlflow
from mlflow.exceptions import MlflowException
from mlflow.protos.databricks_pb2 import RESOURCE_ALREADY_EXISTS, ErrorCode
from mlflow.tracking import MlflowClient

logger = logging.getLogger(__name__)

# MLflow caps a param value at 6000 characters; longer values (e.g. nested lists) are cut with a marker.
MAX_PARAM_LENGTH = 6000
# Which process runs a stage, so that a run left RUNNING by a killed process can be recognized later.
HOST_TAG = "carp.host"
PID_TAG = "carp.pid"


def resolve_tracking_uri(uri: str, project_root: Path) -> str:
    """Make a relative ``sqlite:///relative.db`` URI absolute against ``project_root``.

    Args:
        uri: a tracking URI; ``sqlite:///x.db`` is relative, ``sqlite:////abs/x.db`` absolute.
        project_root: directory that relative paths refer to (the main workspace, never a DVC temp workspace).
    """
    prefix = "sqlite:///"
    if uri.startswith(prefix) and not uri[len(prefix) :].startswith("/"):
        return f"{prefix}{(Path(project_root) / uri[len(prefix) :]).resolve()}"
    return uri


def sqlite_path(tracking_uri: str) -> Path | None:
    """The database file of an absolute ``sqlite:///`` URI, or ``None`` for any other store."""
    prefix = "sqlite:///"
    return Path(tracking_uri[len(prefix) :]) if tracking_uri.startswith(prefix) else None


@contextmanager
def store_creation_lock(tracking_uri: str) -> Iterator[None]:
    """Hold an exclusive inter-process lock while a SQLite store's schema and experiments are created.

    Two stages that open a store which does not exist yet (``dvc exp run --run-all --jobs 2`` on a fresh project)
    otherwise both run MLflow's schema migrations, and one of them fails; two that create the same experiment at
    once fail the same way. The lock file sits beside the database (``mlflow.db.lock``). Server stores serialize
    this themselves, so other URIs take no lock.
    """
    database = sqlite_path(tracking_uri)
    if database is None:
        yield
        return
    database.parent.mkdir(parents=True, exist_ok=True)
    with open(database.with_name(f"{database.name}.lock"), "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def artifact_root(tracking_uri: str) -> str | None:
    """Artifacts next to a SQLite store (``<dir>/mlartifacts``), so runs never write into the working directory."""
    database = sqlite_path(tracking_uri)
    return (database.parent / "mlartifacts").as_uri() if database is not None else None


def ensure_experiment(tracking_uri: str, experiment_name: str) -> str:
    """Id of the named experiment, created (with its artifact root beside the store) when missing.

    The first call on a new SQLite store also creates its schema; both happen under :func:`store_creation_lock`.
    A tracking server takes no lock: when another client creates the experiment between our lookup and our
    creation (two stages starting at once on a fresh server), the server refuses the duplicate and we use theirs.
    """
    with store_creation_lock(tracking_uri):
        client = MlflowClient(tracking_uri=tracking_uri)
        experiment = client.get_experiment_by_name(experiment_name)
        if experiment is not None:
            return experiment.experiment_id
        root = artifact_root(tracking_uri)
        location = f"{root}/{experiment_name}" if root else None
        try:
            return client.create_experiment(experiment_name, artifact_location=location)
        except MlflowException as error:
            if error.error_code != ErrorCode.Name(RESOURCE_ALREADY_EXISTS):
                raise
            return client.get_experiment_by_name(experiment_name).experiment_id


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def end_orphaned_runs(tracking_uri: str, experiment_id: str, run_name: str) -> list[str]:
    """Mark ``KILLED`` the ``RUNNING`` runs of ``run_name`` whose process on the local host no longer exists.

    A run of the same stage still going in another live process (a parallel ``dvc exp run`` worker) is left alone,
    and so is one started on another host, whose processes cannot be inspected locally.

    Returns:
        The ids of the runs that were ended.
    """
    client = MlflowClient(tracking_uri=tracking_uri)
    running = client.search_runs(
        [experiment_id],
        filter_string=f"attributes.run_name = '{run_name}' and attributes.status = 'RUNNING'",
    )
    ended = []
    for run in running:
        tags = run.data.tags
        pid = tags.get(PID_TAG, "")
        if tags.get(HOST_TAG) != socket.gethostname() or not pid.isdigit() or _process_alive(int(pid)):
            continue
        client.set_tag(run.info.run_id, "carp.end_reason", f"process {pid} ended without closing the run")
        client.set_terminated(run.info.run_id, status="KILLED")
        logger.warning("MLflow run %s of %s (process %s, gone) marked KILLED", run.info.run_id, run_name, pid)
        ended.append(run.info.run_id)
    return ended


def params_hash(flat_params: Mapping[str, str]) -> str:
    """Short sha256 of the flattened params, stable across key order."""
    return hashlib.sha256(json.dumps(dict(sorted(flat_params.items()))).encode()).hexdigest()[:16]


@dataclass
class StageRun:
    """Handle on an active MLflow run."""

    run_id: str
    experiment_id: str

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Log numeric metrics (non-numbers are skipped); names keep only MLflow-safe characters."""
        clean = {_metric_name(k): float(v) for k, v in metrics.items() if isinstance(v, (int, float))}
        if clean:
            mlflow.log_metrics(clean, step=step)

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        """Copy a file or directory into the run's artifacts."""
        path = Path(path)
        if path.is_dir():
            mlflow.log_artifacts(str(path), artifact_path=artifact_path)
        elif path.exists():
            mlflow.log_artifact(str(path), artifact_path=artifact_path)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        """Add tags to the run."""
        mlflow.set_tags(dict(tags))


def _metric_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "_-./ " else "_" for c in name)


@contextmanager
def stage_run(
    tracking_uri: str,
    experiment_name: str,
    run_name: str,
    flat_params: Mapping[str, str],
    tags: Mapping[str, str],
    parent_run_id: str | None = None,
) -> Iterator[StageRun]:
    """Open an MLflow run for one stage execution; ends it FAILED if the body raises.

    Args:
        tracking_uri: absolute tracking URI (see :func:`resolve_tracking_uri`).
        experiment_name: created when missing.
        run_name: e.g. ``train_policy@lift``.
        flat_params: dotted-key params; logged as run params.
        tags: e.g. git commit, DVC stage, DVC experiment; the params hash is added.
        parent_run_id: makes this a nested (child) run, e.g. a sweep trial under its study's run.
    """
    mlflow.set_tracking_uri(tracking_uri)
    experiment = mlflow.set_experiment(experiment_id=ensure_experiment(tracking_uri, experiment_name))
    end_orphaned_runs(tracking_uri, experiment.experiment_id, run_name)
    all_tags = {
        **tags,
        "carp.params_hash": params_hash(flat_params),
        HOST_TAG: socket.gethostname(),
        PID_TAG: str(os.getpid()),
    }
    if parent_run_id is not None:
        all_tags["mlflow.parentRunId"] = parent_run_id
    with mlflow.start_run(run_name=run_name, tags=all_tags) as run:
        params = {key: value[:MAX_PARAM_LENGTH] for key, value in flat_params.items()}
        # MLflow accepts at most 100 params per call.
        items = list(params.items())
        for start in range(0, len(items), 100):
            mlflow.log_params(dict(items[start : start + 100]))
        yield StageRun(run_id=run.info.run_id, experiment_id=experiment.experiment_id)


def find_runs(tracking_uri: str, experiment_name: str, filter_string: str = "") -> list[dict]:
    """Runs of an experiment as plain dicts (id, name, status, tags, metrics), newest first."""
    client = MlflowClient(tracking_uri=tracking_uri)
    experiment = client.get_experiment_by_name(experiment_name)
    if experiment is None:
        return []
    runs = client.search_runs([experiment.experiment_id], filter_string=filter_string, order_by=["start_time DESC"])
    return [
        {
            "run_id": run.info.run_id,
            "run_name": run.info.run_name,
            "status": run.info.status,
            "tags": dict(run.data.tags),
            "metrics": dict(run.data.metrics),
        }
        for run in runs
    ]
