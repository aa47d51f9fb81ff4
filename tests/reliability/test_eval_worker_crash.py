"""An evaluation worker killed hard (SIGKILL, as a native crash or the OOM killer would) costs one episode at most.

The action source below kills its own worker process with SIGKILL when it is reset for a chosen seed, so the
evaluator meets a real dead process, not a mocked pool.
"""

import functools
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from carp.evaluation.metrics import summarize_episodes
from carp.evaluation.rollout import EPISODE_ATTEMPTS, WorkerStartError, evaluate_episodes
from carp.evaluation.runner import episodes_table
from carp.tasks import get_task

OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
MAX_STEPS = 8


class KillingSource:
    """Keeps the gripper where it is; on a chosen seed it logs the attempt, then SIGKILLs its own process.

    Args:
        kills: seed -> how many of its attempts kill the worker (a later attempt runs normally).
        log_directory: one line per attempt at such a seed goes to `<seed>.log` there.
    """

    def __init__(self, kills: dict[int, int], log_directory: str) -> None:
        self.kills = kills
        self.log_directory = Path(log_directory)

    def reset(self, env, seed: int) -> None:
        if seed not in self.kills:
            return
        log = self.log_directory / f"{seed}.log"
        earlier = len(log.read_text().splitlines()) if log.exists() else 0
        with log.open("a") as lines:
            lines.write(f"{os.getpid()}\n")
        if earlier < self.kills[seed]:
            os.kill(os.getpid(), signal.SIGKILL)

    def act(self, observation_history: np.ndarray, env):
        return np.zeros((MAX_STEPS, 7)), None


def _suicidal_factory() -> KillingSource:
    os.kill(os.getpid(), signal.SIGKILL)


def _evaluate(source_factory, seeds: list[int]):
    return evaluate_episodes(
        get_task("lift").make_env_args("absolute"),
        source_factory,
        seeds,
        OBS_KEYS,
        obs_steps=2,
        max_steps=MAX_STEPS,
        workers=2,
    )


@pytest.mark.slow
def test_a_killed_worker_costs_at_most_its_episode_and_an_always_crashing_episode_is_recorded(tmp_path):
    # Seed 21 kills every worker that runs it; seed 22 only the first.
    seeds = [20, 21, 22, 23]
    results = _evaluate(functools.partial(KillingSource, {21: 1_000, 22: 1}, str(tmp_path)), seeds)

    assert [result.seed for result in results] == seeds
    crashed = results[1]
    assert not crashed.success and crashed.steps == 0
    assert crashed.error == f"worker killed by SIGKILL ({EPISODE_ATTEMPTS} attempts)"
    # Retried once on a fresh worker, then given up: no endless loop on a seed that always crashes.
    attempt_pids = (tmp_path / "21.log").read_text().split()
    assert len(attempt_pids) == EPISODE_ATTEMPTS == len(set(attempt_pids))
    # A worker killed once (as the OOM killer might) costs nothing: the episode ran again and finished.
    assert len((tmp_path / "22.log").read_text().split()) == 2
    for result in results[:1] + results[2:]:
        assert result.error == "" and result.steps == MAX_STEPS, result

    # The crash is a failed episode in the success rate, counted and explained in the reports.
    summary = summarize_episodes(
        successes=[r.success for r in results],
        steps=[r.steps for r in results],
        crashed=[bool(r.error) for r in results],
        prediction_seconds=[],
        decoding_seconds=[],
    )
    assert summary["episodes"] == 4 and summary["crashed_episodes"] == 1 and summary["success_rate"] == 0.0
    table = episodes_table(results)
    assert table.loc[table["seed"] == 21, "error"].item() == "worker killed by SIGKILL (2 attempts)"
    assert (table.loc[table["seed"] != 21, "error"] == "").all()


@pytest.mark.slow
def test_a_worker_that_dies_while_starting_stops_the_evaluation_with_the_reason():
    with pytest.raises(WorkerStartError, match="an evaluation worker killed by SIGKILL while starting"):
        _evaluate(_suicidal_factory, [40, 41])
