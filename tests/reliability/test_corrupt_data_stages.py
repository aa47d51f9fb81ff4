"""Collect and ingest stage scripts on every corrupt file: one `error:` line naming file and key, nothing written.

Each case runs the real script in a subprocess of a temporary workspace (the one-line contract is the script's, not
only the library's): collect imports the file named by `data.raw_files.lift`, ingest reads `data/raw/lift.hdf5`.
The cases on camera images run in a workspace whose `data.obs_keys` lists the image keys as well.
"""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import IMAGE_KEYS, OBS_KEYS, write_synthetic_file
from tests.pipeline.workspace import make_workspace, run
from tests.reliability.corrupt_files import CORRUPT_FILES, corrupt_file, expected_message

pytestmark = pytest.mark.slow

USER_FILE = "user/lift.hdf5"


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    return make_workspace(tmp_path_factory.mktemp("corrupt"), {"data": {"raw_files": {"lift": USER_FILE}}})


@pytest.fixture(scope="module")
def image_workspace(tmp_path_factory) -> Path:
    data = {"raw_files": {"lift": USER_FILE}, "obs_keys": [*OBS_KEYS, *IMAGE_KEYS]}
    return make_workspace(tmp_path_factory.mktemp("corrupt-images"), {"data": data})


def _paths(workspace: Path, stage: str) -> tuple[Path, Path]:
    """(where the corrupt file goes, the stage's output) for one stage."""
    if stage == "collect":
        return workspace / USER_FILE, workspace / "data" / "raw" / "lift.hdf5"
    return workspace / "data" / "raw" / "lift.hdf5", workspace / "data" / "processed" / "lift"


@pytest.mark.parametrize("name", sorted(CORRUPT_FILES))
@pytest.mark.parametrize("stage", ["collect", "ingest"])
def test_stage_refuses_corrupt_file_with_one_line_and_writes_nothing(request, stage, name):
    workspace = request.getfixturevalue("image_workspace" if CORRUPT_FILES[name].with_images else "workspace")
    path, output = _paths(workspace, stage)
    try:
        with corrupt_file(name, path) as case:
            completed = run([sys.executable, f"pipeline/{stage}.py", "--task", "lift"], workspace, timeout=300)
    finally:
        path.unlink(missing_ok=True)
    errors = [line for line in completed.stderr.splitlines() if line.startswith("error:")]
    assert completed.returncode != 0
    assert "Traceback" not in completed.stderr and len(errors) == 1, completed.stderr
    assert errors[0].startswith(f"error: {expected_message(case, path.resolve())}"), errors[0]
    assert case.problem in errors[0]
    assert not output.exists()
    leftovers = [
        p for folder in ("data/.staging", "data/raw", "data/processed") for p in workspace.glob(f"{folder}/.*")
    ]
    assert leftovers == []


def test_valid_file_passes_both_stages_and_dead_leftovers_are_cleared(workspace):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    leftovers = [
        workspace / "data" / ".staging" / f".lift.{int(dead.stdout)}.tmp",
        workspace / "data" / "processed" / f".lift.{int(dead.stdout)}.tmp",  # where staging used to be
    ]
    for leftover in leftovers:
        leftover.mkdir(parents=True)
    user_file = workspace / USER_FILE
    write_synthetic_file(user_file)
    try:
        for stage in ("collect", "ingest"):
            completed = run([sys.executable, f"pipeline/{stage}.py", "--task", "lift"], workspace, timeout=300)
            assert completed.returncode == 0, completed.stderr
    finally:
        user_file.unlink()
    assert (workspace / "data" / "raw" / "lift.hdf5").read_bytes() != b""
    assert sorted(p.name for p in (workspace / "data" / "processed").iterdir()) == ["lift"]
    assert list((workspace / "data" / ".staging").iterdir()) == []
    shutil.rmtree(workspace / "data" / "processed")
    (workspace / "data" / "raw" / "lift.hdf5").unlink()
