"""A scripted Push-T expert: a planner over a library of short pushes, checked on a scratch simulation.

The block of Push-T moves only while the agent pushes it (the space has no damping carry-over: its velocity is
lost every physics step), so a push started with the agent at rest at a given point of the block's frame moves the
block by the same rigid displacement wherever the block is, as long as no wall is in reach. The expert uses that:

- Push library (:func:`push_library`): contact points along the T's outer edges x push directions (the inward
  normal and two oblique ones) x push lengths, each simulated once from a canonical pose in the middle of the
  workspace. A push is stored as its agent targets in the block's frame and the block displacement it produced.
- Planning (:meth:`PushTExpert.plan`): a beam search over compositions of library displacements from the current
  block pose, scored by the mean distance of the block's corners to their goal positions.
- Transit (:func:`transit_waypoints`): the agent reaches the push's start point straight when that path keeps
  clear of the T, otherwise around a circle that encloses it.
- Check: the best first pushes are rolled out (transit and push) on a scratch simulation synced to the current
  state; the first that improves the block's pose (or, near the goal, its true coverage) is executed. Near the goal
  every candidate is scored by the coverage it reaches on the scratch simulation.

Controlled diversity: first pushes whose beam scores lie within :data:`TIE_TOLERANCE` of each other are ordered by
draws from the expert's seeded generator (and the library order is shuffled by it before stable sorts), so different
expert seeds pick different, equally good pushes and the same seed repeats its
episode exactly. Nothing is added to the executed actions.
"""

import functools
import math
from dataclasses import dataclass

import numpy as np

from carp.tasks.pusht.env import GOAL_POSE, MAX_STEPS, WORKSPACE_SIZE, PushTEnv, rotation_matrix

AGENT_RADIUS = 15.0
PHYSICS_STEPS_PER_CONTROL = 10
PHYSICS_DT = 0.01
PD_GAINS = (100.0, 20.0)
"""gym-pusht's PD controller of the agent (position gain, velocity gain), repeated by the scratch rollouts."""

# The T in its own frame: crossbar x in [-60, 60], y in [0, 30]; stem x in [-15, 15], y in [30, 120].
# Outer edges as (start, end, outward normal); contact points are spread along them.
T_EDGES = (
    ((-60.0, 0.0), (60.0, 0.0), (0.0, -1.0)),  # top of the crossbar
    ((60.0, 0.0), (60.0, 30.0), (1.0, 0.0)),  # right end
    ((60.0, 30.0), (15.0, 30.0), (0.0, 1.0)),  # underside of the crossbar, right
    ((15.0, 30.0), (15.0, 120.0), (1.0, 0.0)),  # right side of the stem
    ((15.0, 120.0), (-15.0, 120.0), (0.0, 1.0)),  # foot of the stem
    ((-15.0, 120.0), (-15.0, 30.0), (-1.0, 0.0)),  # left side of the stem
    ((-15.0, 30.0), (-60.0, 30.0), (0.0, 1.0)),  # underside of the crossbar, left
    ((-60.0, 30.0), (-60.0, 0.0), (-1.0, 0.0)),  # left end
)
T_CORNERS = np.array(
    [[-60, 0], [60, 0], [60, 30], [15, 30], [15, 120], [-15, 120], [-15, 30], [-60, 30]], dtype=np.float64
)
"""(8, 2) the T's corners in its frame; their mean distance to the goal's corners is the planner's pose error."""
T_CENTER = np.array([0.0, 45.0])
T_ENCLOSING_RADIUS = 77.0
"""Every point of the T lies within this distance of ``T_CENTER`` (the stem's foot corners, at 76.5)."""

CONTACT_SPACING = 10.0
START_GAP = 4.0
"""Distance between the agent's rim and the edge where a push starts."""
PUSH_ANGLES = (-0.5, 0.0, 0.5)
"""Push directions relative to the inward normal, in radians."""
PUSH_LENGTHS = (6.0, 15.0, 35.0, 70.0)
"""How far past the edge's first touch the agent's target travels, in pixels."""
PUSH_SPEED = 12.0
"""Target travel per control step during a push, in pixels."""
PUSH_SETTLE_STEPS = 3
"""Control steps holding the last target, so the lagging agent finishes the push before the next move."""
TRANSIT_SPEED = 30.0
TRANSIT_CLEARANCE = 8.0
"""Extra distance between the agent's rim and the T that a straight transit keeps."""
CANONICAL_POSE = (256.0, 200.0, 0.0)

