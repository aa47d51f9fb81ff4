"""Threading (`carp.tasks.threading`): registration in any process that builds it, seeded placement of the needle and
the tripod, the object-state layout, the success check and the insertion offset on needle poses set directly in the
simulator, and the scripted expert's demos on fixed seeds."""

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carp.data.collect import collect_demonstrations
from carp.data.robomimic_io import read_demonstrations
from carp.tasks import get_task, task_for_env_args
from carp.tasks.arms import simulation
from carp.tasks.arms.insertion_offset import InsertionOffset
from carp.tasks.threading.env import RING_HALF_DEPTH_M, RING_INNER_RADIUS_M
from carp.tasks.threading.insertion import THREADING_PAIRS
from tests.conftest import OBS_KEYS

OBJECT_KEYS = (
    "needle_pos",
    "needle_quat",
    "ring_pos",
    "ring_quat",
    "needle_tip_to_ring",
    "gripper_to_needle",
    "gripper_to_ring",
)
OBJECT_KEY_WIDTHS = (3, 4, 3, 4, 3, 3, 3)


@pytest.fixture(scope="module")
def task():
    return get_task("threading")


@pytest.fixture(scope="module")
def env(task):
    env = task.make_env(task.make_env_args("absolute"))
    yield env
    env.close()


def _ring_frame(env) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ring's centre, its axis, its horizontal side direction and its upward direction, each (3,)."""
    axis = env.ring_axis()
    up = np.array([0.0, 0.0, 1.0])
    return env.ring_center(), axis, np.cross(up, axis), up


def _place_needle(env, tip: np.ndarray, direction: np.ndarray) -> None:
    """Put the needle's tip at ``tip`` (3,), its axis along the unit ``direction`` (3,), unrolled; update contacts."""
    yaw = math.atan2(direction[1], direction[0])
    pitch = -math.asin(float(np.clip(direction[2], -1.0, 1.0)))
    rotation = Rotation.from_euler("ZY", [yaw, pitch])
    center = tip - env.needle.tip_m * rotation.apply([1.0, 0.0, 0.0])
    env.sim.data.set_joint_qpos(env.needle.joints[0], np.concatenate([center, rotation.as_quat(scalar_first=True)]))
    env.sim.forward()


def _needle_on_axis(
    env, depth_m: float, offset_m: tuple[float, float] = (0.0, 0.0), direction_sign: float = 1.0
) -> None:
    """The needle along the ring's axis, its tip ``depth_m`` past the ring's mid-plane (negative: in front of it) and
    ``offset_m`` (side, up) off the axis, coming from the front (``direction_sign`` 1) or from behind (-1)."""
    center, axis, side, up = _ring_frame(env)
    tip = center + direction_sign * depth_m * axis + offset_m[0] * side + offset_m[1] * up
    _place_needle(env, tip, direction_sign * axis)


@pytest.mark.slow
def test_its_task_registers_threading_in_a_process_that_never_imported_it():
    # Evaluation workers and ingestion rebuild the env from stored env_args in fresh processes, through its task.
    script = (
        "import robosuite\n"
        "from robosuite.environments.base import REGISTERED_ENVS\n"
        "from carp.tasks import get_task, task_for_env_args\n"
        "env_args = get_task('threading').make_env_args('absolute')\n"
        "assert 'Threading' not in REGISTERED_ENVS\n"
        "env = task_for_env_args(env_args).make_env(env_args)\n"
        "print(type(env).__name__)\n"
    )
    completed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False)
    assert completed.returncode == 0, completed.stderr
    assert completed.stdout.strip().splitlines()[-1] == "Threading"


def test_threading_is_found_by_the_env_args_it_writes(task):
    assert task.env_name == "Threading"
    assert task_for_env_args(task.make_env_args("delta")) is task
    assert task.controller_of(task.make_env_args("delta")) == "delta"
    assert task.default_max_steps == 400


