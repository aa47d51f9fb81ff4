"""Push-T from Diffusion Policy's human demonstrations as LeRobot publishes them (``lerobot/pusht_keypoints``).

LeRobot's dataset holds, per frame at 10 fps, ``observation.state`` (2: the agent position),
``observation.environment_state`` (16: the T block's 8 polygon vertices, x, y each), ``action`` (2: the agent target)
and ``next.reward``, ``next.done``, ``next.success``. LeRobot's converter (``pusht_zarr_format.py``, its keypoint
variant) computed the vertices from DP's recorded state: per frame, gym-pusht's ``PushTEnv.add_tee(space, (block x,
y), angle)`` places the T (its angle set before its position, so the body's origin is the recorded position) and
``PushTEnv.get_keypoints(block_shapes)`` lists each rectangle's pymunk vertices, turned by the body's angle and moved
by its position: the crossbar's four corners, then the stem's. The image version ``lerobot/pusht`` has only
``observation.image`` and the agent position, no block pose, so it cannot be read for carp's state-based Push-T.

carp's Push-T observes DP's 9 block keypoints and the agent position (`carp.tasks.pusht.env`), so
:class:`PushTKeypoints` inverts gym-pusht's vertex function: per frame, the rigid 2-D fit (rotation and translation,
no scale, no reflection) of the 8 observed vertices to the vertices gym-pusht gives at pose (0, 0, 0), computed with
gym-pusht's own code so their order is the dataset's. Its residual, the largest distance between an observed vertex
and the fitted one, is at most :data:`FIT_TOLERANCE_PX` for vertices of a rigid T stored in float32; a larger one is
refused. From the pose it writes ``block_keypoints`` (18) and ``agent_pos`` (2) and the 5-D simulator state, the block
angle wrapped to [0, 2 pi) as gym-pusht's and DP's state observations give it. The Push-T task offers it to the
LeRobot reader (`carp.data.lerobot.derived`), which uses it when a dataset lacks those keys.

:func:`replay_episode` checks a dataset against carp's environment: it resets Push-T to an episode's first state and
runs its recorded actions open loop, and :func:`check_replay` compares the reward reached with ``next.reward``.
Coordinates are pixels of the 512 x 512 workspace, angles radians.
"""

import functools
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from carp.data.lerobot.derived import DerivedFeatures
from carp.data.robomimic_schema import DatasetError
from carp.tasks.pusht import env as pusht_env

ENVIRONMENT_STATE = "observation.environment_state"
"""The feature holding the T's 8 polygon vertices, (T, 16) as x0, y0, ..., x7, y7 in workspace pixels."""
AGENT_STATE = "observation.state"
"""The feature holding the agent position, (T, 2) in workspace pixels."""
VERTICES = 8
FIT_TOLERANCE_PX = 0.01
"""Largest fit residual accepted, in pixels: float32 storage of coordinates below 512 rounds by about 3e-5 px."""
LAYOUT = (
    "lerobot/pusht_keypoints' features observation.environment_state (16, the T's polygon vertices) and "
    "observation.state (2, the agent position); the image version lerobot/pusht holds no block pose"
)
REPLAY_TOLERANCE = 0.01
"""How far below the recorded reward a replay may end and still count as reaching it (rewards in [0, 1])."""


@functools.cache
def block_vertices() -> np.ndarray:
    """(8, 2) float64: gym-pusht's T vertices (``PushTEnv.get_keypoints``) with the block at pose (0, 0, 0).

    Computed with gym-pusht's own ``add_tee`` and ``get_keypoints``, so the order is that of LeRobot's
    ``observation.environment_state``: pymunk's vertex order of the crossbar, then of the stem.
    """
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pymunk
    from gym_pusht.envs.pusht import PushTEnv

    _, shapes = PushTEnv.add_tee(pymunk.Space(), (0, 0), 0)
    vertices = np.asarray(PushTEnv.get_keypoints(shapes), dtype=np.float64)
    vertices.flags.writeable = False
    return vertices