BEAM_WIDTH = 8
BEAM_DEPTH = 2
CHECKED_CANDIDATES = 12
TIE_TOLERANCE = 3.0
"""Beam scores (pixels of pose error) closer than this are ties, broken by the expert's seed."""
FINE_ERROR = 12.0
"""Pose error (pixels) below which pushes are chosen by the coverage they reach on the scratch simulation."""
FINE_CANDIDATES = 40
WALL_MARGIN = 20.0
RETREAT_DISTANCE = 30.0
"""How far the agent backs off the T when no push can be reached from where it is."""


def to_workspace(block_pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., 2) in the block's frame -> (..., 2) workspace points for ``block_pose`` (x, y, angle)."""
    return points @ rotation_matrix(block_pose[2]).T + block_pose[:2]


def compose(block_poses: np.ndarray, displacements: np.ndarray) -> np.ndarray:
    """Apply block-frame displacements to poses.

    Args:
        block_poses: (P, 3) poses (x, y, angle).
        displacements: (D, 3) rigid displacements (dx, dy, dangle) expressed in the frame of the pose they start from.

    Returns:
        (P, D, 3) resulting poses.
    """
    cos, sin = np.cos(block_poses[:, 2])[:, None], np.sin(block_poses[:, 2])[:, None]
    x = block_poses[:, 0:1] + cos * displacements[None, :, 0] - sin * displacements[None, :, 1]
    y = block_poses[:, 1:2] + sin * displacements[None, :, 0] + cos * displacements[None, :, 1]
    angle = block_poses[:, 2:3] + displacements[None, :, 2]
    return np.stack([x, y, angle], axis=-1)


