"""What every scripted arm expert shares: the commanded pose, its encoding as an action, and motion primitives.

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
        rotations = [self.command_rotation] if yaw is None else [gripper_rotation(way) for way in self._yaw_path(yaw)]
        settled_steps = 0
        while True:
            commanded = self._step_command(np.asarray(position, dtype=np.float64), rotations[0], step_m)
            if len(rotations) > 1 and (rotations[0] * self.command_rotation.inv()).magnitude() < 1e-9:
                rotations.pop(0)
                commanded = False
            if commanded:
                close_enough = np.linalg.norm(self.site_position() - position) < self.limits.position_tolerance_m
                if close_enough or settled_steps >= self.limits.settle_limit_steps:
                    return
                settled_steps += 1
            yield self._encode_action()

    def _yaw_path(self, yaw: float) -> list[float]:
        """Gripper yaws the commanded orientation passes through on its way to ``yaw``, ending with ``yaw``.

        The rotation towards a target takes the shorter way round; when that way passes the yaw opposite home, the
        wrist's last joint would run into its limit and the controller would twist the rest of the arm. The
        turn then goes the other way, through the yaw halfway on the home side (each half is under 180 degrees, so
        the shorter way of each is the home side's).
        """
        start = wrap_angle(yaw_of(self.command_rotation.as_quat()) - HOME_YAW_RAD)
        end = wrap_angle(yaw - HOME_YAW_RAD)
        if abs(wrap_angle(end - start)) >= abs(end - start) - 1e-9:
            return [yaw]
        return [HOME_YAW_RAD + (start + end) / 2, yaw]

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