def vertices_in_workspace(block_pose: np.ndarray) -> np.ndarray:
    """(8, 2) where gym-pusht's vertices are with the block's frame at ``block_pose`` (3,): x, y, angle."""
    x, y, angle = (float(value) for value in block_pose)
    return block_vertices() @ pusht_env.rotation_matrix(angle).T + np.array([x, y])


@dataclass(frozen=True)
class BlockFit:
    """The block poses that best explain observed vertices.

    Attributes:
        poses: (T, 3) float64 block frame origin x, y (pixels) and angle in [0, 2 pi) (radians).
        residuals: (T,) float64 largest distance, in pixels, from an observed vertex to its fitted position.
    """

    poses: np.ndarray
    residuals: np.ndarray


def fit_block_poses(vertices: np.ndarray) -> BlockFit:
    """Invert gym-pusht's vertex function: the rigid 2-D fit of each frame's vertices to :func:`block_vertices`.

    For centred model vertices v_i and observed vertices p_i, the angle maximising sum_i p_i . R v_i is
    ``atan2(sum v_i x p_i, sum v_i . p_i)``; the translation moves the model's mean onto the observed mean.

    Args:
        vertices: (T, 16) observed vertices x0, y0, ..., x7, y7, in :func:`block_vertices`' order.

    Returns:
        The poses and each frame's residual.
    """
    observed = np.asarray(vertices, dtype=np.float64).reshape(-1, VERTICES, 2)
    model = block_vertices()
    model_mean, observed_mean = model.mean(axis=0), observed.mean(axis=1)  # (2,), (T, 2)
    centred_model, centred = model - model_mean, observed - observed_mean[:, None, :]
    dot = np.einsum("vd,tvd->t", centred_model, centred)
    cross = np.einsum("v,tv->t", centred_model[:, 0], centred[:, :, 1]) - np.einsum(
        "v,tv->t", centred_model[:, 1], centred[:, :, 0]
    )
    angles = np.arctan2(cross, dot)
    cos, sin = np.cos(angles), np.sin(angles)
    rotations = np.stack([np.stack([cos, -sin], axis=-1), np.stack([sin, cos], axis=-1)], axis=-2)  # (T, 2, 2)
    origins = observed_mean - np.einsum("tij,j->ti", rotations, model_mean)
    fitted = np.einsum("tij,vj->tvi", rotations, model) + origins[:, None, :]
    residuals = np.linalg.norm(fitted - observed, axis=-1).max(axis=-1)
    poses = np.column_stack([origins, np.mod(angles, 2 * math.pi)])
    return BlockFit(poses=poses, residuals=residuals)


class PushTKeypoints:
    """carp's Push-T observations and states from ``lerobot/pusht_keypoints``' features.

    A `carp.data.lerobot.derived.FeatureAdapter`: it reads ``observation.environment_state`` (T, 16) and
    ``observation.state`` (T, 2) and derives ``block_keypoints`` (T, 18), ``agent_pos`` (T, 2) and the states (T, 5).
    """

    provides = tuple(pusht_env.OBSERVATION_DIMS)
    sources = {ENVIRONMENT_STATE: 2 * VERTICES, AGENT_STATE: 2}
    layout = LAYOUT

    def __init__(self, tolerance_px: float = FIT_TOLERANCE_PX) -> None:
        self.tolerance_px = tolerance_px

    def derive(self, values: Mapping[str, np.ndarray], where: str) -> DerivedFeatures:
        """``block_keypoints`` (T, 18), ``agent_pos`` (T, 2) and the states (T, 5) of one episode.

        Raises:
            DatasetError: the first frame whose vertices fit no rigid T within the tolerance, in one line naming
                ``where`` (the file and the episode), the frame and the residual.
        """
        fit = fit_block_poses(values[ENVIRONMENT_STATE])
        wrong = np.flatnonzero(~(fit.residuals <= self.tolerance_px))
        if wrong.size:
            frame = int(wrong[0])
            raise DatasetError(
                f"{where}: frame {frame}: key '{ENVIRONMENT_STATE}': the 8 vertices are no rigid Push-T block: fit "
                f"residual {fit.residuals[frame]:.4g} px exceeds {self.tolerance_px:g} px (gym-pusht's "
                f"PushTEnv.get_keypoints order expected)"
            )
        agent = np.asarray(values[AGENT_STATE], dtype=np.float64)
        keypoints = np.stack([pusht_env.keypoints_in_workspace(pose).reshape(-1) for pose in fit.poses])
        return DerivedFeatures(
            obs={"block_keypoints": keypoints, "agent_pos": agent},
            states=np.column_stack([agent, fit.poses]),
        )


