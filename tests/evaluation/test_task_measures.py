"""Task measures: the registry, Square's insertion offset at the nut's first contact with its peg, the rollout and the
episodes table carrying it, and Lift's episodes left as they were."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carp.evaluation.rollout import EpisodeResult, run_episode
from carp.evaluation.runner import episodes_table
from carp.evaluation.sources import ExpertSource
from carp.tasks import get_task
from carp.tasks.arms import simulation
from carp.tasks.arms.insertion_offset import InsertionOffset
from carp.tasks.base import NoMeasure
from carp.tasks.threading.insertion import THREADING_PAIRS

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


def peg_top(env, peg_body: int) -> float:
    """World height of a peg's top face (``peg1`` a box, ``peg2`` a cylinder)."""
    import mujoco

    data, model = env.sim.data, env.sim.model
    geom = np.flatnonzero(model.geom_bodyid == peg_body)[0]
    half_height = model.geom_size[geom][1 if model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_CYLINDER else 2]
    return float(data.geom_xpos[geom][2] + half_height)


class DropBothNuts:
    """NutAssembly: puts nut i above peg i + 1, its hole centre ``offsets_m[i]`` (x, y) beside the peg's centre and its
    underside 1 cm above the peg's top, square to the world axes; then holds the arm still while both fall."""

    def __init__(self, offsets_m: tuple[tuple[float, float], tuple[float, float]]) -> None:
        self.offsets_m = offsets_m

    def reset(self, env, seed: int) -> None:
        data, model = env.sim.data, env.sim.model
        for nut, peg_body, offset in zip(env.nuts, (env.peg1_body_id, env.peg2_body_id), self.offsets_m, strict=True):
            peg = data.body_xpos[peg_body]
            nut_half_height = model.geom_size[env.obj_geom_id[nut.name][0]][2]
            height = peg_top(env, peg_body) + nut_half_height + 0.01
            position = [peg[0] + offset[0], peg[1] + offset[1], height]
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
    env = simulation.make_env(get_task("square").make_env_args("absolute"))
    yield env
    env.close()


def test_the_insertion_tasks_measure_their_insertion_offsets_and_the_other_arm_tasks_nothing():
    square = get_task("square")
    assert isinstance(square.measure(), InsertionOffset)
    assert square.measure() is not square.measure()  # one per episode
    assert isinstance(get_task("nut_assembly").measure(), InsertionOffset)
    threading = get_task("threading").measure()
    assert isinstance(threading, InsertionOffset) and threading.pairs == THREADING_PAIRS
    for task in ("lift", "can", "stack", "stack_three"):
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
    env = simulation.make_env(get_task("lift").make_env_args("absolute"))
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


NUT_ASSEMBLY_MEASURES = [
    "insertion_offset_mm",
    "insertion_contact_step",
    "square_nut_insertion_offset_mm",
    "square_nut_insertion_contact_step",
    "round_nut_insertion_offset_mm",
    "round_nut_insertion_contact_step",
]


@pytest.mark.slow
def test_nut_assembly_measures_each_nut_on_its_own_peg_at_the_offset_it_falls_with():
    env = simulation.make_env(get_task("nut_assembly").make_env_args("absolute"))
    try:
        # The square nut's -x wall lands on its peg's top; the round nut's hole (31.2 mm to its flats) is 15 mm off
        # the round peg's centre (20 mm radius), so its -y wall lands 3.8 mm over the peg's edge.
        source = DropBothNuts(((0.010, 0.0), (0.0, 0.015)))
        result = run_episode(get_task("nut_assembly"), env, source, 0, OBS_KEYS, 2, 10)
    finally:
        env.close()
    assert result.error == ""
    measures = result.task_measures
    assert list(measures) == NUT_ASSEMBLY_MEASURES
    assert measures["square_nut_insertion_offset_mm"] == pytest.approx(10.0, abs=0.2)
    assert measures["round_nut_insertion_offset_mm"] == pytest.approx(15.0, abs=0.2)
    assert measures["insertion_offset_mm"] == pytest.approx(12.5, abs=0.2)  # the episode's: the mean of the two
    steps = [measures[key] for key in NUT_ASSEMBLY_MEASURES if key.endswith("contact_step")]
    assert steps == [1.0, 1.0, 1.0]
    assert list(episodes_table([result]).columns) == EPISODE_COLUMNS + NUT_ASSEMBLY_MEASURES


class _Contacts:
    """An env's sim data: bodies at ``body_xpos``, no contacts until a test sets ``ncon`` and ``contact.geom``."""

    def __init__(self, body_xpos: np.ndarray) -> None:
        self.body_xpos = body_xpos
        self.ncon = 0
        self.contact = type("Contact", (), {"geom": np.zeros((0, 2), dtype=np.int64)})()


def test_a_pair_untouched_stays_nan_and_the_episode_takes_the_pairs_that_touched():
    from carp.tasks.nut_assembly.task import NUT_ASSEMBLY_PAIRS

    measure = InsertionOffset(NUT_ASSEMBLY_PAIRS)
    # Geoms 0-1 the square nut, 2 its peg, 3 the round nut, 4 its peg; bodies 1-4 in the same order.
    positions = np.zeros((5, 3))
    positions[1] = [0.003, 0.004, 0.9]  # 5 mm from the square peg at the origin
    env = type("Env", (), {})()
    env.nuts = [type("Nut", (), {"name": name})() for name in ("SquareNut", "RoundNut")]
    env.obj_body_id = {"SquareNut": 1, "RoundNut": 3}
    env.obj_geom_id = {"SquareNut": [0, 1], "RoundNut": [3]}
    env.peg1_body_id, env.peg2_body_id = 2, 4
    env.sim = type("Sim", (), {})()
    env.sim.model = type("Model", (), {"ngeom": 5, "geom_bodyid": np.array([1, 1, 2, 3, 4])})()
    env.sim.data = _Contacts(positions)
    measure.reset(env)
    measure.observe(env, 1)  # no contact yet
    env.sim.data.ncon, env.sim.data.contact.geom = 1, np.array([[2, 1]])  # peg before nut: either order counts
    measure.observe(env, 2)
    positions[1] = [0.0, 0.0, 0.9]
    measure.observe(env, 3)  # only the first contact counts
    values = measure.values()
    assert values["square_nut_insertion_offset_mm"] == pytest.approx(5.0)
    assert values["square_nut_insertion_contact_step"] == 2.0
    assert math.isnan(values["round_nut_insertion_offset_mm"]) and math.isnan(
        values["round_nut_insertion_contact_step"]
    )
    assert values["insertion_offset_mm"] == pytest.approx(5.0) and values["insertion_contact_step"] == 2.0
