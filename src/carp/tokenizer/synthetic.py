"""Synthetic pick-and-place-like action trajectories for tokenizer tests, benchmarks and sizing.

Scripted robomimic experts move through phases (approach, descend, grasp, lift, carry, release) with smooth pose
targets and a binary gripper. These episodes imitate that: every dimension follows minimum-jerk segments between
random waypoints that share the phase boundaries, the gripper toggles between -1 and 1 at grasp and release, and for
A = 10 the rotation dimensions are the 6-D rotation (first two matrix columns) of a slowly turning, mostly downward
gripper, so they stay coupled and on the unit sphere like real absolute actions.
"""

import numpy as np

GRASP_PHASE = 2
RELEASE_PHASE = 5
NUM_PHASES = 7
ROT6D_ACTION_DIM = 10


def _minimum_jerk(progress: np.ndarray) -> np.ndarray:
    return progress**3 * (10 - 15 * progress + 6 * progress**2)


def _piecewise_smooth(waypoints: np.ndarray, durations: np.ndarray) -> np.ndarray:
    """Join (P + 1, F) waypoints with P minimum-jerk segments of the given step counts, giving (sum(durations), F)."""
    segments = []
    for index, steps in enumerate(durations):
        progress = _minimum_jerk(np.arange(steps) / steps)[:, None]
        segments.append(waypoints[index] + progress * (waypoints[index + 1] - waypoints[index]))
    return np.concatenate(segments)


def _rot6d_from_euler(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """First two columns of R = Rz(yaw) Ry(pitch) Rx(roll) @ diag(1, -1, -1) (a gripper pointing down), (T, 6)."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    column_x = np.stack([cy * cp, sy * cp, -sp], axis=-1)
    column_y = np.stack([cy * sp * sr - sy * cr, sy * sp * sr + cy * cr, cp * sr], axis=-1)
    # Flipping the y axis (and z) turns the identity into a downward-facing gripper frame.
    return np.concatenate([column_x, -column_y], axis=-1)


def synthetic_action_episodes(
    num_episodes: int, action_dim: int = ROT6D_ACTION_DIM, seed: int = 0, noise_scale: float = 0.0
) -> list[np.ndarray]:
    """Generate raw (un-normalized) action episodes.

    Args:
        num_episodes: number of episodes.
        action_dim: A; 10 gives (position 3, rotation 6-D, gripper), any other A gives A - 1 smooth dimensions
            and a gripper.
        seed: numpy seed.
        noise_scale: standard deviation of white noise added to the smooth dimensions (not the gripper).

    Returns:
        Episodes as float32 arrays (T_e, A), T_e between roughly 90 and 180 steps.
    """
    rng = np.random.default_rng(seed)
    episodes = []
    for _ in range(num_episodes):
        durations = rng.integers(10, 28, size=NUM_PHASES)
        gripper = np.concatenate(
            [
                np.full(durations[phase], 1.0 if GRASP_PHASE <= phase < RELEASE_PHASE else -1.0)
                for phase in range(NUM_PHASES)
            ]
        )[:, None]
        if action_dim == ROT6D_ACTION_DIM:
            position_waypoints = rng.uniform(-0.25, 0.25, size=(NUM_PHASES + 1, 3)) + np.array([0.0, 0.0, 1.0])
            # Grasp and release happen low, with the gripper parked between those two phases.
            position_waypoints[GRASP_PHASE : GRASP_PHASE + 2, 2] = 0.83 + rng.uniform(0, 0.02)
            position_waypoints[RELEASE_PHASE : RELEASE_PHASE + 2, 2] = 0.9 + rng.uniform(0, 0.05)
            positions = _piecewise_smooth(position_waypoints, durations)
            angles = _piecewise_smooth(
                np.stack(
                    [
                        rng.normal(0, 0.05, NUM_PHASES + 1),
                        rng.normal(0, 0.05, NUM_PHASES + 1),
                        rng.uniform(-np.pi / 2, np.pi / 2, NUM_PHASES + 1),
                    ],
                    axis=-1,
                ),
                durations,
            )
            smooth = np.concatenate([positions, _rot6d_from_euler(*angles.T)], axis=-1)
        else:
            smooth = _piecewise_smooth(rng.uniform(-1, 1, size=(NUM_PHASES + 1, action_dim - 1)), durations)
        smooth = smooth + rng.normal(0, noise_scale, size=smooth.shape) if noise_scale > 0 else smooth
        episodes.append(np.concatenate([smooth, gripper], axis=-1).astype(np.float32))
    return episodes


def sliding_windows(episodes: list[np.ndarray], horizon: int, pad_before: int = 1, pad_after: int = 7) -> np.ndarray:
    """All windows of `horizon` steps of each episode with stride 1, edge-padded like the replay buffer's windows.

    Args:
        episodes: arrays (T_e, A).
        horizon: H.
        pad_before: steps a window may start before an episode (To - 1).
        pad_after: steps a window may run past an episode's end (Ta - 1).

    Returns:
        (N, H, A) float32 windows.
    """
    windows = []
    for episode in episodes:
        padded = np.concatenate(
            [np.repeat(episode[:1], pad_before, axis=0), episode, np.repeat(episode[-1:], pad_after, axis=0)]
        )
        starts = np.arange(len(padded) - horizon + 1)
        windows.append(padded[starts[:, None] + np.arange(horizon)[None, :]])
    return np.concatenate(windows).astype(np.float32)


def min_max_bounds(windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension (A,) minimum and maximum of (N, H, A) windows, the statistics of [-1, 1] normalization."""
    flat = windows.reshape(-1, windows.shape[-1])
    return flat.min(axis=0), flat.max(axis=0)
