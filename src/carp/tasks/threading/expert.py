"""The Threading expert: grasp the needle by its handle, carry it in front of the ring, push its tip through.

The gripper keeps pointing down throughout: grasped across the handle from above, the needle lies horizontal in the
fingers, and turning the wrist about the vertical turns the needle in the horizontal plane, which is enough to lay it
along the ring's axis (the ring stands upright, its axis horizontal). Every target is planned for the needle's tip
from where the tip actually is in the gripper after the lift (the grasp is never exactly where it was aimed), and
before the push the tip is brought onto the ring's axis in closed loop, correcting the controller's steady offset
under the needle's weight.
"""

import math
from collections.abc import Iterator

import numpy as np

from carp.tasks.arms.expert import HOME_YAW_RAD, ScriptedExpert, gripper_rotation, wrap_angle, yaw_of


class ThreadingExpert(ScriptedExpert):
    """Threading (`carp.tasks.threading.env`): the needle's handle in the fingers, its tip along the ring's axis.

    Phases: grasp the handle from above (closing across it, on the side that keeps the wrist nearest home once the
    needle is turned along the ring's axis), lift above the ring's top, turn and carry the tip to a point on the axis
    in front of the ring, lower it onto the axis, correct the tip's offset from the axis, push through along the axis
    while still correcting it.
    """

    name = "threading_scripted"
    max_grasp_attempts = 3
    # The grip site aims this far above the handle's centre (the handle is 3 cm tall): the fingertips clear the table.
    grasp_above_center_m = 0.005
    # Carry height of the tip above the ring's centre: the bar passes over the ring's top (30 mm above the centre).
    carry_above_ring_m = 0.06
    # Distance of the tip in front of the ring's mid-plane before the push, and beyond it at the push's end.
    approach_distance_m = 0.06
    push_distance_m = 0.035
    # Closed-loop corrections of the tip onto the axis before the push, and the offset they stop at.
    max_alignment_steps = 30
    alignment_tolerance_m = 0.002
    # The push advances the command along the axis by this much per step (slower than a placing move), and each step
    # takes back this fraction of the tip's offset from the axis.
    push_step_m = 0.005
    push_correction_gain = 0.3
    # A needle this far above where it rested has come up with the gripper.
    lifted_margin_m = 0.03

    def _script(self) -> Iterator[np.ndarray]:
        env = self.env
        needle_id = env.needle_body_id
        for _ in range(self.max_grasp_attempts):
            rest_height = self.body_position(needle_id)[2]
            yield from self.grasp_from_above(self._plan_grasp, clearance_m=0.06)
            if self.grasped:
                site = self.site_position()
                lift = env.ring_center()[2] + self.carry_above_ring_m - env.needle_tip()[2]
                yield from self.move(site + np.array([0.0, 0.0, lift]))
                if self.body_position(needle_id)[2] > rest_height + self.lifted_margin_m:
                    break
            yield from self.release_and_rise(0.06)
        center, axis = env.ring_center(), env.ring_axis()
        final_yaw = self._threading_yaw()
        above = center - self.approach_distance_m * axis + np.array([0.0, 0.0, self.carry_above_ring_m])
        yield from self.move(self._site_for_tip(above, final_yaw), final_yaw)
        in_front = center - self.approach_distance_m * axis
        yield from self.move(self._site_for_tip(in_front, final_yaw), step_m=self.limits.slow_step_m)
        yield from self._align_tip(in_front)
        yield from self._push_through(center, axis)

    def _plan_grasp(self) -> tuple[np.ndarray, float]:
        env = self.env
        needle_yaw = yaw_of(self.body_quaternion(env.needle_body_id))
        direction = np.array([math.cos(needle_yaw), math.sin(needle_yaw), 0.0])
        grasp = self.body_position(env.needle_body_id) + env.needle.handle_center_m * direction
        grasp[2] += self.grasp_above_center_m
        ring_yaw = math.atan2(env.ring_axis()[1], env.ring_axis()[0])
        # Closing across the handle: the gripper's yaw is the needle's plus or minus 90 degrees, and after the turn
        # that lays the needle along the ring's axis it is the ring's plus or minus 90 degrees; the option whose
        # worse end is nearer home keeps the wrist in its range.
        options = (needle_yaw + math.pi / 2, needle_yaw - math.pi / 2)

        def worst_deviation(option: float) -> float:
            final = ring_yaw + (option - needle_yaw)
            return max(abs(wrap_angle(option - HOME_YAW_RAD)), abs(wrap_angle(final - HOME_YAW_RAD)))

        yaw = min(options, key=worst_deviation)
        return grasp, HOME_YAW_RAD + wrap_angle(yaw - HOME_YAW_RAD)

    def _threading_yaw(self) -> float:
        """The gripper yaw that lays the held needle's horizontal direction along the ring's axis."""
        env = self.env
        needle = env.needle_axis()
        needle_in_gripper = wrap_angle(math.atan2(needle[1], needle[0]) - yaw_of(self.site_rotation().as_quat()))
        axis = env.ring_axis()
        yaw = math.atan2(axis[1], axis[0]) - needle_in_gripper
        return HOME_YAW_RAD + wrap_angle(yaw - HOME_YAW_RAD)

    def _site_for_tip(self, tip_target: np.ndarray, yaw: float) -> np.ndarray:
        """Where the grip site goes (3,) for the tip to reach ``tip_target`` (3,) with the gripper at ``yaw``."""
        site_rotation = self.site_rotation()
        tip_in_gripper = site_rotation.inv().apply(self.env.needle_tip() - self.site_position())
        return tip_target - gripper_rotation(yaw).apply(tip_in_gripper)

    def _align_tip(self, tip_target: np.ndarray) -> Iterator[np.ndarray]:
        """Shift the commanded pose by the tip's remaining offset from ``tip_target`` until it is within tolerance.

        The operational-space controller settles a few millimetres short of its target with the needle's weight on
        the fingers; commanding the target plus that offset removes it.
        """
        for _ in range(self.max_alignment_steps):
            error = tip_target - self.env.needle_tip()
            if np.linalg.norm(error) < self.alignment_tolerance_m:
                return
            correction = error * min(1.0, self.limits.slow_step_m / float(np.linalg.norm(error)))
            # Half the offset per step: the arm lags its command, so a full step each time would overshoot.
            self.command_position = self.command_position + 0.5 * correction
            yield self._encode_action()

    def _push_through(self, center: np.ndarray, axis: np.ndarray) -> Iterator[np.ndarray]:
        """Advance the tip along the ring's axis (unit (3,)) until it is ``push_distance_m`` past ``center`` (3,).

        Accelerating the held needle pitches it in the fingers and the arm lags its command sideways, which moved
        the tip up to 7 mm off the axis during an open-loop push; each step therefore also takes back part of the
        tip's offset from the axis, in the ring's plane.
        """
        budget_steps = int(2 * (self.approach_distance_m + self.push_distance_m) / self.push_step_m)
        for _ in range(budget_steps):
            offset = self.env.needle_tip() - center
            depth = float(np.dot(offset, axis))
            if depth >= self.push_distance_m:
                return
            radial = offset - depth * axis
            self.command_position = self.command_position + self.push_step_m * axis - self.push_correction_gain * radial
            yield self._encode_action()
