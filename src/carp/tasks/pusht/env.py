"""Push-T, the planar pushing task of Diffusion Policy, on gym-pusht's pymunk simulation.

Source: Diffusion Policy's low-dim Push-T (real-stanford/diffusion_policy: ``env/pusht/pusht_keypoints_env.py``,
``env/pusht/pymunk_keypoint_manager.py``, ``env_runner/pusht_keypoints_runner.py`` with the test settings of
``config/task/pusht_lowdim.yaml``). gym-pusht (huggingface/gym-pusht 0.1.8) carries DP's physics over: a disc
agent (radius 15) driven by a PD controller (kp 100, kv 20) towards an absolute target at 10 Hz with 10 physics
steps of 10 ms each, a T-shaped block that moves only while pushed (no damping), walls at 5 and 506 and the goal pose
(256, 256, pi/4). The simulation, its reset to a given state, its coverage and its drawing are gym-pusht's; this
module adds what DP's protocol defines around them:

- Observation: DP's 20 values, the 9 block keypoints (``BLOCK_KEYPOINTS``, fixed in the block's frame, moved by its
  current pose) as (x0, y0, ..., x8, y8), then the agent position. gym-pusht offers neither: its ``"state"``
  observation is the 5-D pose (agent x, y, block x, y, angle) and its ``"environment_state_agent_pos"`` one is the
  T's 8 polygon vertices (16) plus the agent position, corners of the two rectangles rather than DP's keypoints.
- Reset: DP's test-time draw from the episode seed (:func:`reset_state`), applied through gym-pusht's reset to a
  state. gym-pusht's own seeded reset draws from gymnasium's generator with a uniform angle, a different state for the
  same seed.
- Episode: reward ``clip(coverage / 0.95, 0, 1)``, success when coverage > 0.95, at most ``MAX_STEPS`` (300) steps.
  gym-pusht's step limit lives in the ``TimeLimit`` wrapper of ``gym.make``, which is not used here.

Deviations from DP: its observation also carries a keypoint visibility mask (20 more values, all ones at the visible
rate 1.0 of its Push-T config), which its policies drop, so it is left out. The physics runs on pymunk 6.11 where
DP's environment had 6.2.1: the same Chipmunk model and step sizes, not checked to be bit-identical. Everything else
follows DP's test runner, including its legacy reset order (block position set before its angle, see
:func:`reset_state`).

Coordinates are pixels of the 512 x 512 workspace with y pointing down, as drawn; angles are in radians.
"""

import importlib.metadata
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

ENV_NAME = "gym_pusht/PushT-v0"
"""gym-pusht's registered id, the ``env_name`` of Push-T's env_args."""
GYM_ENV_TYPE = 2
"""robomimic's ``EnvType.GYM_TYPE``, the ``type`` of Push-T's env_args (robosuite's envs are 1)."""

WORKSPACE_SIZE = 512
"""Side of the square workspace, in pixels; actions are agent targets in [0, WORKSPACE_SIZE]^2."""
GOAL_POSE = (256.0, 256.0, math.pi / 4)
"""The block pose (x, y, angle) to cover, as gym-pusht and DP place it."""
SUCCESS_COVERAGE = 0.95
"""An episode succeeds once more than this fraction of the goal's area is covered by the block."""
MAX_STEPS = 300
"""DP's step limit of a Push-T episode, in control steps of 0.1 s."""
CONTROL_FREQUENCY_HZ = 10
ACTION_DIM = 2
MIN_RENDER_SIZE = 96
"""Smallest frame side: gym-pusht draws the action's cross 1/96 of the frame thick, which rounds to 0 below."""

OBSERVATION_DIMS = {"block_keypoints": 18, "agent_pos": 2}
"""Observation keys in DP's order and their widths; concatenated, they are DP's 20-D observation."""
OBSERVATION_DIM = sum(OBSERVATION_DIMS.values())

# The block's frame has its origin in the middle of the crossbar's top edge and its y axis down the stem. Its centre
# of gravity is the mean of the two rectangles' centroids, (0, 15) and (0, 75), as gym-pusht's `add_tee` sets it;
# setting the block's angle turns it about this point (pymunk keeps the centre of gravity fixed).
BLOCK_CENTER_OF_GRAVITY = (0.0, 45.0)

