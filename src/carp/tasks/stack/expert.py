"""The Stack expert: Stack's small cube onto the large one (StackThree's expert repeats that move)."""

import math
from collections.abc import Iterator

import numpy as np

from carp.tasks.arms.expert import HOME_YAW_RAD, ScriptedExpert, nearest_symmetric_yaw, yaw_of


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
