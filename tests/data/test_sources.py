import hashlib

import pytest

from carp.data.sources import SourceError, describe_source
from tests.conftest import write_synthetic_file


def test_scripted_source_record_names_only_the_task():
    assert describe_source("lift", None, project_root=".") == {"task": "lift", "source": "scripted"}


def test_user_file_record_changes_with_the_bytes_and_not_with_the_timestamp(tmp_path):
    user_file = tmp_path / "own" / "lift.hdf5"
    user_file.parent.mkdir()
    user_file.write_bytes(b"first version")
    first = describe_source("lift", "own/lift.hdf5", tmp_path)
    assert first == {
        "task": "lift",
        "source": "file",
        "path": "own/lift.hdf5",
        "sha256": hashlib.sha256(b"first version").hexdigest(),
        "bytes": 13,
    }
    user_file.touch()
    assert describe_source("lift", "own/lift.hdf5", tmp_path) == first
    user_file.write_bytes(b"other version")
    assert describe_source("lift", "own/lift.hdf5", tmp_path)["sha256"] != first["sha256"]


@pytest.mark.parametrize(
    "make, reason", [(lambda path: None, "file not found"), (lambda path: path.mkdir(), "not a regular file")]
)
def test_missing_or_directory_source_is_refused_with_the_key(tmp_path, make, reason):
    make(tmp_path / "lift.hdf5")
    with pytest.raises(SourceError, match=rf"^data\.raw_files\.lift='lift\.hdf5': {reason}"):
        describe_source("lift", "lift.hdf5", tmp_path)


def test_a_lerobot_folder_is_recorded_by_the_hash_of_its_files(tmp_path):
    import shutil

    from tests.data.lerobot.fixtures import FIXTURES

    shutil.copytree(FIXTURES / "v3.0", tmp_path / "pusht")
    record = describe_source("pusht", "pusht", tmp_path)
    assert record["source"] == "lerobot" and record["files"] == 7 and "cameras" not in record
    assert describe_source("pusht", "pusht", tmp_path) == record
    (tmp_path / "pusht" / "meta" / "extra.json").write_text("{}")
    added = describe_source("pusht", "pusht", tmp_path)
    assert added["sha256"] != record["sha256"] and added["files"] == 8
    (tmp_path / "pusht" / "meta" / "extra.json").unlink()
    (tmp_path / "pusht" / "meta" / "info.json").write_text("{}")
    assert describe_source("pusht", "pusht", tmp_path)["sha256"] != record["sha256"]
    cameras = describe_source("pusht", "pusht", tmp_path, cameras=("top",), image_size=32)
    assert cameras["cameras"] == ["top"] and cameras["image_size"] == 32
    # A robomimic file's record does not depend on the cameras: ingestion, not collect, reads its images.
    write_synthetic_file(tmp_path / "lift.hdf5")
    assert "cameras" not in describe_source("lift", "lift.hdf5", tmp_path, cameras=("top",), image_size=32)
