"""What scripted collection records for the arm tasks, pinned by stored demos.

The first `STEPS` steps of the expert's seed-0 demo on Lift, Can and Square (absolute actions), taken through the task
seam the way `collect` takes them (`run_expert_episode`), must match `REFERENCE_FILE`: the actions the controller
received, the object observation and the simulator state. A change to a task's env arguments, reset, expert plan,
action conversion or observation keys shows up here, so adding a task or changing the seam cannot move the arm tasks'
seeded demos unnoticed. After a deliberate change, or an upgrade of robosuite or MuJoCo that moves the numbers,
regenerate the file with :func:`write_reference` and say why in the commit.
"""

from pathlib import Path

import numpy as np
import pytest

from carp.data.collect import run_expert_episode
from carp.tasks import get_task

REFERENCE_FILE = Path(__file__).parent / "data" / "arm_expert_reference.npz"
TASKS = ("lift", "can", "square")
SEED = 0
STEPS = 40
# MuJoCo steps the same float64 computation on every CPU the pinned wheel runs on, up to the rounding of its
# vectorized kernels, which differs between CPU vendors by a float32 unit in the last place of a stored value
# (about 1.2e-7 near 1); a changed plan, reset or conversion moves actions by millimetres or more.
TOLERANCE = 1e-6


def record(task_name: str) -> dict[str, np.ndarray]:
    """(STEPS, 7) actions, (STEPS, Do_object) object observations and (STEPS, S) states of the seed-0 demo."""
    task = get_task(task_name)
    env = task.make_env(task.make_env_args("absolute"))
    try:
        episode, _ = run_expert_episode(task, env, SEED, STEPS)
    finally:
        env.close()
    return {"actions": episode.actions, "object": episode.obs["object"], "states": episode.states}


def write_reference(path: Path = REFERENCE_FILE) -> Path:
    """Record every task's reference into `path`.

    ``python -c "from tests.tasks.test_arm_expert_reference import write_reference; write_reference()"``
    """
    arrays = {f"{task}/{key}": value for task in TASKS for key, value in record(task).items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE_FILE) as stored:
        return {key: stored[key] for key in stored.files}


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_expert_demo_matches_the_stored_reference(task, reference):
    recorded = record(task)
    for key, value in recorded.items():
        expected = reference[f"{task}/{key}"]
        assert value.shape == expected.shape, key
        np.testing.assert_allclose(value, expected, rtol=0, atol=TOLERANCE, err_msg=f"{task} {key}")


@pytest.mark.parametrize("task", TASKS)
def test_reference_demo_moves_the_arm_and_the_object(task, reference):
    """A reference in which nothing moved would pin nothing about the plan."""
    actions = reference[f"{task}/actions"]
    assert actions.shape == (STEPS, 7)
    assert np.ptp(actions[:, :3], axis=0).max() > 1e-2  # the commanded position travels centimetres
    assert len({row.round(4).tobytes() for row in actions}) > STEPS // 2
