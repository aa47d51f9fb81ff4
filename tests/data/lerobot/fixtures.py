"""The LeRobotDataset fixtures that LeRobot's own writer made (tests/fixtures/lerobot), and damaged copies."""

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures" / "lerobot"
VERSIONS = ("v3.0", "v2.1")
LENGTHS = (12, 9, 15)
TASKS = ("push the T into the target", "push the T, then stop")
# The fixtures' obs keys as carp names them: `state` reads observation.state.
OBS_KEYS = ("state", "environment_state")
ENV_ARGS = {"env_name": "PushT", "type": "pusht"}


def fixture_copy(version: str, tmp_path: Path) -> Path:
    """A writable copy of the fixture of one codebase version."""
    root = tmp_path / f"dataset-{version}"
    shutil.copytree(FIXTURES / version, root)
    return root


def inputs(version: str) -> dict[str, np.ndarray]:
    """What LeRobot's writer was given: ``<feature>_<episode>`` arrays, (T, D)."""
    with np.load(FIXTURES / version / "inputs.npz") as data:
        return dict(data)


def data_file(root: Path, episode: int) -> Path:
    """The Parquet file holding an episode's frames (v3: one shared file; v2.1: one per episode)."""
    legacy = root / "data" / "chunk-000" / f"episode_{episode:06d}.parquet"
    return legacy if legacy.exists() else root / "data" / "chunk-000" / "file-000.parquet"


def edit_rows(path: Path, edit, schema: pa.Schema | None = None) -> None:
    """Rewrite a Parquet file after ``edit(rows)`` changed its rows (a list of dicts) in place."""
    table = pq.read_table(path)
    rows = table.to_pylist()
    edit(rows)
    pq.write_table(pa.Table.from_pylist(rows, schema=schema or table.schema), path)


def episode_rows(rows: list[dict], episode: int) -> list[dict]:
    """The rows of one episode, in file order."""
    return [row for row in rows if row["episode_index"] == episode]


def edit_info(root: Path, edit) -> None:
    """Rewrite meta/info.json after ``edit(info)``."""
    path = root / "meta" / "info.json"
    info = json.loads(path.read_text())
    edit(info)
    path.write_text(json.dumps(info))


def with_field_type(path: Path, name: str, kind: pa.DataType) -> pa.Schema:
    """The file's schema with column ``name`` of type ``kind``."""
    schema = pq.read_schema(path)
    return schema.set(schema.get_field_index(name), pa.field(name, kind))


def without_field(path: Path, name: str) -> pa.Schema:
    """The file's schema without column ``name``."""
    schema = pq.read_schema(path)
    return schema.remove(schema.get_field_index(name))
