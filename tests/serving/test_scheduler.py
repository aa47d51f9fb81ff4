import numpy as np
import pytest
from carp_client import ChunkScheduler, ensemble_weights

from carp.evaluation.sources import ChunkEnsemble

# To = 2 (offset 1), Ta = 3, H = 6: a plain chunk covers 3 steps, an ensembled one H - To + 1 = 5.
OFFSET, ACTION_STEPS, HORIZON = 1, 3, 6


def stamped_chunk(step: int) -> np.ndarray:
    """(H, 2) float32 chunk whose row r holds (prediction step, the step the row acts at = step + r - To + 1)."""
    rows = np.arange(HORIZON)
    return np.stack([np.full(HORIZON, step), step + rows - OFFSET], axis=1).astype(np.float32)


def test_plain_execution_gives_each_step_the_row_stamped_with_it_and_asks_again_after_ta_steps():
    scheduler = ChunkScheduler(OFFSET, ACTION_STEPS)
    executed, queried = [], []
    for step in range(7):
        if not scheduler.has_action(step):
            queried.append(step)
            scheduler.add(stamped_chunk(step), step)
        executed.append(scheduler.action(step))
    assert queried == [0, 3, 6]
    np.testing.assert_array_equal(np.stack(executed)[:, 1], np.arange(7))  # every action belongs to its step
    np.testing.assert_array_equal(np.stack(executed)[:, 0], [0, 0, 0, 3, 3, 3, 6])


def test_a_late_chunk_loses_only_its_stale_rows_and_the_newest_prediction_wins():
    scheduler = ChunkScheduler(OFFSET, ACTION_STEPS)
    scheduler.add(stamped_chunk(0), 0)
    np.testing.assert_array_equal(scheduler.action(0), [0, 0])
    np.testing.assert_array_equal(scheduler.action(1), [0, 1])
    # Predicted from step 1's observation, arriving after step 1 ran: its row for step 1 is dropped.
    assert scheduler.add(stamped_chunk(1), 1) == 2
    np.testing.assert_array_equal(scheduler.action(2), [1, 2])
    np.testing.assert_array_equal(scheduler.action(3), [1, 3])
    assert scheduler.action(4) is None and not scheduler.has_action(4)
    # Entirely stale: nothing kept; an executed step cannot be asked again.
    assert scheduler.add(stamped_chunk(0), 0) == 0
    with pytest.raises(ValueError, match="step 2 comes before step 4"):
        scheduler.action(2)
    # Skipped steps' actions are dropped.
    scheduler.add(stamped_chunk(5), 5)
    np.testing.assert_array_equal(scheduler.action(7), [5, 7])
    assert not scheduler.has_action(6)
    scheduler.reset()
    assert scheduler.action(0) is None


def test_the_ensemble_weights_are_acts_exponential_weights_oldest_first():
    np.testing.assert_allclose(ensemble_weights(3, 0.5), np.exp([0.0, -0.5, -1.0]) / np.exp([0.0, -0.5, -1.0]).sum())
    np.testing.assert_array_equal(ensemble_weights(4, 0.0), np.full(4, 0.25))
    assert ensemble_weights(1, 2.0).tolist() == [1.0]


def test_ensembling_constant_chunks_gives_the_constant():
    scheduler = ChunkScheduler(OFFSET, ACTION_STEPS, ensemble_m=0.1)
    for step in range(8):
        scheduler.add(np.full((HORIZON, 2), 0.3, np.float32), step)
        action = scheduler.action(step)
        assert action.dtype == np.float32
        np.testing.assert_array_equal(action, np.full(2, 0.3, np.float32))


def test_ensembling_weights_every_chunk_covering_a_step_by_its_age():
    m = 0.7
    scheduler = ChunkScheduler(OFFSET, ACTION_STEPS, ensemble_m=m)
    chunks = [np.random.default_rng(step).normal(size=(HORIZON, 2)) for step in range(6)]
    for step in range(6):
        scheduler.add(chunks[step], step)
        action = scheduler.action(step)
        # Chunks predicted at steps step-4 .. step cover it (H - To + 1 = 5 rows from the offset), oldest first.
        covering = range(max(0, step - (HORIZON - OFFSET) + 1), step + 1)
        rows = np.stack([chunks[past][OFFSET + step - past] for past in covering])
        np.testing.assert_allclose(action, ensemble_weights(len(rows), m) @ rows, rtol=1e-12)


def test_a_scheduler_follows_the_servers_metadata_and_refuses_bad_settings():
    scheduler = ChunkScheduler.from_metadata({"executed_offset": 1, "action_steps": 8}, ensemble_m=0.01)
    assert (scheduler.executed_offset, scheduler.action_steps, scheduler.ensemble_m) == (1, 8, 0.01)
    with pytest.raises(ValueError, match="ensemble_m must be >= 0"):
        ChunkScheduler(1, 8, ensemble_m=-1.0)
    with pytest.raises(ValueError, match="4 rows cannot cover 8 steps from row 1"):
        ChunkScheduler(1, 8).add(np.zeros((4, 2)), 0)


@pytest.mark.parametrize("m", [0.0, 0.3])
def test_the_client_ensembles_served_chunks_as_the_evaluation_ensembles_its_own(m):
    # carp_client never imports carp, so the rule lives twice: the robot and the simulator must execute alike.
    rng = np.random.default_rng(4)
    chunks = rng.normal(size=(12, 6, 3))  # a chunk per step, H = 6, To = 2: each covers 5 steps
    scheduler = ChunkScheduler(executed_offset=1, action_steps=4, ensemble_m=m)
    ensemble = ChunkEnsemble(m)
    for step, chunk in enumerate(chunks):
        scheduler.add(chunk, step)
        np.testing.assert_allclose(scheduler.action(step), ensemble.act(chunk[1:]), rtol=1e-12, atol=1e-12)
