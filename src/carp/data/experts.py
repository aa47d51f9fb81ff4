"""Scripted experts that solve Lift, PickPlaceCan and NutAssemblySquare from privileged object state.

Each expert is a phase machine (approach above, descend, close, lift, carry, place) written as a Python generator:
one ``yield`` per control step, so the phases read top to bottom. The expert keeps a *commanded* grip-site pose that
moves towards each phase's target by a bounded step per control step (translation and rotation), which makes the
demonstrations smooth enough for a policy to learn. Nothing is random: given the env's initial state (fixed by the
reset seed) the actions are a deterministic function of the simulator state.

The commanded pose is emitted in the env's action space:

- absolute: (world position (3), world orientation as a canonical axis-angle vector (3), gripper (1));
- delta: the pose error between the commanded and the current grip-site pose, scaled into the controller's [-1, 1]
  input range. robosuite's delta OSC adds the scaled input to the *achieved* pose, so both modes ask the
  controller for the same goal.

Orientation convention: the gripper points down and its closing axis (the grip site's x-axis) points along the
world yaw ``yaw``. A perfectly vertical gripper is a rotation by exactly pi for every yaw, where the axis-angle sign
is ambiguous and a 7-D -> 10-D -> 7-D round trip could flip it. A small tilt of :data:`GRIPPER_TILT_RAD` about the
site's diagonal (x + y) axis moves that singular case to the single yaw opposite home (-pi/2), which no expert
commands: every commanded yaw stays within 135 degrees of home, where the rotation angle is at least 0.01 rad
below pi.

Square's expert makes two choices that keep its grasps reliable: the nut's target yaw is chosen among the square
peg's 90-degree symmetric options so the handle never points away from the robot (that side is at the edge of the
Panda's workspace), and the grasp aims slightly above and further out along the handle so the fingertips clear the
table and the nut ring; if the gripper closes on nothing it opens, rises and grasps again.
"""

import abc
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

GRIPPER_OPEN = -1.0
GRIPPER_CLOSED = 1.0
GRIPPER_TILT_RAD = 0.03
# Panda home pose: fingers close along world +y.
HOME_YAW_RAD = math.pi / 2
# Sum of both finger joint positions (m) below which a closed gripper holds nothing.
EMPTY_GRASP_WIDTH_M = 0.012
CLOSE_GRIPPER_STEPS = 10
OPEN_GRIPPER_STEPS = 5


@dataclass(frozen=True)
class MotionLimits:
    """Bounds on how far the commanded pose moves per control step (20 Hz), and when a move counts as done.

    Attributes:
        fast_step_m: translation per step in free space.
        slow_step_m: translation per step near objects (descending, placing).
        rotation_step_rad: rotation per step.
        position_tolerance_m: a move ends once the grip site is this close to the target...
        settle_limit_steps: ...or this many steps after the command reached the target.
    """

    fast_step_m: float = 0.016
    slow_step_m: float = 0.008
    rotation_step_rad: float = 0.08
    position_tolerance_m: float = 0.006
    settle_limit_steps: int = 12


def gripper_rotation(yaw: float) -> Rotation:
    """Downward-pointing grip-site orientation whose closing axis lies along world yaw ``yaw`` (radians)."""
    closing_axis = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    approach_axis = np.array([0.0, 0.0, -1.0])
    third_axis = np.cross(approach_axis, closing_axis)
    vertical = Rotation.from_matrix(np.stack([closing_axis, third_axis, approach_axis], axis=1))
    tilt_axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    return vertical * Rotation.from_rotvec(GRIPPER_TILT_RAD * tilt_axis)


def wrap_angle(angle: float) -> float:
    """Map an angle to [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def nearest_symmetric_yaw(yaw: float, period: float, reference: float) -> float:
    """The angle ``yaw + k * period`` (integer k) closest to ``reference``."""
    return reference + wrap_angle_period(yaw - reference, period)


def wrap_angle_period(angle: float, period: float) -> float:
    """Map an angle to [-period/2, period/2)."""
    return (angle + period / 2) % period - period / 2


def yaw_of(quaternion_xyzw: np.ndarray) -> float:
    """World yaw (radians) of an object's x-axis, from its (x, y, z, w) quaternion."""
    x_axis = Rotation.from_quat(quaternion_xyzw).as_matrix()[:, 0]
    return math.atan2(x_axis[1], x_axis[0])


