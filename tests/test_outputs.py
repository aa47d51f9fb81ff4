import json

import pandas as pd
import pytest

from carp.outputs import atomic_path, write_history, write_json, write_text


def test_json_is_written_with_sorted_keys_and_no_temporary_left(tmp_path):
    path = tmp_path / "reports" / "metrics.json"
    write_json(path, {"b": 1.5, "a": [1, 2]})
    assert json.loads(path.read_text()) == {"a": [1, 2], "b": 1.5}
    assert path.read_text().index('"a"') < path.read_text().index('"b"')
    write_json(path, {"c": 0})
    assert json.loads(path.read_text()) == {"c": 0}
    assert sorted(p.name for p in path.parent.iterdir()) == ["metrics.json"]


def test_history_round_trips_and_no_epochs_give_a_header(tmp_path):
    path = tmp_path / "history.csv"
    write_history(path, [{"epoch": 1, "loss": 2.0}, {"epoch": 2, "loss": 1.0}])
    assert pd.read_csv(path).to_dict("records") == [{"epoch": 1, "loss": 2.0}, {"epoch": 2, "loss": 1.0}]
    write_history(path, [])
    assert path.read_text().strip() == "epoch"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["history.csv"]


def test_an_interrupted_write_leaves_the_previous_file_and_no_temporary(tmp_path):
    path = tmp_path / "deep" / "metrics.txt"
    write_text(path, "before")
    with pytest.raises(RuntimeError, match="disk full"), atomic_path(path) as temporary:
        temporary.write_text("half")
        raise RuntimeError("disk full")
    assert path.read_text() == "before"
    assert [entry.name for entry in path.parent.iterdir()] == ["metrics.txt"]
    with atomic_path(path) as temporary:
        assert temporary.parent == path.parent and temporary.name.startswith(".metrics.txt.")
        temporary.write_text("after")
    assert path.read_text() == "after" and len(list(path.parent.iterdir())) == 1
