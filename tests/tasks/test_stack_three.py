"""StackThree (`carp.tasks.stack_three`): registration in any process that builds it, seeded placement of the third
cube, Stack's object-state layout extended, and the success check on cube poses set directly in the simulator."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carp.tasks import get_task
from carp.tasks.arms import simulation

# robosuite's Stack object-state, in its order (23 values), then what StackThree appends (13).
STACK_OBJECT_KEYS = (
    "cubeA_pos",
    "cubeA_quat",
    "cubeB_pos",
    "cubeB_quat",
    "cubeA_to_cubeB",
    "gripper_to_cubeA",
    "gripper_to_cubeB",
)
THIRD_CUBE_KEYS = ("cubeC_pos", "cubeC_quat", "cubeC_to_cubeA", "gripper_to_cubeC")
# Cubes set into one another by this much, so that MuJoCo reports the contact of cubes resting on each other.
OVERLAP_M = 0.0005
UPRIGHT = Rotation.identity()


@pytest.fixture(scope="module")
def env():
    task = get_task("stack_three")
    env = task.make_env(task.make_env_args("absolute"))
    yield env
    env.close()


def _place(env, cube, center: np.ndarray, rotation: Rotation = UPRIGHT) -> None:
    env.sim.data.set_joint_qpos(cube.joints[0], np.concatenate([center, rotation.as_quat(scalar_first=True)]))


def _tower(env, bottom_center: np.ndarray, down: np.ndarray, rotation: Rotation = UPRIGHT) -> None:
    """B at ``bottom_center``, A on B, C on A, each next one along ``-down`` (unit (3,)), turned by ``rotation``."""
    half = {cube: float(cube.size[2]) for cube in (env.cubeA, env.cubeB, env.cubeC)}
    cube_a = bottom_center - down * (half[env.cubeB] + half[env.cubeA] - OVERLAP_M)
    cube_c = cube_a - down * (half[env.cubeA] + half[env.cubeC] - OVERLAP_M)
    for cube, center in ((env.cubeB, bottom_center), (env.cubeA, cube_a), (env.cubeC, cube_c)):
        _place(env, cube, center, rotation)


def _set_fingers(env, first: float, second: float) -> None:
    robot = env.robots[0]
    env.sim.data.qpos[robot._ref_gripper_joint_pos_indexes["right"]] = [first, second]


def _table_height(env) -> float:
    return float(env.table_offset[2])


@pytest.mark.slow
def test_its_task_registers_stack_three_in_a_process_that_never_imported_it():
    # Evaluation workers and ingestion rebuild the env from stored env_args in fresh processes, through its task.
    script = (
        "import robosuite\n"
        "from robosuite.environments.base import REGISTERED_ENVS\n"
        "from carp.tasks import get_task, task_for_env_args\n"
        "env_args = get_task('stack_three').make_env_args('absolute')\n"
        "assert 'StackThree' not in REGISTERED_ENVS\n"
        "env = task_for_env_args(env_args).make_env(env_args)\n"
        "print(type(env).__name__)\n"
    )
    completed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False)
    assert completed.returncode == 0, completed.stderr
    assert completed.stdout.strip().splitlines()[-1] == "StackThree"


def test_the_third_cube_is_placed_by_the_seed_clear_of_the_other_two(env):
    positions = {}
    for seed in (0, 1, 2, 3, 0):
        simulation.reset_env(env, seed)
        cubes = [env.cubeA, env.cubeB, env.cubeC]
        centers = [np.array(env.sim.data.body_xpos[env.sim.model.body_name2id(cube.root_body)]) for cube in cubes]
        for first in range(3):
            for second in range(first + 1, 3):
                distance = np.linalg.norm(centers[first][:2] - centers[second][:2])
                assert distance > cubes[first].horizontal_radius + cubes[second].horizontal_radius
        if seed in positions:
            np.testing.assert_array_equal(centers[2], positions[seed])
        positions[seed] = centers[2]
    third_cube_moves = [np.abs(positions[seed] - positions[0]).max() for seed in (1, 2, 3)]
    assert min(third_cube_moves) > 1e-2


def test_object_state_is_stacks_layout_then_the_third_cubes_pose_and_offsets(env):
    observation = simulation.reset_env(env, 5)
    expected = np.concatenate([observation[key] for key in STACK_OBJECT_KEYS + THIRD_CUBE_KEYS])
    np.testing.assert_array_equal(observation["object-state"], expected)
    assert observation["object-state"].shape == (get_task("stack_three").object_obs_dim,) == (36,)
    assert [observation[key].shape[0] for key in THIRD_CUBE_KEYS] == [3, 4, 3, 3]
    np.testing.assert_allclose(observation["cubeC_to_cubeA"], observation["cubeA_pos"] - observation["cubeC_pos"])
    np.testing.assert_allclose(
        observation["gripper_to_cubeC"], observation["cubeC_pos"] - observation["robot0_eef_pos"]
    )


def test_a_released_tower_of_three_succeeds_and_two_stacked_do_not(env):
    simulation.reset_env(env, 0)
    up = np.array([0.0, 0.0, 1.0])
    bottom = np.array([0.0, 0.06, _table_height(env) + float(env.cubeB.size[2])])
    _tower(env, bottom, -up)
    env.sim.forward()
    assert env._check_success() and env.reward() == 1.0

    # The same pair, the third cube on the table beside it.
    _place(env, env.cubeC, np.array([0.0, -0.06, _table_height(env) + float(env.cubeC.size[2])]))
    env.sim.forward()
    assert not env._check_success() and env.reward() == 0.0


def test_a_tower_whose_top_cube_the_gripper_holds_or_touches_has_not_succeeded(env):
    simulation.reset_env(env, 0)
    # The tower hangs below the top cube, which sits between the fingertips in the gripper's frame; success does not
    # ask that B rests on the table, only that A rests on B and C on A.
    site = env.robots[0].eef_site_id["right"]
    grip_rotation = Rotation.from_matrix(np.array(env.sim.data.site_xmat[site]).reshape(3, 3))
    down = grip_rotation.apply([0.0, 0.0, 1.0])  # the gripper's approach axis
    top = np.array(env.sim.data.site_xpos[site])
    half_a, half_b, half_c = (float(cube.size[2]) for cube in (env.cubeA, env.cubeB, env.cubeC))
    bottom = top + down * (half_c + 2 * half_a + half_b - 2 * OVERLAP_M)
    _tower(env, bottom, down, grip_rotation)
    gripper = env.robots[0].gripper["right"]
    # Each finger joint at just under the cube's half width presses its pad into the cube's face.
    pressed = float(env.cubeC.size[0]) - OVERLAP_M

    _set_fingers(env, pressed, -pressed)
    env.sim.forward()
    assert env._check_grasp(gripper, env.cubeC)
    assert not env._check_success()

    _set_fingers(env, pressed, -0.04)  # one fingertip rests on the cube, the other is open: no grasp, still touching
    env.sim.forward()
    assert not env._check_grasp(gripper, env.cubeC) and env.check_contact(gripper, env.cubeC)
    assert not env._check_success()

    _set_fingers(env, 0.04, -0.04)
    env.sim.forward()
    assert not env.check_contact(gripper, env.cubeC)
    assert env._check_success()


def test_a_shaped_reward_is_refused():
    env_args = get_task("stack_three").make_env_args("absolute")
    env_args["env_kwargs"]["reward_shaping"] = True
    with pytest.raises(ValueError, match="StackThree has a sparse reward only"):
        get_task("stack_three").make_env(env_args)