class ScriptedExpert(abc.ABC):
    """Base class: commanded-pose bookkeeping, action encoding and motion primitives.

    Usage: build once per env, call :meth:`reset` after every env reset, then :meth:`act` before every step.
    Subclasses implement :meth:`_script`, a generator yielding one 7-D action per control step.

    Args:
        env: the robosuite env (Panda, OSC pose controller, absolute or delta input).
        limits: motion bounds.
    """

    name = "scripted"

    def __init__(self, env, limits: MotionLimits | None = None) -> None:
        self.env = env
        self.limits = limits or MotionLimits()
        self._bind_robot()
        self._script_steps: Iterator[np.ndarray] | None = None
        self.command_position = np.zeros(3)
        self.command_rotation = Rotation.identity()
        self.gripper = GRIPPER_OPEN
        # Outcome of the latest grasp_from_above: whether something is held, where and at which yaw.
        self.grasped = False
        self.grasp_position = np.zeros(3)
        self.grasp_yaw = HOME_YAW_RAD

    def _bind_robot(self) -> None:
        # A hard reset rebuilds the model and the robot's controllers, so these are looked up again every episode.
        robot = self.env.robots[0]
        self._arm_controller = robot.composite_controller.part_controllers["right"]
        self.controller = self._arm_controller.input_type
        self._site_id = robot.eef_site_id["right"]
        self._gripper_joint_indexes = robot._ref_gripper_joint_pos_indexes["right"]

    def reset(self) -> None:
        """Start a new episode from the env's current (just reset) state."""
        self._bind_robot()
        self.command_position = self.site_position()
        self.command_rotation = self.site_rotation()
        self.gripper = GRIPPER_OPEN
        self.grasped = False
        self._script_steps = self._script()

    def act(self) -> np.ndarray:
        """The next action (7,) for the env's controller; holds the final pose once the script is done."""
        if self._script_steps is None:
            raise RuntimeError("call reset() after resetting the env and before act()")
        try:
            return next(self._script_steps)
        except StopIteration:
            return self._encode_action()

    @abc.abstractmethod
    def _script(self) -> Iterator[np.ndarray]:
        """The task's phase machine: yields one 7-D action per control step."""

    def site_position(self) -> np.ndarray:
        """World position (3,) of the grip site, the point the OSC controller moves."""
        return np.array(self.env.sim.data.site_xpos[self._site_id])

    def site_rotation(self) -> Rotation:
        """World orientation of the grip site."""
        return Rotation.from_matrix(np.array(self.env.sim.data.site_xmat[self._site_id]).reshape(3, 3))

    def gripper_width(self) -> float:
        """Sum of the two finger joint positions (m): about 0.08 open, near 0 closed on nothing."""
        finger_positions = self.env.sim.data.qpos[self._gripper_joint_indexes]
        return float(np.sum(np.abs(finger_positions)))

    def body_position(self, body_id: int) -> np.ndarray:
        """World position (3,) of a simulator body."""
        return np.array(self.env.sim.data.body_xpos[body_id])

    def body_quaternion(self, body_id: int) -> np.ndarray:
        """World orientation of a simulator body as an (x, y, z, w) quaternion (4,)."""
        w, x, y, z = self.env.sim.data.body_xquat[body_id]
        return np.array([x, y, z, w])

    def _encode_action(self) -> np.ndarray:
        if self.controller == "absolute":
            rotation_vector = self.command_rotation.as_rotvec()  # canonical: angle in [0, pi]
            return np.concatenate([self.command_position, rotation_vector, [self.gripper]])
        # The delta controller expresses inputs in its origin (robot base) frame and scales them from [-1, 1].
        origin = np.asarray(self._arm_controller.origin_ori)
        position_error = origin.T @ (self.command_position - self.site_position())
        rotation_error = (self.command_rotation * self.site_rotation().inv()).as_rotvec()
        rotation_error = origin.T @ rotation_error
        controller = self._arm_controller
        output_max = np.asarray(controller.output_max, dtype=np.float64) * np.ones(6)
        input_max = np.asarray(controller.input_max, dtype=np.float64) * np.ones(6)
        scaled = np.concatenate([position_error, rotation_error]) / output_max * input_max
        return np.concatenate([np.clip(scaled, -input_max, input_max), [self.gripper]])

    def _step_command(self, position: np.ndarray, rotation: Rotation, step_m: float) -> bool:
        """Move the commanded pose towards a target by at most one step; True once it equals the target."""
        offset = position - self.command_position
        distance = float(np.linalg.norm(offset))
        if distance <= step_m:
            self.command_position = np.array(position, dtype=np.float64)
        else:
            self.command_position = self.command_position + offset * (step_m / distance)
        rotation_offset = (rotation * self.command_rotation.inv()).as_rotvec()
        angle = float(np.linalg.norm(rotation_offset))
        if angle <= self.limits.rotation_step_rad:
            self.command_rotation = rotation
        else:
            fraction = self.limits.rotation_step_rad / angle
            self.command_rotation = Rotation.from_rotvec(rotation_offset * fraction) * self.command_rotation
        return distance <= step_m and angle <= self.limits.rotation_step_rad

    def move(self, position: np.ndarray, yaw: float | None = None, step_m: float | None = None) -> Iterator[np.ndarray]:
        """Move the grip site to ``position`` with gripper yaw ``yaw`` (None: keep the commanded orientation)."""
        step_m = self.limits.fast_step_m if step_m is None else step_m
        rotation = self.command_rotation if yaw is None else gripper_rotation(yaw)
        settled_steps = 0
        while True:
            commanded = self._step_command(np.asarray(position, dtype=np.float64), rotation, step_m)
            if commanded:
                close_enough = np.linalg.norm(self.site_position() - position) < self.limits.position_tolerance_m
                if close_enough or settled_steps >= self.limits.settle_limit_steps:
                    return
                settled_steps += 1
            yield self._encode_action()

    def set_gripper(self, command: float, steps: int) -> Iterator[np.ndarray]:
        """Hold the commanded pose while the gripper opens or closes."""
        self.gripper = command
        for _ in range(steps):
            yield self._encode_action()

    def grasp_from_above(
        self, plan_grasp: Callable[[], tuple[np.ndarray, float]], clearance_m: float = 0.08
    ) -> Iterator[np.ndarray]:
        """Approach above the grasp point, descend, close. Sets ``self.grasped`` to whether something is held.

        Args:
            plan_grasp: returns the grip-site grasp position (3,) and gripper yaw from the current object state;
                called again before the descent because objects may still be settling after the reset.
            clearance_m: height of the approach point above the grasp point.
        """
        self.gripper = GRIPPER_OPEN
        grasp_position, yaw = plan_grasp()
        yield from self.move(grasp_position + np.array([0.0, 0.0, clearance_m]), yaw)
        grasp_position, yaw = plan_grasp()
        yield from self.move(grasp_position, yaw, self.limits.slow_step_m)
        yield from self.set_gripper(GRIPPER_CLOSED, CLOSE_GRIPPER_STEPS)
        self.grasped = self.gripper_width() > EMPTY_GRASP_WIDTH_M
        self.grasp_position, self.grasp_yaw = grasp_position, yaw

    def release_and_rise(self, rise_m: float) -> Iterator[np.ndarray]:
        """Open the gripper, then move straight up."""
        yield from self.set_gripper(GRIPPER_OPEN, OPEN_GRIPPER_STEPS)
        yield from self.move(self.command_position + np.array([0.0, 0.0, rise_m]))


