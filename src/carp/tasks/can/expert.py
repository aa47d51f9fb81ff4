"""The PickPlaceCan expert: the can into its quadrant of the target bin."""

from collections.abc import Iterator

import numpy as np

from carp.tasks.arms.expert import HOME_YAW_RAD, ScriptedExpert


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
