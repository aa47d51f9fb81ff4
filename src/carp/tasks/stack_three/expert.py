"""StackThree's scripted expert: Stack's (`carp.tasks.stack.expert`) twice."""

from collections.abc import Iterator

import numpy as np

from carp.tasks.stack.expert import StackExpert


class StackThreeExpert(StackExpert):
    """StackThree (`carp.tasks.stack_three.env`): Stack's move twice, A onto B, then C onto A, the top of the pair.

    The second move measures A where it came to rest, so it stacks onto the pair as built, not as planned. Between
    the two, the gripper crosses over to above C at the pair's height, already turned to C's grasp yaw: Stack's move
    would otherwise head diagonally down from the pair towards C, and the open fingers, turning on the way, could
    sweep A off B.
    """

    name = "stack_three_scripted"
    # Least height of the grip site (between the fingertips) above the pair's top while crossing over to the third cube.
    cross_clearance_m = 0.05

    def _script(self) -> Iterator[np.ndarray]:
        cube_a, cube_b, cube_c = self.env.cubeA_body_id, self.env.cubeB_body_id, self.env.cubeC_body_id
        yield from self.stack_cube(cube_a, cube_b)
        pair_top = self.body_position(cube_a)[2] + self._half_height(cube_a)
        grasp, yaw = self._plan_cube_grasp(cube_c, cube_a)
        cross_height = max(self.site_position()[2], pair_top + self.cross_clearance_m)
        yield from self.move(np.array([grasp[0], grasp[1], cross_height]), yaw)
        yield from self.stack_cube(cube_c, cube_a)