class LiftExpert(ScriptedExpert):
    """Grasp the cube across two faces (yaw among its 90-degree symmetric options nearest home) and lift it."""

    name = "lift_scripted"
    max_grasp_attempts = 3
    lift_height_m = 0.10

    def _script(self) -> Iterator[np.ndarray]:
        for _ in range(self.max_grasp_attempts):
            yield from self.grasp_from_above(self._plan_grasp, clearance_m=0.06)
            if self.grasped:
                break
            yield from self.release_and_rise(0.06)
        yield from self.move(self.grasp_position + np.array([0.0, 0.0, self.lift_height_m]))

    def _plan_grasp(self) -> tuple[np.ndarray, float]:
        cube_id = self.env.cube_body_id
        yaw = nearest_symmetric_yaw(yaw_of(self.body_quaternion(cube_id)), math.pi / 2, HOME_YAW_RAD)
        return self.body_position(cube_id), yaw


class CanExpert(ScriptedExpert):
    """Grasp the can near its top, carry it over its quadrant of the target bin, lower it, release, rise."""

    name = "can_scripted"
    max_grasp_attempts = 3
    carry_height_m = 1.05
    grasp_above_center_m = 0.02
    release_above_floor_m = 0.10

    def _script(self) -> Iterator[np.ndarray]:
        env = self.env
        target = np.array(env.target_bin_placements[env.object_id], dtype=np.float64)
        for _ in range(self.max_grasp_attempts):
            yield from self.grasp_from_above(self._plan_grasp)
            if self.grasped:
                break
            yield from self.release_and_rise(0.08)
        here = self.site_position()
        yield from self.move(np.array([here[0], here[1], self.carry_height_m]))
        yield from self.move(np.array([target[0], target[1], self.carry_height_m]))
        release = np.array([target[0], target[1], target[2] + self.release_above_floor_m])
        yield from self.move(release, step_m=self.limits.slow_step_m)
        yield from self.release_and_rise(0.10)

    def _plan_grasp(self) -> tuple[np.ndarray, float]:
        can = self.body_position(self.env.obj_body_id[self.env.obj_to_use])
        # Fingers spread along the closing axis; keep that axis parallel to the nearest bin wall.
        bin_center = np.asarray(self.env.bin1_pos, dtype=np.float64)
        half_size = np.asarray(self.env.bin_size[:2], dtype=np.float64) / 2
        wall_distance = half_size - np.abs(can[:2] - bin_center[:2])
        yaw = HOME_YAW_RAD if wall_distance[0] < wall_distance[1] else 0.0
        return can + np.array([0.0, 0.0, self.grasp_above_center_m]), yaw


