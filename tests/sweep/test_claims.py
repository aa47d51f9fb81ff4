"""Claims of grid points on SQLite (one machine); the same code on PostgreSQL is in test_distributed_sweep.py."""

import threading

import pytest

from carp.sweep.claims import ClaimLostError, ClaimStore

POINTS = [f"point-{index}" for index in range(6)]


@pytest.fixture
def url(tmp_path) -> str:
    return f"sqlite:///{tmp_path / 'optuna.db'}"


def stores(url: str, count: int, study_id: int = 1) -> list[ClaimStore]:
    return [ClaimStore(url, study_id) for _ in range(count)]


def test_workers_claim_distinct_points_until_the_budget_is_spent(url):
    first, second = stores(url, 2)
    claimed = []
    for _ in range(3):
        claimed += [first.claim(POINTS, num_slots=4, stale_seconds=60), second.claim(POINTS, 4, 60)]
    assert claimed[:4] == POINTS[:4] and claimed[4:] == [None, None]  # in the given order, at most 4 in all
    assert sorted(claim.slot for claim in first.claims()) == [0, 1, 2, 3]
    # A larger budget frees more slots; a study with another id has its own claims.
    assert first.claim(POINTS, num_slots=5, stale_seconds=60) == POINTS[4]
    assert ClaimStore(url, study_id=2).claim(POINTS, 1, 60) == POINTS[0]


def test_threads_racing_for_points_claim_each_once(url):
    workers = stores(url, 4)
    won: list[tuple[int, str]] = []
    lock = threading.Lock()

    def work(index: int) -> None:
        while (point := workers[index].claim(POINTS, num_slots=5, stale_seconds=60)) is not None:
            with lock:
                won.append((index, point))

    threads = [threading.Thread(target=work, args=(index,)) for index in range(len(workers))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    points = [point for _, point in won]
    assert len(points) == 5 and len(set(points)) == 5
    assert sorted(claim.point for claim in workers[0].claims()) == sorted(points)


def test_claim_moves_from_a_failed_trial_to_its_retry(url):
    first, second = stores(url, 2)
    point = first.claim(POINTS, 6, 60)
    first.assign(point, trial_number=0)
    assert second.transfer(failed_trial=0, retry_trial=3) == point
    assert [(claim.point, claim.trial_number) for claim in first.claims()] == [(point, 3)]
    assert second.transfer(failed_trial=7, retry_trial=8) is None


def test_a_claim_left_without_a_trial_is_taken_over_once_it_is_stale(url):
    first, second, third = stores(url, 3)
    point = first.claim(POINTS[:1], num_slots=1, stale_seconds=60)
    assert second.claim(POINTS[:1], num_slots=1, stale_seconds=60) is None  # fresh: its owner may be alive
    assert second.claim(POINTS[:1], num_slots=1, stale_seconds=-1) == point  # stale: taken over, slot kept
    assert third.claim(POINTS[:1], num_slots=1, stale_seconds=60) is None  # taken over once: fresh again
    with pytest.raises(ClaimLostError, match="taken over by another worker"):
        first.assign(point, trial_number=0)
    second.assign(point, trial_number=1)
    assert third.claim(POINTS[:1], num_slots=1, stale_seconds=-1) is None  # it has a trial now
    assert [(claim.slot, claim.trial_number) for claim in first.claims()] == [(0, 1)]


def test_existing_trials_are_recorded_beyond_the_budget_and_values_keep_the_first_writer(url):
    first, second = stores(url, 2)
    for number, point in enumerate(POINTS[:3]):
        first.record(point, number)
    first.record(POINTS[0], 9)  # already claimed: unchanged
    assert [(claim.point, claim.slot, claim.trial_number) for claim in second.claims()] == [
        (POINTS[0], 0, 0),
        (POINTS[1], 1, 1),
        (POINTS[2], 2, 2),
    ]
    assert second.claim(POINTS, num_slots=2, stale_seconds=60) is None

    assert first.get("parent") is None
    assert first.setdefault("parent", "run-a") == "run-a"
    assert second.setdefault("parent", "run-b") == "run-a" == second.get("parent")
