import os
import subprocess
import sys

import pytest

from carp.data.staging import remove_stale_entries, staged


def _dead_pid() -> int:
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(finished.stdout)


def test_staged_path_is_removed_when_the_block_fails(tmp_path):
    with pytest.raises(RuntimeError), staged(tmp_path / "staging", "lift") as path:
        assert path == tmp_path / "staging" / f".lift.{os.getpid()}.tmp"
        path.mkdir()
        (path / "part").write_text("half")
        raise RuntimeError("killed halfway")
    assert list((tmp_path / "staging").iterdir()) == []


def test_only_entries_of_exited_processes_are_removed(tmp_path):
    dead = _dead_pid()
    (tmp_path / f".lift.{dead}.tmp").mkdir()
    (tmp_path / f".lift.hdf5.{dead}.tmp").write_text("partial")
    kept = [f".lift.{os.getpid()}.tmp", f".lift.{os.getppid()}.tmp", "lift", f"lift.{dead}.tmp", ".notes.tmp"]
    for name in kept:
        (tmp_path / name).write_text("keep")
    removed = remove_stale_entries(tmp_path)
    assert sorted(path.name for path in removed) == [f".lift.{dead}.tmp", f".lift.hdf5.{dead}.tmp"]
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted(kept)
    assert remove_stale_entries(tmp_path / "missing") == []