class NutExpert(ScriptedExpert):
    """Shared by the nut tasks: grasp a nut's handle, turn it to a peg-symmetric yaw facing the robot, drop it on a peg.

    The square nut fits its peg in four yaws 90 degrees apart and the round nut its peg in any yaw, so both nuts take
    a target handle yaw among the same options.
    """

    max_grasp_attempts = 4
    # Grasp point along the square nut's handle (the handle site is at 0.054 m, the handle ends at 0.079 m) and above
    # the nut's center, so the fingertips clear the ring and the table.
    handle_grasp_offset_m = 0.062
    grasp_above_center_m = 0.012
    carry_nut_height_m = 1.0
    release_nut_height_m = 0.86
    # Handle directions (world yaw) aligned with the square peg; +x (0) would put the gripper at the workspace edge.
    handle_yaw_options = (math.pi / 2, math.pi, -math.pi / 2)
    target_handle_yaw = math.pi

    def place_nut(
        self,
        nut_id: int,
        peg_id: int,
        handle_grasp_offset_m: float,
        target_handle_yaw: Callable[[float], float] | None = None,
    ) -> Iterator[np.ndarray]:
        """Grasp a nut by its handle and drop it on a peg; ends with the gripper open, risen above the peg.

        Args:
            nut_id: the nut's body.
            peg_id: the peg's body.
            handle_grasp_offset_m: distance of the grasp point from the nut's centre along its handle.
            target_handle_yaw: the handle's yaw over the peg given its yaw at the grasp; None: the nearest of
                ``handle_yaw_options``.
        """
        peg = self.body_position(peg_id)
        target = self._nearest_handle_yaw_option if target_handle_yaw is None else target_handle_yaw

        def plan_grasp() -> tuple[np.ndarray, float]:
            return self._plan_nut_grasp(nut_id, handle_grasp_offset_m, target)

        for _ in range(self.max_grasp_attempts):
            yield from self.grasp_from_above(plan_grasp)
            if self.grasped:
                break
            yield from self.release_and_rise(0.08)
        site, nut = self.site_position(), self.body_position(nut_id)
        yield from self.move(np.array([site[0], site[1], self.carry_nut_height_m + site[2] - nut[2]]))
        # Where the grip site must be for the nut to sit over the peg, from the grasp as it actually is.
        nut_in_gripper = self.site_rotation().inv().apply(self.body_position(nut_id) - self.site_position())
        nut_yaw_in_gripper = wrap_angle(yaw_of(self.body_quaternion(nut_id)) - self.grasp_yaw)
        final_yaw = self.grasp_yaw + wrap_angle(self.target_handle_yaw - nut_yaw_in_gripper - self.grasp_yaw)
        final_rotation = gripper_rotation(final_yaw)
        above_peg = np.array([peg[0], peg[1], self.carry_nut_height_m]) - final_rotation.apply(nut_in_gripper)
        yield from self.move(above_peg, final_yaw)
        lowered = np.array([peg[0], peg[1], self.release_nut_height_m]) - final_rotation.apply(nut_in_gripper)
        yield from self.move(lowered, step_m=self.limits.slow_step_m)
        yield from self.release_and_rise(0.08)

    def _nearest_handle_yaw_option(self, handle_yaw: float) -> float:
        return min(self.handle_yaw_options, key=lambda option: abs(wrap_angle(option - handle_yaw)))

    def _plan_nut_grasp(
        self, nut_id: int, handle_grasp_offset_m: float, target_handle_yaw: Callable[[float], float]
    ) -> tuple[np.ndarray, float]:
        nut = self.body_position(nut_id)
        handle_yaw = yaw_of(self.body_quaternion(nut_id))
        self.target_handle_yaw = target_handle_yaw(handle_yaw)
        yaw = self._grasp_yaw(handle_yaw, wrap_angle(self.target_handle_yaw - handle_yaw))
        handle_direction = np.array([math.cos(handle_yaw), math.sin(handle_yaw), 0.0])
        grasp = nut + handle_grasp_offset_m * handle_direction
        grasp[2] = nut[2] + self.grasp_above_center_m
        return grasp, yaw

    @staticmethod
    def _grasp_yaw(handle_yaw: float, turn: float) -> float:
        """Closing axis across the handle; of the two options, the one that strays least from home overall."""
        options = (handle_yaw + math.pi / 2, handle_yaw - math.pi / 2)

        def worst_deviation(option: float) -> float:
            start = wrap_angle(option - HOME_YAW_RAD)
            return max(abs(start), abs(start + turn))

        best = min(options, key=worst_deviation)
        return HOME_YAW_RAD + wrap_angle(best - HOME_YAW_RAD)


