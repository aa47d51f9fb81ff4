"""Pipelines built once per test run, for end-to-end tests that start from a finished run.

Two workspaces are built with :func:`~tests.pipeline.workspace.make_workspace` and a full `dvc repro`: the arm
pipeline (:data:`LIFT_PIPELINE`) and the Push-T pipeline (:data:`PUSHT_PIPELINE`). A test takes its own copy with
:func:`copy_pipeline` (the fixtures ``lift_pipeline`` and ``pusht_pipeline`` give the built workspace, never to be
changed), changes params or files in it, and `dvc repro` reruns only the stages that the change reaches: the copy
holds the DVC cache (``.dvc/cache``, the run cache included), every output, ``dvc.lock`` and the MLflow store.

A third, ``lift_demos``, stops after the demos are ingested and commits them: experiments and sweeps start from it.

Under pytest-xdist every worker asks for the same workspace: the first builds it under a file lock in the run's
shared temporary folder (``getbasetemp().parent``), the others wait for the lock and find it built.
"""

import fcntl
import os
import shutil
import sqlite3
import sys
from pathlib import Path

import pytest
import yaml

from tests.pipeline.workspace import make_workspace, merge, run

# The arm pipeline: Lift on the tiny params, CARP and VQ-BeT, four demos for Lift through its per-task count.
LIFT_PIPELINE = {"data": {"num_demos_per_task": {"lift": 4}}, "policies": ["carp", "vq_bet"]}

# The Push-T pipeline: the planning expert's demos, CARP with the two families that bring their own tokenizer and
# teacher (VQ-BeT's residual VQ-VAE, Consistency Policy's EDM teacher), a video of one evaluation episode.
TINY_UNET = {"down_dims": [16, 32], "kernel_size": 3, "num_groups": 8, "step_embedding_dim": 16, "warmup_steps": 2}
PUSHT_PIPELINE = {
    "tasks": ["pusht"],
    "policies": ["carp", "vq_bet", "consistency_policy"],
    "edm_unet": TINY_UNET,
    "consistency_policy": TINY_UNET | {"num_levels": 10},
    "eval": {"max_steps": {"pusht": 30}, "video": True, "video_episodes": 1},
}


