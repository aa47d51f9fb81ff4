"""NutAssembly's scripted expert: both nuts onto their pegs, each placed as Square's (`carp.tasks.square.expert`)."""

import math
from collections.abc import Iterator

import numpy as np

from carp.tasks.arms.expert import HOME_YAW_RAD, wrap_angle
from carp.tasks.square.expert import NutExpert


class NutAssemblyExpert(NutExpert):
    """NutAssembly: the round nut onto the round peg, then the square nut onto the square peg.

    Each nut starts on its own peg's side of the table (robosuite's sampler), so the first carry never crosses the
    second nut. Over a peg the arm is nearly stretched, and heading back from there towards the robot can lock its
    elbow straight (the operational-space controller stalls at that singularity); the round peg, which takes its nut
    in any yaw, is served first with the handle turned towards the robot, where the arm stays bent, and the square
    nut, whose peg leaves less choice, goes last, with nothing to reach for afterwards. Between the two, the wrist turns
    back to home above the round peg: the round nut can leave it turned by up to 135 degrees, and turning that far while
    crossing the table to the square nut would twist the arm instead of the wrist.
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
        yield from self.move(self.command_position, HOME_YAW_RAD)
        yield from self.place_nut(square, env.peg1_body_id, self.handle_grasp_offset_m)

    def _towards_robot(self, handle_yaw: float) -> float:
        """The yaw nearest the handle's own within ``round_handle_spread_rad`` of the direction towards the robot."""
        away = wrap_angle(handle_yaw - math.pi)
        return math.pi + float(np.clip(away, -self.round_handle_spread_rad, self.round_handle_spread_rad))