class SquareExpert(NutExpert):
    """NutAssemblySquare: the square nut onto the square peg."""

    name = "square_scripted"

    def _script(self) -> Iterator[np.ndarray]:
        env = self.env
        yield from self.place_nut(env.obj_body_id[env.obj_to_use], env.peg1_body_id, self.handle_grasp_offset_m)


class NutAssemblyExpert(NutExpert):
    """NutAssembly: the round nut onto the round peg, then the square nut onto the square peg.

    Each nut starts on its own peg's side of the table (robosuite's sampler), so the first carry never crosses the
    second nut. Over a peg the arm is nearly stretched, and heading back from there towards the robot can lock its
    elbow straight (the operational-space controller stalls at that singularity); the round peg, which takes its nut
    in any yaw, is served first with the handle turned towards the robot, where the arm stays bent, and the square
    nut, whose peg leaves less choice, goes last, with nothing to reach for afterwards.
    """

    name = "nut_assembly_scripted"
    # The round nut's handle reaches 6 mm further out than the square nut's (site at 0.060 m, end at 0.085 m); the
    # grasp takes its outer part, which keeps the arm as close to the robot as the handle allows over the peg.
    round_handle_grasp_offset_m = 0.074
    # Largest angle (radians) between the round nut's handle over its peg and the direction towards the robot (-x).
    round_handle_spread_rad = math.pi / 4

    def _script(self) -> Iterator[np.ndarray]:
        env = self.env
        square, round_ = (env.obj_body_id[nut.name] for nut in env.nuts)
        yield from self.place_nut(round_, env.peg2_body_id, self.round_handle_grasp_offset_m, self._towards_robot)
        yield from self.place_nut(square, env.peg1_body_id, self.handle_grasp_offset_m)

    def _towards_robot(self, handle_yaw: float) -> float:
        """The yaw nearest the handle's own within ``round_handle_spread_rad`` of the direction towards the robot."""
        away = wrap_angle(handle_yaw - math.pi)
        return math.pi + float(np.clip(away, -self.round_handle_spread_rad, self.round_handle_spread_rad))


