"""Rotation formats for absolute end-effector actions.

robosuite's OSC controller with absolute input takes a 7-D action: world-frame position (3), axis-angle rotation (3)
and gripper (1). The policy learns a 10-D form where the rotation is the continuous 6-D representation (the first
two columns of the rotation matrix, Zhou et al. 2019), because axis-angle jumps at pi. The conversion back
re-orthonormalizes the two columns (Gram-Schmidt), so any network output maps to a valid rotation.
"""

import numpy as np

ABSOLUTE_ACTION_DIM = 7
ROT6D_ACTION_DIM = 10


def axis_angle_to_rot6d(axis_angle: np.ndarray) -> np.ndarray:
    """Convert axis-angle vectors (..., 3) to 6-D rotations (..., 6): column 0 then column 1 of the matrix."""
    from scipy.spatial.transform import Rotation  # imported here: the task registry reads this module's constants

    batch_shape = axis_angle.shape[:-1]
    matrices = Rotation.from_rotvec(axis_angle.reshape(-1, 3)).as_matrix()  # (N, 3, 3)
    rot6d = np.concatenate([matrices[:, :, 0], matrices[:, :, 1]], axis=-1)  # (N, 6)
    return rot6d.reshape(*batch_shape, 6)


def rot6d_to_matrix(rot6d: np.ndarray) -> np.ndarray:
    """Gram-Schmidt two (possibly non-orthonormal) columns (..., 6) into rotation matrices (..., 3, 3)."""
    first, second = rot6d[..., :3], rot6d[..., 3:]
    x_axis = first / np.linalg.norm(first, axis=-1, keepdims=True).clip(min=1e-12)
    second = second - np.sum(x_axis * second, axis=-1, keepdims=True) * x_axis
    y_axis = second / np.linalg.norm(second, axis=-1, keepdims=True).clip(min=1e-12)
    z_axis = np.cross(x_axis, y_axis)
    return np.stack([x_axis, y_axis, z_axis], axis=-1)


def rot6d_to_axis_angle(rot6d: np.ndarray) -> np.ndarray:
    """Convert 6-D rotations (..., 6) back to axis-angle vectors (..., 3)."""
    from scipy.spatial.transform import Rotation

    batch_shape = rot6d.shape[:-1]
    matrices = rot6d_to_matrix(rot6d.reshape(-1, 6).astype(np.float64))
    return Rotation.from_matrix(matrices).as_rotvec().reshape(*batch_shape, 3)


def absolute_to_rot6d_actions(actions: np.ndarray) -> np.ndarray:
    """Map absolute 7-D actions (..., 7) = (pos, axis-angle, gripper) to 10-D (..., 10) = (pos, rot6d, gripper)."""
    if actions.shape[-1] != ABSOLUTE_ACTION_DIM:
        raise ValueError(f"expected absolute actions of width 7, got width {actions.shape[-1]}")
    rot6d = axis_angle_to_rot6d(actions[..., 3:6].astype(np.float64))
    return np.concatenate([actions[..., :3], rot6d, actions[..., 6:]], axis=-1)


def rot6d_to_absolute_actions(actions: np.ndarray) -> np.ndarray:
    """Map 10-D actions (..., 10) back to the 7-D absolute actions (..., 7) the controller executes."""
    if actions.shape[-1] != ROT6D_ACTION_DIM:
        raise ValueError(f"expected rot6d actions of width 10, got width {actions.shape[-1]}")
    axis_angle = rot6d_to_axis_angle(actions[..., 3:9])
    return np.concatenate([actions[..., :3], axis_angle, actions[..., 9:]], axis=-1)
