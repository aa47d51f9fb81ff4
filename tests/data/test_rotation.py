import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carp.data.rotation import (
    absolute_to_rot6d_actions,
    axis_angle_to_rot6d,
    rot6d_to_absolute_actions,
    rot6d_to_matrix,
)


def test_absolute_actions_round_trip_within_1e6():
    rng = np.random.default_rng(0)
    axis_angle = Rotation.random(500, random_state=1).as_rotvec()  # canonical: angle in [0, pi]
    actions = np.concatenate([rng.normal(size=(500, 3)), axis_angle, rng.choice([-1.0, 1.0], size=(500, 1))], axis=1)
    converted = absolute_to_rot6d_actions(actions)
    assert converted.shape == (500, 10)
    np.testing.assert_allclose(rot6d_to_absolute_actions(converted), actions, atol=1e-6)


def test_rot6d_columns_are_the_rotation_matrix_columns():
    rotation = Rotation.from_euler("xyz", [0.3, -1.1, 2.0])
    rot6d = axis_angle_to_rot6d(rotation.as_rotvec())
    matrix = rotation.as_matrix()
    np.testing.assert_allclose(rot6d, np.concatenate([matrix[:, 0], matrix[:, 1]]), atol=1e-12)


def test_noisy_rot6d_maps_to_a_valid_rotation():
    rng = np.random.default_rng(3)
    matrices = rot6d_to_matrix(rng.normal(size=(50, 6)))
    identity = np.broadcast_to(np.eye(3), (50, 3, 3))
    np.testing.assert_allclose(matrices.transpose(0, 2, 1) @ matrices, identity, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(matrices), 1.0, atol=1e-9)


def test_wrong_widths_are_refused():
    with pytest.raises(ValueError, match="width 7, got width 6"):
        absolute_to_rot6d_actions(np.zeros((2, 6)))
    with pytest.raises(ValueError, match="width 10, got width 7"):
        rot6d_to_absolute_actions(np.zeros((2, 7)))