def shared_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder all workers of this run share: the base temp folder's parent under pytest-xdist, else the base."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def build_once(
    tmp_path_factory: pytest.TempPathFactory,
    name: str,
    params: dict,
    targets: tuple[str, ...] = (),
    commit: bool = False,
) -> Path:
    """The workspace ``name`` with ``params`` after `dvc repro` of ``targets`` (every stage when empty), built by the
    first worker that asks; with ``commit``, its outputs tracked in git are committed.

    A failed build is recorded beside the workspace: the other workers fail with its message instead of building
    again.
    """
    root = shared_root(tmp_path_factory) / "shared-pipelines"
    root.mkdir(exist_ok=True)
    workspace, done, failed = root / name / "carp", root / f"{name}.done", root / f"{name}.failed"
    with (root / f"{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not done.exists() and not failed.exists():
                _build(workspace, params, targets, commit, failed)
                done.touch()
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    if failed.exists():
        pytest.fail(f"the shared {name} workspace failed to build:\n{failed.read_text()}", pytrace=False)
    return workspace


def _build(workspace: Path, params: dict, targets: tuple[str, ...], commit: bool, failed: Path) -> None:
    if workspace.parent.exists():
        shutil.rmtree(workspace.parent)
    workspace.mkdir(parents=True)
    make_workspace(workspace, params)
    commands = [[sys.executable, "-m", "dvc", "repro", *targets]]
    if commit:
        commands += [["git", "add", "-A"], ["git", "commit", "-qm", "built"]]
    for command in commands:
        completed = run(command, workspace, timeout=1800)
        if completed.returncode != 0:
            failed.write_text(f"{' '.join(command)}\n{completed.stdout[-3000:]}{completed.stderr[-3000:]}")
            return


def copy_pipeline(source: Path, directory: Path, params: dict | None = None, tracking: bool = True) -> Path:
    """A copy of the built workspace ``source`` at ``directory / "carp"``, independent of it.

    Args:
        source: a workspace from the ``lift_pipeline`` or ``pusht_pipeline`` fixture.
        directory: created; the copy goes into its ``carp`` folder.
        params: overrides merged into the copy's ``params.yaml`` (as :func:`make_workspace` merges them) and
            committed; `dvc repro` then reruns the stages they reach.
        tracking: with False the copy starts without an MLflow store (a test that counts the runs a change logs).
            Otherwise the copy's store points at the copy's own ``mlartifacts``: the store records absolute artifact
            locations, rewritten here.
    """
    workspace = directory / "carp"

    def ignore(folder: str, names: list[str]) -> set[str]:
        # DVC's own scratch folder (locks, indexes, queued experiments) stays behind; DVC makes a new one.
        left = {"tmp"} if Path(folder) == source / ".dvc" else set()
        if not tracking and Path(folder) == source:
            left |= {"mlflow.db", "mlartifacts"}
        return left & set(names)

    shutil.copytree(source, workspace, symlinks=True, ignore=ignore)
    if (workspace / "mlflow.db").exists():
        _move_store(workspace, source)
    if params:
        params_file = workspace / "params.yaml"
        merged = merge(yaml.safe_load(params_file.read_text()), params)
        params_file.write_text(yaml.safe_dump(merged, sort_keys=False))
        for command in (["git", "add", "params.yaml"], ["git", "commit", "-qm", "variation"]):
            completed = run(command, workspace)
            assert completed.returncode == 0, completed.stderr
    return workspace


def _move_store(workspace: Path, source: Path) -> None:
    """Rewrite every text naming ``source`` (a path or a file URI) in the copy's MLflow store to name ``workspace``:
    the SQLite database's text columns and the text files among the artifacts (a logged model's ``MLmodel``)."""
    old, new = str(source.resolve()), str(workspace.resolve())
    connection = sqlite3.connect(workspace / "mlflow.db")
    with connection:
        tables = [row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        for table in tables:
            columns = [
                row[1]
                for row in connection.execute(f'PRAGMA table_info("{table}")')
                if any(kind in row[2].upper() for kind in ("CHAR", "TEXT"))
            ]
            for column in columns:
                connection.execute(
                    f'UPDATE "{table}" SET "{column}" = replace("{column}", ?, ?) WHERE instr("{column}", ?) > 0',
                    (old, new, old),
                )
    connection.close()
    for path in (workspace / "mlartifacts").rglob("*"):
        if path.is_file() and path.stat().st_size < 1_000_000:
            try:
                text = path.read_text()
            except UnicodeDecodeError:
                continue
            if old in text:
                path.write_text(text.replace(old, new))


@pytest.fixture(scope="session")
def lift_demos(tmp_path_factory) -> Path:
    """A workspace on the tiny params whose demos are collected and ingested, all of it committed in git: the start of
    experiment and sweep tests (each copies it with ``copy_workspace`` of tests/pipeline/experiments_support.py)."""
    return build_once(tmp_path_factory, "lift-demos", {}, targets=("ingest",), commit=True)


@pytest.fixture(scope="session")
def lift_pipeline(tmp_path_factory) -> Path:
    """The arm pipeline (:data:`LIFT_PIPELINE`) after a full `dvc repro`; copy it with :func:`copy_pipeline`."""
    return build_once(tmp_path_factory, "lift", LIFT_PIPELINE)


@pytest.fixture(scope="session")
def pusht_pipeline(tmp_path_factory) -> Path:
    """The Push-T pipeline (:data:`PUSHT_PIPELINE`) after a full `dvc repro`; copy it with :func:`copy_pipeline`."""
    return build_once(tmp_path_factory, "pusht", PUSHT_PIPELINE)