def _corners_in_workspace(block_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The T's corners for (..., 3) poses: their x and y, each (..., 8)."""
    cos, sin = np.cos(block_poses[..., 2:3]), np.sin(block_poses[..., 2:3])
    corners_x = block_poses[..., 0:1] + cos * T_CORNERS[:, 0] - sin * T_CORNERS[:, 1]
    corners_y = block_poses[..., 1:2] + sin * T_CORNERS[:, 0] + cos * T_CORNERS[:, 1]
    return corners_x, corners_y


def pose_error(block_poses: np.ndarray) -> np.ndarray:
    """(...,) mean distance in pixels of the T's corners to their goal positions, for (..., 3) poses."""
    goal = np.asarray(GOAL_POSE)
    corners_x, corners_y = _corners_in_workspace(block_poses)
    goal_corners = to_workspace(goal, T_CORNERS)
    return np.hypot(corners_x - goal_corners[:, 0], corners_y - goal_corners[:, 1]).mean(axis=-1)


def distance_to_t(points: np.ndarray) -> np.ndarray:
    """(N,) distance of (N, 2) block-frame points to the T (0 inside it)."""
    distances = []
    for low, high in (((-60.0, 0.0), (60.0, 30.0)), ((-15.0, 30.0), (15.0, 120.0))):
        outside = np.maximum(np.maximum(np.asarray(low) - points, points - np.asarray(high)), 0.0)
        distances.append(np.hypot(outside[:, 0], outside[:, 1]))
    return np.minimum(*distances)


@dataclass(frozen=True)
class Push:
    """One library push, in the block's frame."""

    targets: np.ndarray
    """(steps, 2) agent targets, the first being the start point where the agent waits at rest."""
    displacement: np.ndarray
    """(3,) the block's rigid displacement (dx, dy, dangle) in its frame at the push's start."""


class ScratchSimulation:
    """A second gym-pusht simulation, synced to a real one, on which action sequences are tried first.

    gym-pusht's space holds a collision callback bound to its env, so it cannot be copied; the scratch one copies
    the bodies' positions, angles and velocities instead (not the solver's cached contact impulses, so a rollout
    here can differ slightly from the real one while the agent touches the block).
    """

    def __init__(self) -> None:
        self.env = PushTEnv(render_size=96)
        self.env.reset_to_state(np.array([100.0, 100.0, *CANONICAL_POSE]))

    def sync(self, source: PushTEnv) -> None:
        """Copy the agent's and the block's state from ``source``."""
        for name in ("agent", "block"):
            mine, theirs = getattr(self.env._simulation, name), getattr(source._simulation, name)
            mine.angle = theirs.angle
            mine.position = theirs.position
            mine.velocity = theirs.velocity
            mine.angular_velocity = theirs.angular_velocity

    def place(self, agent_position: np.ndarray, block_pose: np.ndarray) -> None:
        """Put the agent at rest at ``agent_position`` and the block's frame exactly at ``block_pose``."""
        agent, block = self.env._simulation.agent, self.env._simulation.block
        block.angle = float(block_pose[2])
        block.position = (float(block_pose[0]), float(block_pose[1]))
        block.velocity = (0.0, 0.0)
        block.angular_velocity = 0.0
        agent.position = (float(agent_position[0]), float(agent_position[1]))
        agent.velocity = (0.0, 0.0)

    def drive(self, target: np.ndarray) -> None:
        """One control step towards ``target``: gym-pusht's PD law over its 10 physics steps, without coverage."""
        simulation = self.env._simulation
        agent = simulation.agent
        position_gain, velocity_gain = PD_GAINS
        for _ in range(PHYSICS_STEPS_PER_CONTROL):
            acceleration = position_gain * (target - np.asarray(agent.position)) - velocity_gain * np.asarray(
                agent.velocity
            )
            agent.velocity = tuple(np.asarray(agent.velocity) + acceleration * PHYSICS_DT)
            simulation.space.step(PHYSICS_DT)

    def agent_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(2,) agent position and (2,) velocity."""
        agent = self.env._simulation.agent
        return np.asarray(agent.position, dtype=np.float64), np.asarray(agent.velocity, dtype=np.float64)

    def block_pose(self) -> np.ndarray:
        """(3,) the block frame's origin and angle."""
        return self.env.state()[2:]


def _push_targets(contact: np.ndarray, normal: np.ndarray, angle: float, length: float) -> np.ndarray | None:
    """(steps, 2) block-frame targets of one push, or None where the disc cannot start or travel there."""
    start = contact + normal * (AGENT_RADIUS + START_GAP)
    if distance_to_t(start[None])[0] < AGENT_RADIUS + START_GAP - 0.5:
        return None  # too close to a concave corner for the disc
    direction = rotation_matrix(angle) @ -normal
    travel = START_GAP + length
    steps = max(1, math.ceil(travel / PUSH_SPEED))
    ramp = [start + direction * travel * (step + 1) / steps for step in range(steps)]
    return np.array([start, *ramp, *[ramp[-1]] * PUSH_SETTLE_STEPS])


@functools.lru_cache(maxsize=1)
def push_library() -> tuple[Push, ...]:
    """Every library push, simulated once from :data:`CANONICAL_POSE` with the agent at rest at its start."""
    scratch = ScratchSimulation()
    canonical = np.asarray(CANONICAL_POSE)
    pushes = []
    for start_corner, end_corner, outward in T_EDGES:
        start_corner, end_corner, normal = (np.asarray(value) for value in (start_corner, end_corner, outward))
        edge_length = float(np.linalg.norm(end_corner - start_corner))
        count = max(1, round(edge_length / CONTACT_SPACING))
        for fraction in (np.arange(count) + 0.5) / count:
            contact = start_corner + fraction * (end_corner - start_corner)
            for angle in PUSH_ANGLES:
                for length in PUSH_LENGTHS:
                    targets = _push_targets(contact, normal, angle, length)
                    if targets is None:
                        continue
                    world_targets = to_workspace(canonical, targets)
                    scratch.place(world_targets[0], canonical)
                    for target in world_targets[1:]:
                        scratch.drive(target)
                    moved = scratch.block_pose()
                    offset = rotation_matrix(-canonical[2]) @ (moved[:2] - canonical[:2])
                    displacement = np.array([*offset, moved[2] - canonical[2]])
                    if np.abs(displacement).max() < 1e-3:
                        continue  # the push never reached the block
                    pushes.append(Push(targets=targets, displacement=displacement))
    return tuple(pushes)


def transit_waypoints(agent_position: np.ndarray, block_pose: np.ndarray, goal_point: np.ndarray) -> np.ndarray:
    """Agent targets from ``agent_position`` to ``goal_point`` that keep the disc off the T at ``block_pose``.

    Straight when the straight path keeps :data:`TRANSIT_CLEARANCE` from the T; otherwise out to a circle enclosing
    the T, along it the shorter way, and in to the goal point.

    Returns:
        (waypoints, 2) workspace points, spaced at most :data:`TRANSIT_SPEED` apart, ending at ``goal_point``.
    """
    straight = _resample(np.array([agent_position, goal_point]), 5.0)  # (points, 2)
    straight_in_block_frame = (straight - block_pose[:2]) @ rotation_matrix(-block_pose[2]).T
    if _path_is_clear(straight_in_block_frame):
        corners = [goal_point]
    else:
        center = to_workspace(block_pose, T_CENTER)
        radius = T_ENCLOSING_RADIUS + AGENT_RADIUS + TRANSIT_CLEARANCE
        start_angle = math.atan2(*(agent_position - center)[::-1])
        end_angle = math.atan2(*(goal_point - center)[::-1])
        sweep = (end_angle - start_angle + math.pi) % (2 * math.pi) - math.pi
        # The shorter way round, unless it leaves the workspace and the longer one does not.
        best = None
        for candidate_sweep in (sweep, sweep - math.copysign(2 * math.pi, sweep)):
            angles = start_angle + candidate_sweep * np.linspace(0, 1, max(2, math.ceil(abs(candidate_sweep) / 0.3)))
            arc = center + radius * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
            inside = np.all((arc > AGENT_RADIUS + 6) & (arc < WORKSPACE_SIZE - AGENT_RADIUS - 6))
            if inside or best is None:
                best = arc
            if inside:
                break
        corners = [*np.clip(best, AGENT_RADIUS + 6, WORKSPACE_SIZE - AGENT_RADIUS - 6), goal_point]
    return _resample(np.array([agent_position, *corners]), TRANSIT_SPEED)[1:]


def _path_is_clear(block_frame_points: np.ndarray) -> bool:
    return bool(distance_to_t(block_frame_points).min() > AGENT_RADIUS + TRANSIT_CLEARANCE)


def _resample(polyline: np.ndarray, spacing: float) -> np.ndarray:
    """(N, 2) points along ``polyline`` (its corners kept) at most ``spacing`` apart, starting at its first."""
    points = [polyline[0]]
    for start, end in zip(polyline[:-1], polyline[1:], strict=True):
        pieces = max(1, math.ceil(np.linalg.norm(end - start) / spacing))
        points.extend(start + (end - start) * (piece + 1) / pieces for piece in range(pieces))
    return np.array(points)


class PushTExpert:
    """Plans and executes pushes until the block covers the goal; :meth:`act` gives one action per control step.

    Use: ``env.reset(seed)``, then ``env.step(expert.act(env))`` until the step's ``done``. The expert replans
    whenever its queue of actions (one transit and one push) runs out.
    """

    def __init__(self, seed: int = 0) -> None:
        self.library = push_library()
        order = np.random.default_rng(seed).permutation(len(self.library))
        self.library = tuple(self.library[index] for index in order)
        self.displacements = np.array([push.displacement for push in self.library])  # (pushes, 3)
        self.tie_breaks = np.random.default_rng(seed)
        self.scratch = ScratchSimulation()
        self.queue: list[np.ndarray] = []

    def act(self, env: PushTEnv) -> np.ndarray:
        """(2,) the next agent target for ``env``'s current state."""
        if not self.queue:
            self.queue = self.plan(env)
        return self.queue.pop(0)

    def plan(self, env: PushTEnv) -> list[np.ndarray]:
        """Actions (each (2,)) of the next transit and push, checked on the scratch simulation."""
        state = env.state()
        block_pose = state[2:]
        error = float(pose_error(block_pose))
        steps_left = MAX_STEPS - env.steps
        if error < FINE_ERROR:
            candidates = np.argsort(pose_error(compose(block_pose[None], self.displacements)[0]), kind="stable")
            actions = self._best_by_rollout(env, candidates[:FINE_CANDIDATES], steps_left, by_coverage=True)
            return actions if actions is not None else [_retreat_target(state)]
        actions = self._best_by_rollout(env, self._beam_first_pushes(block_pose), steps_left, by_coverage=False)
        if actions is None:
            # Near a wall the beam's favourites may all be unreachable (their start or their transit leaves the
            # workspace); any reachable push, the best predicted first, gets the block back into open space.
            ranked = np.argsort(pose_error(compose(block_pose[None], self.displacements)[0]), kind="stable")
            actions = self._best_by_rollout(env, ranked, steps_left, by_coverage=False)
        # Nothing reachable: the agent sits against or inside the T (DP's reset draws the two independently) or is
        # boxed in by a wall. Backing off frees it; the next plan starts from open space.
        return actions if actions is not None else [_retreat_target(state)]

    def _beam_first_pushes(self, block_pose: np.ndarray) -> np.ndarray:
        """Library indices of first pushes, best first, ranked by the best pose a beam search reaches after them."""
        poses = block_pose[None]  # (beam, 3)
        first = np.array([-1])
        best_by_first: dict[int, float] = {}
        for depth in range(BEAM_DEPTH):
            reached = compose(poses, self.displacements)  # (beam, pushes, 3)
            errors = pose_error(reached) + _wall_penalty(reached)
            firsts = np.broadcast_to(np.arange(len(self.library)) if depth == 0 else first[:, None], errors.shape)
            for index, value in zip(firsts.reshape(-1), errors.reshape(-1), strict=True):
                if value < best_by_first.get(int(index), np.inf):
                    best_by_first[int(index)] = float(value)
            keep = np.argsort(errors.reshape(-1), kind="stable")[: BEAM_WIDTH * 4]
            poses = reached.reshape(-1, 3)[keep]
            first = firsts.reshape(-1)[keep]
        # Pushes within TIE_TOLERANCE of each other count as equals, ordered by the expert's seeded draws.
        firsts = np.array(list(best_by_first))
        errors = np.array([best_by_first[index] for index in firsts])
        keys = errors + self.tie_breaks.uniform(0.0, TIE_TOLERANCE, size=len(errors))
        return firsts[np.argsort(keys, kind="stable")[:CHECKED_CANDIDATES]]

    def _rollout(self, env: PushTEnv, push: Push, steps_left: int) -> tuple[list[np.ndarray], float, float] | None:
        """Transit and push on the scratch simulation: (actions, pose error, coverage), or None if they fail."""
        state = env.state()
        block_pose = state[2:]
        world_targets = to_workspace(block_pose, push.targets)
        if np.any(world_targets < AGENT_RADIUS) or np.any(world_targets > WORKSPACE_SIZE - AGENT_RADIUS):
            return None
        self.scratch.sync(env)
        actions = []
        for waypoint in transit_waypoints(state[:2], block_pose, world_targets[0]):
            actions.append(waypoint)
            self.scratch.drive(waypoint)
        for _ in range(8):  # wait at the start until the agent is nearly at rest there
            position, velocity = self.scratch.agent_state()
            if np.linalg.norm(position - world_targets[0]) < 1.0 and np.linalg.norm(velocity) < 10.0:
                break
            actions.append(world_targets[0])
            self.scratch.drive(world_targets[0])
        if np.abs(self.scratch.block_pose() - block_pose).max() > 0.5:
            return None  # the transit touched the block
        for target in world_targets[1:]:
            actions.append(target)
            self.scratch.drive(target)
        if len(actions) > steps_left:
            actions = actions[:steps_left]
        reached = self.scratch.block_pose()
        return actions, float(pose_error(reached)), self.scratch.env.coverage()

    def _best_by_rollout(
        self, env: PushTEnv, candidates: np.ndarray, steps_left: int, by_coverage: bool
    ) -> list[np.ndarray] | None:
        """Actions of the candidate push whose rollout ends best (the first improving one when not fine), or None."""
        current_error = float(pose_error(env.state()[2:]))
        best_actions, best_score = None, -np.inf
        for index in candidates:
            outcome = self._rollout(env, self.library[int(index)], steps_left)
            if outcome is None:
                continue
            actions, error, coverage = outcome
            score = coverage if by_coverage else -error
            if score > best_score:
                best_actions, best_score = actions, score
            if not by_coverage and error < current_error - 1.0:
                return actions
        return best_actions


def _retreat_target(state: np.ndarray) -> np.ndarray:
    """(2,) a target `RETREAT_DISTANCE` from the agent, straight away from the T's centre, inside the workspace."""
    agent = state[:2]
    away = agent - to_workspace(state[2:], T_CENTER)
    length = float(np.linalg.norm(away))
    direction = away / length if length > 1e-6 else np.array([0.0, -1.0])
    return np.clip(agent + RETREAT_DISTANCE * direction, AGENT_RADIUS, WORKSPACE_SIZE - AGENT_RADIUS)


def _wall_penalty(block_poses: np.ndarray) -> np.ndarray:
    """(...,) large for (..., 3) poses whose T comes within :data:`WALL_MARGIN` of the workspace's edge."""
    corners_x, corners_y = _corners_in_workspace(block_poses)
    low = np.minimum(corners_x.min(axis=-1), corners_y.min(axis=-1))
    high = np.maximum(corners_x.max(axis=-1), corners_y.max(axis=-1))
    outside = np.maximum(WALL_MARGIN - low, 0) + np.maximum(high - (WORKSPACE_SIZE - WALL_MARGIN), 0)
    return 10.0 * outside


def run_episode(env: PushTEnv, seed: int, expert_seed: int = 0) -> tuple[bool, int]:
    """Reset ``env`` to ``seed`` and let a fresh expert act until done: (success, control steps taken)."""
    env.reset(seed)
    expert = PushTExpert(seed=expert_seed)
    while True:
        step = env.step(expert.act(env))
        if step.done:
            return step.success, env.steps
