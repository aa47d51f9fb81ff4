import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carp.data.rotation import absolute_to_rot6d_actions, rot6d_to_absolute_actions
from carp.tasks import TASK_NAMES, get_task
from carp.tasks.arms import expert as experts
from carp.tasks.arms import simulation
from carp.tasks.arms.task import RobosuiteArmTask
from carp.tasks.square.expert import SquareExpert


@pytest.mark.parametrize("yaw", np.linspace(-math.pi, math.pi, 73))
def test_gripper_rotation_points_down_with_closing_axis_at_yaw(yaw):
    matrix = experts.gripper_rotation(yaw).as_matrix()
    closing_axis, approach_axis = matrix[:, 0], matrix[:, 2]
    assert approach_axis[2] < -0.999
    closing_yaw = math.atan2(closing_axis[1], closing_axis[0])
    assert abs(experts.wrap_angle(closing_yaw - yaw)) < experts.GRIPPER_TILT_RAD


def test_commanded_rotations_stay_clear_of_pi_and_round_trip_exactly_through_rot6d():
    # Every yaw an expert commands lies within 135 degrees of home.
    yaws = experts.HOME_YAW_RAD + np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 541)
    rotation_vectors = np.stack([experts.gripper_rotation(yaw).as_rotvec() for yaw in yaws])
    angles = np.linalg.norm(rotation_vectors, axis=1)
    assert math.pi - angles.max() > 0.01
    actions = np.concatenate([np.zeros((len(yaws), 3)), rotation_vectors, np.ones((len(yaws), 1))], axis=1)
    np.testing.assert_allclose(rot6d_to_absolute_actions(absolute_to_rot6d_actions(actions)), actions, atol=1e-9)


def test_home_rotation_matches_the_panda_reset_pose_within_ten_degrees():
    # Panda's reset grip-site orientation: closing axis along +y, pointing down with a small forward tilt.
    home = Rotation.from_matrix([[0.0, 0.99, 0.139], [1.0, 0.0, 0.002], [0.003, 0.139, -0.99]])
    error = (experts.gripper_rotation(experts.HOME_YAW_RAD) * home.inv()).magnitude()
    assert error < math.radians(10)


def test_angle_helpers():
    assert experts.wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert experts.wrap_angle_period(math.radians(100), math.pi / 2) == pytest.approx(math.radians(10))
    assert experts.nearest_symmetric_yaw(math.radians(10), math.pi / 2, math.pi / 2) == pytest.approx(math.radians(100))
    quaternion = Rotation.from_euler("z", 0.7).as_quat()
    assert experts.yaw_of(quaternion) == pytest.approx(0.7)


@pytest.mark.parametrize(
    ("start", "end"),
    [(math.radians(225), math.radians(27)), (math.radians(-40), math.radians(200)), (0.3, 1.9), (2.0, 3.9)],
)
def test_yaw_turns_keep_to_the_home_side(start, end):
    # Whatever the shorter way round, the commanded yaw never passes the direction opposite home (-pi/2), where the
    # wrist's last joint runs out of range: every leg is under 180 degrees and stays on home's side.
    commanded = SimpleNamespace(command_rotation=experts.gripper_rotation(start))
    path = experts.ScriptedExpert._yaw_path(commanded, end)
    assert path[-1] == end
    legs = zip([start, *path[:-1]], path, strict=True)
    for leg_start, leg_end in legs:
        turn = experts.wrap_angle(leg_end - leg_start)
        for fraction in np.linspace(0.0, 1.0, 50):
            yaw = leg_start + fraction * turn
            assert abs(experts.wrap_angle(yaw - experts.HOME_YAW_RAD)) < math.pi - 0.1
    # A turn that stays on home's side the shorter way takes no detour.
    home = experts.HOME_YAW_RAD
    assert (len(path) == 1) == (abs(experts.wrap_angle(end - home) - experts.wrap_angle(start - home)) < math.pi)


@pytest.mark.parametrize("handle_yaw", np.linspace(-math.pi, math.pi, 37))
def test_square_plan_keeps_handle_towards_robot_and_gripper_near_home(handle_yaw):
    target = min(
        SquareExpert.handle_yaw_options,
        key=lambda option: abs(experts.wrap_angle(option - handle_yaw)),
    )
    turn = experts.wrap_angle(target - handle_yaw)
    grasp_yaw = SquareExpert._grasp_yaw(handle_yaw, turn)
    assert abs(turn) <= math.pi / 2 + 1e-9
    # The handle never ends up pointing away from the robot (+x).
    assert math.cos(target) < 0.5
    # Closing axis across the handle.
    assert abs(math.cos(grasp_yaw - handle_yaw)) < 1e-9
    for yaw in (grasp_yaw, grasp_yaw + turn):
        assert abs(yaw - experts.HOME_YAW_RAD) <= math.radians(135) + 1e-9


def test_every_arm_task_names_a_scripted_expert_of_its_own():
    arm_tasks = [get_task(name) for name in TASK_NAMES if isinstance(get_task(name), RobosuiteArmTask)]
    assert len(arm_tasks) == 7
    for task in arm_tasks:
        assert task.expert_name == f"{task.name}_scripted"


def run_expert(task: str, controller: str, seeds) -> list[tuple[bool, int, np.ndarray]]:
    task_spec = get_task(task)
    env = task_spec.make_env(task_spec.make_env_args(controller))
    results = []
    try:
        for seed in seeds:
            simulation.reset_env(env, seed)
            expert = task_spec.make_expert(env, seed)
            actions = []
            success = False
            for _ in range(400):
                actions.append(expert.act())
                env.step(actions[-1])
                if simulation.is_success(env):
                    success = True
                    break
            results.append((success, len(actions), np.stack(actions)))
    finally:
        env.close()
    return results


@pytest.mark.slow
@pytest.mark.parametrize(
    ("task", "controller", "max_steps"),
    [("lift", "absolute", 80), ("lift", "delta", 80), ("can", "absolute", 250), ("square", "absolute", 200)],
)
def test_expert_succeeds_on_seeded_episodes(task, controller, max_steps):
    results = run_expert(task, controller, seeds=(11, 12, 13))
    assert [success for success, _, _ in results] == [True, True, True]
    assert max(steps for _, steps, _ in results) <= max_steps
    for _, _, actions in results:
        assert actions.shape[1] == 7
        assert set(np.unique(actions[:, 6])) <= {-1.0, 1.0}
        if controller == "absolute":
            assert np.linalg.norm(actions[:, 3:6], axis=1).max() <= math.pi
            # Bounded commanded motion per control step keeps demonstrations smooth.
            assert np.linalg.norm(np.diff(actions[:, :3], axis=0), axis=1).max() <= 0.0161
        else:
            assert np.abs(actions[:, :6]).max() <= 1.0


@pytest.mark.slow
def test_expert_is_deterministic_given_the_seed():
    first, second = run_expert("lift", "absolute", seeds=(21, 21))
    np.testing.assert_array_equal(first[2], second[2])