class StackExpert(ScriptedExpert):
    """Stack: grasp the small cube (A), carry it above the large cube (B), lower it until just above B, release, rise.

    The closing axis is taken across the pair of A's faces most nearly facing B, so that the fingers, spread along
    it, stay clear of B when the cubes lie close together.
    """

    name = "stack_scripted"
    max_grasp_attempts = 3
    # Grasp above the cube's center so the fingertips end above its bottom and never touch the lower cube's top.
    grasp_above_center_m = 0.008
    carry_clearance_m = 0.04
    release_clearance_m = 0.006

    def _script(self) -> Iterator[np.ndarray]:
        yield from self.stack_cube(self.env.cubeA_body_id, self.env.cubeB_body_id)

    def stack_cube(self, cube_id: int, base_id: int) -> Iterator[np.ndarray]:
        """Put the cube body ``cube_id`` onto the body ``base_id``; ends with the gripper open, risen above them."""
        cube_half = self._half_height(cube_id)

        def plan_grasp() -> tuple[np.ndarray, float]:
            return self._plan_cube_grasp(cube_id, base_id)

        for _ in range(self.max_grasp_attempts):
            yield from self.grasp_from_above(plan_grasp, clearance_m=0.06)
            if self.grasped:
                break
            yield from self.release_and_rise(0.06)
        # Where the grip site must be for the cube to sit over the base, from the grasp as it actually is.
        cube_below_site = self.body_position(cube_id) - self.site_position()
        base = self.body_position(base_id)
        base_top = base[2] + self._half_height(base_id)
        carry = np.array([base[0], base[1], base_top + cube_half + self.carry_clearance_m]) - cube_below_site
        here = self.site_position()
        yield from self.move(np.array([here[0], here[1], max(carry[2], here[2])]))
        yield from self.move(carry)
        release = np.array([base[0], base[1], base_top + cube_half + self.release_clearance_m]) - cube_below_site
        yield from self.move(release, step_m=self.limits.slow_step_m)
        yield from self.release_and_rise(0.06)

    def _half_height(self, body_id: int) -> float:
        """Half the height of a cube body (its first geom, robosuite's box objects)."""
        model = self.env.sim.model
        geom = int(np.flatnonzero(np.asarray(model.geom_bodyid) == body_id)[0])
        return float(model.geom_size[geom][2])

    def _plan_cube_grasp(self, cube_id: int, base_id: int) -> tuple[np.ndarray, float]:
        cube = self.body_position(cube_id)
        towards_base = self.body_position(base_id)[:2] - cube[:2]
        face_yaw = yaw_of(self.body_quaternion(cube_id))
        # Closing along a face normal; of the two normals (mod pi), the one most nearly across the line to the base.
        base_yaw = math.atan2(towards_base[1], towards_base[0])
        across = min(
            (face_yaw, face_yaw + math.pi / 2),
            key=lambda option: abs(math.cos(option - base_yaw)),
        )
        yaw = nearest_symmetric_yaw(across, math.pi, HOME_YAW_RAD)
        return cube + np.array([0.0, 0.0, self.grasp_above_center_m]), yaw


EXPERTS: dict[str, type[ScriptedExpert]] = {
    "lift": LiftExpert,
    "can": CanExpert,
    "square": SquareExpert,
    "stack": StackExpert,
    "nut_assembly": NutAssemblyExpert,
}


def make_expert(task: str, env, limits: MotionLimits | None = None) -> ScriptedExpert:
    """The scripted expert for a task, bound to its env.

    Raises:
        ValueError: no expert for ``task``.
    """
    if task not in EXPERTS:
        raise ValueError(f"no scripted expert for task '{task}'; expected one of {sorted(EXPERTS)}")
    return EXPERTS[task](env, limits)
