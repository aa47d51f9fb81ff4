"""The nut experts' shared moves (`NutExpert`, which NutAssembly's expert extends) and NutAssemblySquare's expert.

Square's expert makes two choices that keep its grasps reliable: the nut's target yaw is chosen among the square
peg's 90-degree symmetric options so the handle never points away from the robot (that side is at the edge of the
Panda's workspace), and the grasp aims slightly above and further out along the handle so the fingertips clear the
table and the nut ring; if the gripper closes on nothing, or the nut does not come up with it, it opens, rises and
grasps again.
"""

import math
from collections.abc import Callable, Iterator

import numpy as np

from carp.tasks.arms.expert import HOME_YAW_RAD, ScriptedExpert, gripper_rotation, wrap_angle, yaw_of


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
    # A nut this far above where it rested has come up with the gripper.
    lifted_margin_m = 0.05
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
            rest_height = self.body_position(nut_id)[2]
            yield from self.grasp_from_above(plan_grasp)
            if self.grasped:
                site, nut = self.site_position(), self.body_position(nut_id)
                yield from self.move(np.array([site[0], site[1], self.carry_nut_height_m + site[2] - nut[2]]))
                # Fingers that close on the handle's edge rather than across it feel like a grasp but let go.
                if self.body_position(nut_id)[2] > rest_height + self.lifted_margin_m:
                    break
            yield from self.release_and_rise(0.08)
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