# DP's 9 block keypoints in the block's frame, (9, 2). Computed once by `farthest_point_block_keypoints()` as DP's
# keypoint manager defines them: the T drawn at (256, 300) with angle 0 on a white 512 x 512 pygame surface by
# gym-pusht's `DrawOptions` (DP's drawing code: a light fill and 2 px outlines), every painted pixel moved into the
# block's frame, farthest-point sampling from a first pixel drawn by `numpy.random.default_rng(0).choice`, then a
# shift by `uniform(0, 1)` per coordinate from the same generator. Stored rather than recomputed at import because
# they depend on pygame's rasterisation; a test recomputes them, so a pygame that draws the T differently shows up.
BLOCK_KEYPOINTS = np.array(
    [
        [9.269786713763871, 90.04097352393619],
        [-60.983472364471474, -1.1867297607997276],
        [60.91275557727772, -1.3933642242328201],
        [-0.2705034390160016, 25.54362499146542],
        [-14.064927576212233, 122.81585355412153],
        [39.002738500170146, 32.857404276587566],
        [-39.966414424694534, 32.729655446429945],
        [-16.82434437939744, 62.86317892234989],
        [23.54146122024909, -1.7002881094626152],
    ]
)
BLOCK_KEYPOINTS.flags.writeable = False

# Where DP draws the T to find its keypoints; the result is in the block's frame, so only the seed matters.
_KEYPOINT_DRAWING_POSITION = (256, 300)
_KEYPOINT_SEED = 0


def _gym_pusht():
    """gym-pusht's env module, imported on first use (it brings pygame, gymnasium, OpenCV and shapely)."""
    # pygame prints a greeting to stdout when imported; evaluation workers would repeat it once per process.
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    from gym_pusht.envs import pusht

    return pusht


def rotation_matrix(angle: float) -> np.ndarray:
    """(2, 2) matrix turning a block-frame vector by ``angle`` into the workspace, as pymunk's ``Vec2d.rotated``."""
    cos, sin = math.cos(angle), math.sin(angle)
    return np.array([[cos, -sin], [sin, cos]])


def keypoints_in_workspace(block_pose: np.ndarray) -> np.ndarray:
    """Where the block keypoints are when the block's frame has ``block_pose``.

    Args:
        block_pose: (3,) the block frame's origin (x, y) in the workspace and its angle.

    Returns:
        (9, 2) float64 keypoint positions, in the order of :data:`BLOCK_KEYPOINTS`.
    """
    x, y, angle = (float(value) for value in block_pose)
    return BLOCK_KEYPOINTS @ rotation_matrix(angle).T + np.array([x, y])


def farthest_point_block_keypoints(count: int = 9, seed: int = _KEYPOINT_SEED) -> np.ndarray:
    """Recompute DP's block keypoints: farthest-point samples of the T's drawn pixels (see :data:`BLOCK_KEYPOINTS`).

    Args:
        count: number of keypoints.
        seed: seed of the generator that picks the first pixel and the sub-pixel shifts.

    Returns:
        (count, 2) float64 keypoints in the block's frame.
    """
    pusht = _gym_pusht()
    space = pusht.pymunk.Space()
    block, _ = pusht.PushTEnv.add_tee(space, _KEYPOINT_DRAWING_POSITION, 0)
    surface = pusht.pygame.Surface((WORKSPACE_SIZE, WORKSPACE_SIZE))
    surface.fill((255, 255, 255))
    space.debug_draw(pusht.DrawOptions(surface))
    # surfarray indexes (x, y); DP lists the pixels row by row (y, then x), and the first pick depends on that order.
    painted = (pusht.pygame.surfarray.array3d(surface) != 255).any(axis=-1).T  # (y, x)
    rows, columns = np.nonzero(painted)
    pixels = np.stack([columns, rows], axis=-1) - np.array(block.position)  # (pixels, 2), block frame at angle 0

    generator = np.random.default_rng(seed)
    chosen = [int(generator.choice(len(pixels)))]
    distance_to_chosen = np.linalg.norm(pixels - pixels[chosen[0]], axis=-1)
    for _ in range(count - 1):
        farthest = int(np.argmax(distance_to_chosen))  # the first pixel among equals, as DP's argmax
        chosen.append(farthest)
        distance_to_chosen = np.minimum(distance_to_chosen, np.linalg.norm(pixels - pixels[farthest], axis=-1))
    return pixels[chosen] + generator.uniform(0, 1, size=(count, 2))


