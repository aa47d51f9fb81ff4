"""A study point's open-loop replay: measured once from the point's own tokenizer copy, shown in the report."""

import json

import numpy as np
import pytest

from carp.data.collect import collect_demonstrations
from carp.data.ingest import NORMALIZATION_FILENAME
from carp.data.normalizer import MinMaxNormalizer, save_normalizers
from carp.data.robomimic_io import read_demonstrations
from carp.studies import point_replay
from carp.studies.point_replay import REPLAY_FILE, TOKENIZER_FOLDER, ReplaySetup, read_replay, replay_cell, replay_point
from carp.tasks import task_for_env_args
from carp.tokenizer.kinds.binning import BinningTokenizer

TO, TA, H = 2, 8, 16


def workspace(tmp_path, num_demos=2):
    """data/raw/lift.hdf5 (carp-collected) and its action statistics, as a pipeline workspace holds them."""
    raw = tmp_path / "data/raw/lift.hdf5"
    raw.parent.mkdir(parents=True)
    collect_demonstrations("lift", num_demos=num_demos, output_path=raw, seed=700)
    demos = read_demonstrations(raw, ())
    action_format = task_for_env_args(demos.env_args).action_format(
        task_for_env_args(demos.env_args).controller_of(demos.env_args)
    )
    actions = np.concatenate([action_format.to_policy(episode.actions) for episode in demos.episodes])
    statistics = tmp_path / "data/processed/lift" / NORMALIZATION_FILENAME
    statistics.parent.mkdir(parents=True)
    save_normalizers(statistics, {"action": MinMaxNormalizer.fit(actions)})
    return ReplaySetup(tmp_path / "data/raw", tmp_path / "data/processed", TO, TA, H, num_demos=num_demos)


@pytest.mark.slow
def test_the_points_demos_replay_through_its_tokenizer_once(tmp_path, monkeypatch):
    setup = workspace(tmp_path)
    point = tmp_path / "study/V512"
    BinningTokenizer(action_dim=10, action_horizon=H, bins=256).save(point / TOKENIZER_FOLDER)
    figures = replay_point(point, ["lift"], setup)
    # 256 bins over each normalized dimension are finer than Lift needs: both demos still lift the cube.
    assert figures == {"lift": {"successes": 2, "demos": 2}}
    assert json.loads((point / REPLAY_FILE).read_text()) == figures
    assert replay_cell(read_replay(point), "lift") == "2/2" and replay_cell(figures, "can") == "-"

    def no_second_replay(*args, **kwargs):
        raise AssertionError("a stored replay is not measured again")

    monkeypatch.setattr(point_replay, "replay_demonstrations", no_second_replay)
    assert replay_point(point, ["lift"], setup) == figures


def test_no_tokenizer_copy_or_no_demos_measures_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(point_replay, "replay_demonstrations", pytest.fail)
    setup = ReplaySetup(tmp_path / "raw", tmp_path / "processed", TO, TA, H, num_demos=5)
    assert replay_point(tmp_path / "K4", ["lift"], setup) == {}
    BinningTokenizer(action_dim=10, action_horizon=H).save(tmp_path / "K4" / TOKENIZER_FOLDER)
    none = ReplaySetup(tmp_path / "raw", tmp_path / "processed", TO, TA, H, num_demos=0)
    assert replay_point(tmp_path / "K4", ["lift"], none) == {}
    assert not (tmp_path / "K4" / REPLAY_FILE).exists()