def test_reset_is_a_function_of_the_seed_only(task, env):
    first = task.observations(task.reset(env, 7))
    first_state = task.simulator_state(env)
    first_ring = env.ring_center()
    other = task.observations(task.reset(env, 8))
    other_ring = env.ring_center()
    again = task.observations(task.reset(env, 7))
    np.testing.assert_array_equal(first_state, task.simulator_state(env))
    np.testing.assert_array_equal(first["object"], again["object"])
    np.testing.assert_array_equal(first_ring, env.ring_center())
    # Another seed places the objects elsewhere and moves the fixed tripod (centimetres, not rounding).
    assert np.abs(first["object"] - other["object"]).max() > 1e-2
    assert np.abs(first_ring - other_ring).max() > 1e-2
    assert not task.is_success(env)


def test_the_tripod_and_the_needle_stay_in_their_regions_and_apart(env):
    for seed in range(8):
        simulation.reset_env(env, seed)
        table = env.table_offset
        ring, axis = env.ring_center(), env.ring_axis()
        assert 0.10 <= ring[0] - table[0] <= 0.16 and 0.06 <= ring[1] - table[1] <= 0.14
        assert ring[2] - table[2] == pytest.approx(0.11)
        assert axis[2] == pytest.approx(0.0, abs=1e-9) and abs(math.atan2(axis[1], axis[0])) <= math.pi / 6 + 1e-9
        needle = env.sim.data.body_xpos[env.needle_body_id]
        assert -0.12 <= needle[0] - table[0] <= -0.02 and -0.20 <= needle[1] - table[1] <= -0.12
        needle_axis = env.needle_axis()
        assert abs(math.atan2(needle_axis[1], needle_axis[0])) <= math.pi / 3 + 1e-3
        assert not env.check_contact(env.needle, env.tripod)


def test_object_state_is_the_needles_and_the_rings_poses_then_the_offsets(task, env):
    observation = simulation.reset_env(env, 5)
    expected = np.concatenate([observation[key] for key in OBJECT_KEYS])
    np.testing.assert_array_equal(observation["object-state"], expected)
    assert observation["object-state"].shape == (get_task("threading").object_obs_dim,) == (23,)
    assert tuple(observation[key].shape[0] for key in OBJECT_KEYS) == OBJECT_KEY_WIDTHS
    np.testing.assert_allclose(observation["ring_pos"], env.ring_center())
    np.testing.assert_allclose(observation["needle_tip_to_ring"], env.ring_center() - env.needle_tip())
    np.testing.assert_allclose(
        observation["gripper_to_needle"], observation["needle_pos"] - observation["robot0_eef_pos"]
    )
    np.testing.assert_allclose(observation["gripper_to_ring"], observation["ring_pos"] - observation["robot0_eef_pos"])
    features = task.observations(observation)
    assert {key: features[key].shape for key in OBS_KEYS} == {
        "object": (23,),
        "robot0_eef_pos": (3,),
        "robot0_eef_quat": (4,),
        "robot0_gripper_qpos": (2,),
    }


def test_a_tip_through_the_ring_succeeds_from_either_side(env):
    simulation.reset_env(env, 0)
    _needle_on_axis(env, 0.02)
    assert env._check_success() and env.reward() == 1.0
    # Off the axis but with the bar inside the hole (4 mm half width, 20 mm inner radius).
    _needle_on_axis(env, 0.02, (0.008, -0.010))
    assert env._check_success()
    _needle_on_axis(env, 0.02, direction_sign=-1.0)
    assert env._check_success()


@pytest.mark.parametrize(
    ("depth_m", "offset_m", "why"),
    [
        (-0.01, (0.0, 0.0), "the tip stops in front of the ring"),
        (RING_HALF_DEPTH_M - 0.002, (0.0, 0.0), "the tip is inside the ring, short of its far face"),
        (0.02, (0.0, RING_INNER_RADIUS_M + 0.002), "the tip passes through the ring's wall"),
        (0.02, (0.045, 0.0), "the tip passes beside the ring"),
    ],
)
def test_a_tip_short_of_the_ring_or_outside_its_hole_does_not_succeed(env, depth_m, offset_m, why):
    simulation.reset_env(env, 0)
    _needle_on_axis(env, depth_m, offset_m)
    assert not env._check_success(), why
    assert env.reward() == 0.0