def reset_state(seed: int) -> np.ndarray:
    """DP's initial state for an episode seed, in the form gym-pusht's reset to a state takes.

    DP's test runner draws, from a legacy ``numpy.random.RandomState(seed)``: the agent position from
    ``randint(50, 450)`` twice, the block position from ``randint(100, 400)`` twice and the angle as
    ``randn() * 2 pi - pi``. Both DP (with ``legacy=True``, its test setting) and gym-pusht apply the block position
    before the angle, so the angle turns the block about its centre of gravity and the block's origin ends away
    from the drawn position (see :func:`reset_state_for_pose` for a state that lands on a given pose).

    Returns:
        (5,) float64: agent x, y, block x, y, block angle.
    """
    draws = np.random.RandomState(seed)
    agent = draws.randint(50, 450, size=2)
    block = draws.randint(100, 400, size=2)
    angle = draws.randn() * 2 * math.pi - math.pi
    return np.array([*agent, *block, angle], dtype=np.float64)


def reset_state_for_pose(agent_position: np.ndarray, block_pose: np.ndarray) -> np.ndarray:
    """The reset state that puts the agent at ``agent_position`` and the block's frame exactly at ``block_pose``.

    The reset sets the block's position (at angle 0) and then turns it by the angle about its centre of gravity,
    which moves the origin by ``(I - R) c`` for the centre of gravity ``c``; the state compensates for it.

    Args:
        agent_position: (2,) agent x, y.
        block_pose: (3,) block frame origin x, y and angle.

    Returns:
        (5,) float64 state for :meth:`PushTEnv.reset_to_state`.
    """
    x, y, angle = (float(value) for value in block_pose)
    center_of_gravity = np.array(BLOCK_CENTER_OF_GRAVITY)
    position_before_turn = np.array([x, y]) - center_of_gravity + rotation_matrix(angle) @ center_of_gravity
    return np.array([*np.asarray(agent_position, dtype=np.float64), *position_before_turn, angle])


def reward_for(coverage: float) -> float:
    """DP's reward: the covered fraction of the goal relative to the success threshold, clipped to [0, 1]."""
    return float(np.clip(coverage / SUCCESS_COVERAGE, 0.0, 1.0))


def make_env_args() -> dict:
    """robomimic-style env_args (JSON-serializable) of Push-T, stored in its demonstration files.

    ``env_kwargs`` is empty: DP's Push-T has no options (gym-pusht's ``block_cog`` and ``damping`` variants stay at
    their defaults, DP's values), and the pinned gym-pusht version in ``env_version`` fixes the physics.
    """
    return {
        "env_name": ENV_NAME,
        "type": GYM_ENV_TYPE,
        "env_version": importlib.metadata.version("gym-pusht"),
        "env_kwargs": {},
    }


def make_env(env_args: Mapping, render_size: int = 256) -> "PushTEnv":
    """Build the Push-T env described by env_args.

    Args:
        env_args: dict from :func:`make_env_args` or a Push-T file's ``data.attrs["env_args"]``.
        render_size: height and width of :meth:`PushTEnv.render` frames.

    Raises:
        ValueError: env_args of another environment, naming it.
    """
    if env_args.get("env_name") != ENV_NAME:
        raise ValueError(f"env_args describe '{env_args.get('env_name')}', not Push-T ('{ENV_NAME}')")
    return PushTEnv(render_size=render_size, **env_args["env_kwargs"])


@dataclass(frozen=True)
class PushTStep:
    """What one control step of Push-T leads to."""

    observation: dict[str, np.ndarray]
    """:data:`OBSERVATION_DIMS` keys -> (width,) float64, after the step."""
    reward: float
    coverage: float
    success: bool
    done: bool
    """Success, or the step limit reached."""


