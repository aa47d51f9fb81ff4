"""Task measures: the registry, Square's insertion offset at the nut's first contact with its peg, the rollout and the
episodes table carrying it, and Lift's episodes left as they were."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carp import simulation
from carp.evaluation.insertion_offset import InsertionOffset
from carp.evaluation.rollout import EpisodeResult, run_episode
from carp.evaluation.runner import episodes_table
from carp.evaluation.sources import ExpertSource
from carp.tasks import get_task
from carp.tasks.base import NoMeasure

OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
EPISODE_COLUMNS = ["seed", "success", "steps", "seconds", "chunks", "chunk_ms_median", "error"]
MEASURE_COLUMNS = ["insertion_offset_mm", "insertion_contact_step"]


def hold_still(env) -> np.ndarray:
    """(8, 7) absolute actions that keep the gripper where it is, open."""
    site = env.robots[0].eef_site_id["right"]
    rotation = Rotation.from_matrix(env.sim.data.site_xmat[site].reshape(3, 3)).as_rotvec()
    return np.repeat(np.concatenate([env.sim.data.site_xpos[site], rotation, [-1.0]])[None], 8, axis=0)


class DropNut:
    """After the reset, puts the square nut above its peg and holds the arm still while the nut falls.

    The nut is turned to match the peg (both square to the world axes), its hole centre ``offset_m`` (x, y) beside
    the peg's centre and its underside ``gap_m`` above the peg's top.
    """

    def __init__(self, offset_m: tuple[float, float], gap_m: float = 0.01) -> None:
        self.offset_m = offset_m
        self.gap_m = gap_m

    def reset(self, env, seed: int) -> None:
        data, model = env.sim.data, env.sim.model
        nut = env.nuts[env.nut_id]
        peg = data.body_xpos[env.peg1_body_id]
        peg_geom = np.flatnonzero(model.geom_bodyid == env.peg1_body_id)[0]
        peg_top = data.geom_xpos[peg_geom][2] + model.geom_size[peg_geom][2]
        nut_half_height = model.geom_size[env.obj_geom_id[nut.name][0]][2]
        position = [peg[0] + self.offset_m[0], peg[1] + self.offset_m[1], peg_top + nut_half_height + self.gap_m]
        data.set_joint_qpos(nut.joints[0], np.concatenate([position, [1.0, 0.0, 0.0, 0.0]]))
        env.sim.forward()

    def act(self, history, env):
        return hold_still(env), None


class HoldStill:
    """Keeps the arm where the reset left it."""

    def reset(self, env, seed: int) -> None:
        pass

    def act(self, history, env):
        return hold_still(env), None


@pytest.fixture(scope="module")
def square_env():
    env = simulation.make_env(simulation.make_env_args("square"))
    yield env
    env.close()


def test_square_measures_its_insertion_offset_and_the_other_arm_tasks_nothing():
    square = get_task("square")
    assert isinstance(square.measure(), InsertionOffset)
    assert square.measure() is not square.measure()  # one per episode
    for task in ("lift", "can"):
        assert isinstance(get_task(task).measure(), NoMeasure) and get_task(task).measure().values() == {}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("offset_m", "expected_mm"),
    [
        ((0.010, 0.0), 10.0),  # the hole's -x wall lands on the peg's top, 3.25 mm of it over the peg
        ((-0.008, 0.008), math.hypot(8.0, 8.0)),  # two walls land on it: the distance is horizontal, in x and y
    ],
    ids=["one wall on the peg", "two walls on the peg"],
)
def test_a_nut_dropped_onto_the_peg_is_measured_at_the_offset_it_falls_with(square_env, offset_m, expected_mm):
    result = run_episode(get_task("square"), square_env, DropNut(offset_m), 0, OBS_KEYS, 2, 10)
    # Nothing pushes the nut sideways while it falls, so it touches the peg at the offset it was dropped with. The
    # 1 cm fall takes 45 ms, just inside the first 50 ms control step, so when the measure looks the nut has tipped
    # on the peg's edge for at most a few physics steps (2 ms each); 0.2 mm is room for that tipping and no more.
    assert result.error == ""
    assert result.task_measures["insertion_offset_mm"] == pytest.approx(expected_mm, abs=0.2)
    assert result.task_measures["insertion_contact_step"] == 1.0
    table = episodes_table([result])
    assert list(table.columns) == EPISODE_COLUMNS + MEASURE_COLUMNS
    assert table["insertion_offset_mm"][0] == result.task_measures["insertion_offset_mm"]


@pytest.mark.slow
def test_a_nut_that_clears_the_peg_never_touches_it_and_has_no_measure(square_env):
    # The hole is 45.5 mm across and the peg 32 mm: turned to match the peg, a nut 5 mm off its centre slides down
    # around it to the table. robosuite then counts it as on the peg, but there was no contact to measure.
    result = run_episode(get_task("square"), square_env, DropNut((0.005, 0.0)), 0, OBS_KEYS, 2, 10)
    nut_position = square_env.sim.data.body_xpos[square_env.obj_body_id[square_env.nuts[square_env.nut_id].name]]
    assert square_env.on_peg(nut_position, 0)
    assert math.isnan(result.task_measures["insertion_offset_mm"])
    assert math.isnan(result.task_measures["insertion_contact_step"])
    assert list(episodes_table([result]).columns) == EPISODE_COLUMNS + MEASURE_COLUMNS


@pytest.mark.slow
def test_the_scripted_expert_touches_the_peg_within_robosuites_on_peg_tolerance(square_env):
    result = run_episode(get_task("square"), square_env, ExpertSource("square"), 1000, OBS_KEYS, 2, 400)
    assert result.success
    assert 0 <= result.task_measures["insertion_offset_mm"] < 30.0  # robosuite's on-peg check: 3 cm in x and y
    assert 0 < result.task_measures["insertion_contact_step"] <= result.steps


@pytest.mark.slow
def test_a_lift_episode_records_no_measure_and_keeps_its_columns():
    env = simulation.make_env(simulation.make_env_args("lift"))
    try:
        result = run_episode(get_task("lift"), env, HoldStill(), 0, OBS_KEYS, 2, 3)
    finally:
        env.close()
    assert result.error == "" and result.steps == 3 and result.task_measures == {}
    assert list(episodes_table([result]).columns) == EPISODE_COLUMNS


def test_the_episodes_table_has_a_column_per_measure_nan_where_an_episode_lacks_it():
    measured = [
        EpisodeResult(1, True, 50, 1.0, task_measures={"insertion_offset_mm": 4.0, "insertion_contact_step": 30.0}),
        EpisodeResult(2, False, 0, 1.0, error="worker killed by SIGKILL (2 attempts)"),
    ]
    table = episodes_table(measured)
    assert list(table.columns) == EPISODE_COLUMNS + MEASURE_COLUMNS
    assert table["insertion_offset_mm"][0] == 4.0 and math.isnan(table["insertion_offset_mm"][1])
    assert list(episodes_table([EpisodeResult(1, True, 50, 1.0)]).columns) == EPISODE_COLUMNS
