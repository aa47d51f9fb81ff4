import h5py
import numpy as np
import pytest
import torch

from carp.data.collect import collect_demonstrations
from carp.data.normalizer import MinMaxNormalizer
from carp.data.robomimic_io import DatasetError
from carp.evaluation.replay import TokenizedReplaySource, replay_demonstrations
from carp.tasks.arms.task import DELTA_ACTIONS
from carp.tokenizer.artifact import save_tokenizer_artifact
from carp.tokenizer.kinds.binning import BinningTokenizer
from carp.tokenizer.kinds.registry import load_tokenizer
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

TO, TA, H = 2, 8, 16


def delta_actions(steps: int) -> np.ndarray:
    """(T, 7) distinct rows: row t holds t in every column (delta actions are executed without conversion)."""
    return np.repeat(np.arange(steps, dtype=np.float64)[:, None], 7, axis=1)


def test_chunks_are_the_rows_a_policy_would_predict_and_execute():
    actions = delta_actions(20)
    source = TokenizedReplaySource({5: actions}, MinMaxNormalizer.fit(actions), None, DELTA_ACTIONS, TO, TA, H)
    source.reset(env=None, seed=5)
    # Decision at step 0: the chunk starts one step before (clamped to the first row), rows 1..8 are executed.
    np.testing.assert_array_equal(source.chunk()[:, 0], [0, 0, *range(1, 15)])
    np.testing.assert_array_equal(source.act(None, None)[0], actions[0:8])
    np.testing.assert_array_equal(source.act(None, None)[0], actions[8:16])
    # Past the recorded end the last action is held, as the training windows pad.
    np.testing.assert_array_equal(source.act(None, None)[0], actions[[16, 17, 18, 19, 19, 19, 19, 19]])


def test_each_chunk_goes_through_the_tokenizer_round_trip(tmp_path):
    torch.manual_seed(0)
    tokenizer = MultiScaleActionTokenizer(TokenizerSpec(action_dim=7, codebook_size=16)).eval()
    actions = np.random.default_rng(0).uniform(-2.0, 3.0, size=(30, 7))
    normalizer = MinMaxNormalizer.fit(actions)
    save_tokenizer_artifact(tmp_path, tokenizer, {"lift": normalizer}, "panda-delta7")
    source = TokenizedReplaySource({1: actions}, normalizer, load_tokenizer(tmp_path), DELTA_ACTIONS, TO, TA, H)
    source.reset(env=None, seed=1)
    source.act(None, None)
    recorded = actions[7:23]  # the decision at step 8
    with torch.no_grad():
        normalized = torch.as_tensor(normalizer.normalize(recorded[None]), dtype=torch.float32)
        expected = normalizer.unnormalize(tokenizer.decode_ids(tokenizer.encode_to_ids(normalized))[0].double().numpy())
    np.testing.assert_allclose(source.chunk(), expected, rtol=0, atol=1e-9)
    assert np.abs(source.chunk() - recorded).max() > 1e-3  # an untrained tokenizer does change the actions


def test_any_kind_replays_through_its_round_trip():
    actions = np.random.default_rng(1).uniform(-2.0, 3.0, size=(30, 7))
    normalizer = MinMaxNormalizer.fit(actions)
    tokenizer = BinningTokenizer(action_dim=7, action_horizon=H, bins=4)
    source = TokenizedReplaySource({1: actions}, normalizer, tokenizer, DELTA_ACTIONS, TO, TA, H)
    source.reset(env=None, seed=1)
    chunk = source.chunk()
    # Four bins over [-1, 1]: every replayed value is one of the four bin centres, within half a bin of the record.
    centres = normalizer.unnormalize(np.tile(np.array([-0.75, -0.25, 0.25, 0.75])[:, None], (1, 7)))
    assert all(np.isin(np.round(chunk[:, d], 9), np.round(centres[:, d], 9)).all() for d in range(7))
    recorded = actions[np.clip(np.arange(H) - (TO - 1), 0, None)]
    assert (np.abs(chunk - recorded) <= normalizer.half_range() * 0.25 + 1e-9).all()


@pytest.mark.slow
def test_recorded_scripted_demos_replay_to_success(tmp_path):
    path = tmp_path / "lift.hdf5"
    collect_demonstrations("lift", num_demos=2, output_path=path, seed=700)
    unused = MinMaxNormalizer.fit(np.zeros((1, 10)))  # statistics only matter with a tokenizer
    results = replay_demonstrations(path, unused, None, TO, TA, H, workers=1)
    assert [result.seed for result in results] == [700, 701]
    assert all(result.success and result.error == "" for result in results)


def test_demos_without_a_collection_seed_are_refused(synthetic_file):
    with h5py.File(synthetic_file, "r+") as handle:
        del handle["data/demo_1"].attrs["seed"]
    unused = MinMaxNormalizer.fit(np.zeros((1, 10)))
    with pytest.raises(DatasetError, match=r"raw.hdf5: demo 'demo_1' has no 'seed' attribute"):
        replay_demonstrations(synthetic_file, unused, None, TO, TA, H)
