"""The Lift expert: grasp the cube and lift it."""

import math
from collections.abc import Iterator

import numpy as np

from carp.tasks.arms.expert import HOME_YAW_RAD, ScriptedExpert, nearest_symmetric_yaw, yaw_of


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
