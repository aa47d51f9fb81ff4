import json

import numpy as np
import pytest

from carp.tasks import get_task
from carp.tasks.arms import simulation


def test_absolute_env_args_set_world_frame_absolute_arm_input():
    env_args = get_task("square").make_env_args("absolute")
    arm = env_args["env_kwargs"]["controller_configs"]["body_parts"]["right"]
    assert env_args["env_name"] == "NutAssemblySquare"
    assert env_args["type"] == 1
    assert (arm["type"], arm["input_type"], arm["input_ref_frame"]) == ("OSC_POSE", "absolute", "world")
    assert json.loads(json.dumps(env_args)) == env_args
    kwargs = env_args["env_kwargs"]
    assert kwargs["robots"] == "Panda" and kwargs["control_freq"] == 20 and kwargs["ignore_done"] is True
    assert not kwargs["use_camera_obs"] and not kwargs["has_offscreen_renderer"] and not kwargs["reward_shaping"]
    assert simulation.controller_kind(env_args) == "absolute"


def test_delta_env_args_keep_default_delta_osc():
    env_args = get_task("can").make_env_args("delta")
    arm = env_args["env_kwargs"]["controller_configs"]["body_parts"]["right"]
    assert env_args["env_name"] == "PickPlaceCan"
    assert arm["input_type"] == "delta" and arm["input_ref_frame"] == "base"
    assert simulation.controller_kind(env_args) == "delta"


def test_controller_kind_reads_robosuite_1_4_part_configs():
    env_args = {"env_kwargs": {"controller_configs": {"type": "OSC_POSE", "control_delta": False}}}
    assert simulation.controller_kind(env_args) == "absolute"


@pytest.mark.parametrize(
    ("task", "controller", "message"),
    [("peg_in_hole", "absolute", "unknown task 'peg_in_hole'"), ("lift", "joint", "unknown controller 'joint'")],
)
def test_make_env_args_rejects_unknown_values(task, controller, message):
    with pytest.raises(ValueError, match=message):
        get_task(task).make_env_args(controller)


def test_low_dim_observations_skip_images_and_use_robomimic_object_key():
    obs = {
        "object-state": np.arange(10, dtype=np.float32),
        "robot0_eef_pos": np.ones(3),
        "agentview_image": np.zeros((84, 84, 3), dtype=np.uint8),
        "robot0_eye_in_hand_depth": np.zeros((84, 84, 1)),
    }
    features = simulation.low_dim_observations(obs)
    assert sorted(features) == ["object", "robot0_eef_pos"]
    assert features["object"].dtype == np.float64 and features["object"].shape == (10,)


@pytest.fixture(scope="module")
def lift_env():
    env = simulation.make_env(get_task("lift").make_env_args("absolute"))
    yield env
    env.close()


def test_reset_is_reproducible_per_seed(lift_env):
    first = simulation.low_dim_observations(simulation.reset_env(lift_env, 7))
    first_state = lift_env.sim.get_state().flatten()
    other = simulation.low_dim_observations(simulation.reset_env(lift_env, 8))
    again = simulation.low_dim_observations(simulation.reset_env(lift_env, 7))
    np.testing.assert_array_equal(first["cube_pos"], again["cube_pos"])
    np.testing.assert_array_equal(first["robot0_joint_pos"], again["robot0_joint_pos"])
    np.testing.assert_array_equal(first_state, lift_env.sim.get_state().flatten())
    assert np.linalg.norm(first["cube_pos"][:2] - other["cube_pos"][:2]) > 1e-4


def test_lift_observations_match_design_dims(lift_env):
    features = simulation.low_dim_observations(simulation.reset_env(lift_env, 0))
    widths = {key: features[key].shape[0] for key in ("object", "robot0_eef_pos", "robot0_eef_quat")}
    assert widths == {"object": get_task("lift").object_obs_dim, "robot0_eef_pos": 3, "robot0_eef_quat": 4}
    low_dim = sum(features[key].shape[0] for key in ("object", "robot0_eef_pos", "robot0_eef_quat"))
    assert low_dim + features["robot0_gripper_qpos"].shape[0] == get_task("lift").low_dim_obs_dim == 19
    assert not simulation.is_success(lift_env)


def test_absolute_action_at_current_pose_holds_still(lift_env):
    from scipy.spatial.transform import Rotation

    obs = simulation.reset_env(lift_env, 3)
    site_id = lift_env.robots[0].eef_site_id["right"]
    position = np.array(lift_env.sim.data.site_xpos[site_id])
    rotation = Rotation.from_matrix(np.array(lift_env.sim.data.site_xmat[site_id]).reshape(3, 3))
    np.testing.assert_allclose(obs["robot0_eef_pos"], position)
    for _ in range(5):
        obs, _, _, _ = lift_env.step(np.concatenate([position, rotation.as_rotvec(), [-1.0]]))
    np.testing.assert_allclose(obs["robot0_eef_pos"], position, atol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["can", "square"])
def test_object_observation_dims(task):
    env = simulation.make_env(get_task(task).make_env_args("delta"))
    try:
        features = simulation.low_dim_observations(simulation.reset_env(env, 0))
    finally:
        env.close()
    assert features["object"].shape == (get_task(task).object_obs_dim,)