class PushTEnv:
    """Push-T with DP's observation, seeded reset, reward, success and step limit around gym-pusht's simulation.

    An episode starts with :meth:`reset` (a seed) or :meth:`reset_to_state` (a hand-placed state) and lasts until
    the step limit: stepping on after a success is allowed (DP's runner does, and scores the maximum reward), stepping
    past the limit is an error.
    """

    def __init__(
        self,
        render_size: int = 256,
        max_steps: int = MAX_STEPS,
    ) -> None:
        """Build the simulation; an episode starts with a reset.

        Args:
            render_size: height and width of :meth:`render` frames, in pixels, at least 96.
            max_steps: step limit of an episode.
        """
        if max_steps < 1:
            raise ValueError(f"max_steps must be at least 1, got {max_steps}")
        if render_size < MIN_RENDER_SIZE:
            raise ValueError(f"render_size must be at least {MIN_RENDER_SIZE} pixels, got {render_size}")
        self.max_steps = max_steps
        self._simulation = _gym_pusht().PushTEnv(
            obs_type="state",  # the cheapest of gym-pusht's observations; the keypoints are computed here
            render_mode="rgb_array",
            visualization_width=render_size,
            visualization_height=render_size,
        )
        self.steps = 0
        self._started = False

    def reset(self, seed: int) -> dict[str, np.ndarray]:
        """Start an episode in DP's initial state for ``seed`` (:func:`reset_state`).

        Returns:
            The observation (:meth:`observation`).
        """
        return self.reset_to_state(reset_state(seed))

    def reset_to_state(self, state: np.ndarray) -> dict[str, np.ndarray]:
        """Start an episode from ``state`` through gym-pusht's reset to a state.

        Args:
            state: (5,) agent x, y, block x, y, block angle, applied as :func:`reset_state` describes (block position
                before the angle, then one physics step of 10 ms).

        Returns:
            The observation (:meth:`observation`).
        """
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (5,):
            raise ValueError(f"a Push-T state has shape (5,) (agent x, y, block x, y, angle), got {state.shape}")
        self._simulation.reset(options={"reset_to_state": state})
        # gym-pusht keeps the previous episode's last action through a reset and would draw its cross on this
        # episode's first frames.
        self._simulation._last_action = None
        self.steps = 0
        self._started = True
        return self.observation()

    def step(self, action: np.ndarray) -> PushTStep:
        """Drive the agent towards ``action`` for one control step (0.1 s).

        Args:
            action: (2,) absolute agent target (x, y) in [0, 512]^2.

        Raises:
            ValueError: an action of another shape, naming both shapes.
            RuntimeError: no reset yet, or the episode already reached its step limit.
        """
        target = np.asarray(action, dtype=np.float64)
        if target.shape != (ACTION_DIM,):
            raise ValueError(
                f"a Push-T action is an absolute agent target of shape ({ACTION_DIM},), got shape {target.shape}"
            )
        if not self._started:
            raise RuntimeError("reset the Push-T env before stepping it")
        if self.steps >= self.max_steps:
            raise RuntimeError(f"the Push-T episode ended at its step limit of {self.max_steps}; reset it")
        _, _, _, _, info = self._simulation.step(target)
        self.steps += 1
        coverage = float(info["coverage"])
        success = coverage > SUCCESS_COVERAGE
        return PushTStep(
            observation=self.observation(),
            reward=reward_for(coverage),
            coverage=coverage,
            success=success,
            done=success or self.steps >= self.max_steps,
        )

    def state(self) -> np.ndarray:
        """(5,) float64: agent x, y, block frame origin x, y, block angle (not wrapped)."""
        agent, block = self._simulation.agent, self._simulation.block
        return np.array([*agent.position, *block.position, block.angle], dtype=np.float64)

    def observation(self) -> dict[str, np.ndarray]:
        """DP's observation by key: ``block_keypoints`` (18,) as x0, y0, ..., x8, y8 and ``agent_pos`` (2,)."""
        state = self.state()
        return {
            "block_keypoints": keypoints_in_workspace(state[2:]).reshape(-1),
            "agent_pos": state[:2],
        }

    def observation_vector(self) -> np.ndarray:
        """DP's (20,) float64 observation: the 9 keypoints' x, y, then the agent's x, y."""
        observation = self.observation()
        return np.concatenate([observation[key] for key in OBSERVATION_DIMS])

    def coverage(self) -> float:
        """Fraction of the goal's area that the block covers now (gym-pusht's shapely intersection)."""
        return float(self._simulation._get_coverage())

    def reward(self) -> float:
        """DP's reward for the current state (:func:`reward_for`)."""
        return reward_for(self.coverage())

    def is_success(self) -> bool:
        """Whether the block covers more than 95% of the goal now."""
        return self.coverage() > SUCCESS_COVERAGE

    def render(self) -> np.ndarray:
        """(render_size, render_size, 3) uint8 RGB frame: goal, block, agent and the last action's target (a cross).

        Drawn by pygame on an offscreen surface, so it needs no display.
        """
        return self._simulation.render()

    def close(self) -> None:
        """Release gym-pusht's resources (a window, if it ever opened one)."""
        self._simulation.close()