def replay_episode(env: "pusht_env.PushTEnv", first_state: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Rewards of an episode's recorded actions run open loop from its first state in carp's Push-T.

    Args:
        env: a Push-T env (`carp.tasks.pusht.make_env`) whose step limit is at least ``len(actions)``.
        first_state: (5,) agent x, y, block frame origin x, y, angle, as recorded (the block lands exactly there).
        actions: (T, 2) agent targets.

    Returns:
        (T,) DP's reward after each step, ``clip(coverage / 0.95, 0, 1)``.
    """
    state = np.asarray(first_state, dtype=np.float64)
    env.reset_to_state(pusht_env.reset_state_for_pose(state[:2], state[2:]))
    return np.array([env.step(action).reward for action in np.asarray(actions, dtype=np.float64)])


@dataclass(frozen=True)
class ReplayCheck:
    """How an episode's replay in carp's Push-T compares with its recorded rewards.

    Attributes:
        episode: the demo name.
        steps: T, the actions replayed.
        recorded_reward: the highest recorded ``next.reward``.
        replayed_reward: the highest reward of the replay.
        largest_gap: the largest |replayed - recorded| reward after the same step, over the steps whose
            ``next.reward`` is the next frame's (every step but the last, which repeats its own in LeRobot's data).
    """

    episode: str
    steps: int
    recorded_reward: float
    replayed_reward: float
    largest_gap: float

    @property
    def reached(self) -> bool:
        """Whether the replay reaches the recorded reward, within :data:`REPLAY_TOLERANCE`."""
        return self.replayed_reward >= self.recorded_reward - REPLAY_TOLERANCE


def check_replay(
    env: "pusht_env.PushTEnv", episode: str, states: np.ndarray, actions: np.ndarray, rewards: np.ndarray
) -> ReplayCheck:
    """Replay one episode (:func:`replay_episode`) from ``states[0]`` and compare with its rewards.

    Args:
        env: a Push-T env whose step limit is at least T.
        episode: the demo name, for the result.
        states: (T, 5) the episode's states; only the first is used.
        actions: (T, 2) its actions.
        rewards: (T,) its recorded ``next.reward``.
    """
    replayed = replay_episode(env, states[0], actions)
    rewards = np.asarray(rewards, dtype=np.float64)
    compared = slice(0, max(len(rewards) - 1, 1))
    return ReplayCheck(
        episode=episode,
        steps=len(actions),
        recorded_reward=float(rewards.max()),
        replayed_reward=float(replayed.max()),
        largest_gap=float(np.abs(replayed[compared] - rewards[compared]).max()),
    )


def check_replays(demos, episodes: int | None = None) -> list[ReplayCheck]:
    """Replay demos in carp's Push-T (:func:`check_replay`), each from its first state.

    Args:
        demos: `carp.data.robomimic_io.Demonstrations` with states and rewards, e.g. a ``lerobot/pusht_keypoints``
            folder read with :class:`PushTKeypoints` (`carp.data.lerobot.reader.read_lerobot_demonstrations`).
        episodes: the first this many demos; ``None`` replays all.

    Raises:
        DatasetError: a demo without states or rewards, naming it.
    """
    chosen = list(zip(demos.names, demos.episodes, strict=True))[:episodes]
    missing = next((name for name, episode in chosen if episode.states is None or episode.rewards is None), None)
    if missing is not None:
        raise DatasetError(f"{demos.path}: {missing}: the replay needs its states and rewards ('next.reward')")
    env = pusht_env.PushTEnv(max_steps=max([len(episode.actions) for _, episode in chosen], default=1))
    try:
        return [check_replay(env, name, episode.states, episode.actions, episode.rewards) for name, episode in chosen]
    finally:
        env.close()