def test_a_needle_past_the_ring_that_never_crossed_its_hole_does_not_succeed(env):
    simulation.reset_env(env, 0)
    center, axis, _, up = _ring_frame(env)
    # The tip 2 cm past the ring's plane and on its axis, but the bar comes down steeply from above the ring: it
    # crosses the plane 5 cm above the centre, above the ring (30 mm outer radius).
    base = center - 0.02 * axis + 0.10 * up
    tip = center + 0.02 * axis
    _place_needle(env, tip, (tip - base) / np.linalg.norm(tip - base))
    assert not env._check_success()


def test_a_shaped_reward_is_refused():
    env_args = get_task("threading").make_env_args("absolute")
    env_args["env_kwargs"]["reward_shaping"] = True
    with pytest.raises(ValueError, match="Threading has a sparse reward only"):
        get_task("threading").make_env(env_args)


@pytest.mark.parametrize(
    "offset_m",
    [(0.0, 0.019), (0.012, -0.014)],
    ids=["above the axis", "to the side and below"],
)
def test_the_insertion_offset_is_where_the_needle_meets_the_ring_plane_at_first_contact(task, env, offset_m):
    measure = task.measure()
    assert isinstance(measure, InsertionOffset) and measure.pairs == THREADING_PAIRS
    simulation.reset_env(env, 0)
    measure.reset(env)
    # The bar (4 mm half width) this far off the axis overlaps the ring's wall (20 to 30 mm from the axis).
    _needle_on_axis(env, -0.03, offset_m)
    measure.observe(env, 1)
    assert math.isnan(measure.values()["insertion_offset_mm"])
    _needle_on_axis(env, -0.003, offset_m)  # the tip 2 mm into the ring's front face
    assert env.check_contact(env.needle, env.tripod)
    measure.observe(env, 2)
    _needle_on_axis(env, 0.01, (0.0, 0.0))
    measure.observe(env, 3)  # only the first contact counts
    values = measure.values()
    assert values["insertion_offset_mm"] == pytest.approx(1000.0 * math.hypot(*offset_m), abs=1e-6)
    assert values["insertion_contact_step"] == 2.0


def test_a_needle_touching_only_a_leg_has_no_insertion_offset(task, env):
    measure = task.measure()
    simulation.reset_env(env, 0)
    measure.reset(env)
    leg = env.sim.model.geom_name2id(env.tripod.naming_prefix + "leg0")
    # The tip in the middle of the leg behind the ring, the bar under the ring along its axis.
    _place_needle(env, np.array(env.sim.data.geom_xpos[leg]), env.ring_axis())
    assert env.check_contact(env.needle, env.tripod)
    measure.observe(env, 1)
    assert math.isnan(measure.values()["insertion_offset_mm"])


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["absolute", "delta"])
def test_the_expert_threads_the_needle_on_fixed_seeds_and_its_demos_pass_the_schema(tmp_path, controller):
    path = tmp_path / "threading.hdf5"
    seeds = 2
    # As many attempts as demos: every seed must succeed, within a step limit well under the evaluation's.
    summary = collect_demonstrations(
        "threading", seeds, path, seed=11, controller=controller, max_steps=160, max_attempts=seeds
    )
    assert summary.kept == seeds and summary.seeds == [11, 12]
    demos = read_demonstrations(path, OBS_KEYS, action_dim=7, env_name="Threading")
    assert simulation.controller_kind(demos.env_args) == controller
    for episode in demos.episodes:
        assert episode.obs["object"].shape == (episode.length, get_task("threading").object_obs_dim)
        assert episode.dones[-1] == 1 and episode.dones[:-1].sum() == 0
        assert set(np.unique(episode.actions[:, 6])) == {-1.0, 1.0}  # open at the start, closed on the handle
        if controller == "delta":
            assert np.abs(episode.actions[:, :6]).max() <= 1.0
        else:
            # Bounded commanded motion per control step keeps demonstrations smooth.
            assert np.linalg.norm(np.diff(episode.actions[:, :3], axis=0), axis=1).max() <= 0.0161
