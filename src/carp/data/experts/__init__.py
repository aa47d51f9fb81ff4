"""Scripted experts that solve the robosuite arm tasks from privileged object state, one file per task.

Lift, PickPlaceCan, NutAssemblySquare, NutAssembly, Stack, and carp's StackThree and Threading;
`carp.data.experts.base` holds what they share.
"""

from carp.data.experts.base import (
    CLOSE_GRIPPER_STEPS,
    EMPTY_GRASP_WIDTH_M,
    GRIPPER_CLOSED,
    GRIPPER_OPEN,
    GRIPPER_TILT_RAD,
    HOME_YAW_RAD,
    OPEN_GRIPPER_STEPS,
    MotionLimits,
    ScriptedExpert,
    gripper_rotation,
    nearest_symmetric_yaw,
    wrap_angle,
    wrap_angle_period,
    yaw_of,
)
from carp.data.experts.can import CanExpert
from carp.data.experts.lift import LiftExpert
from carp.data.experts.nut import NutAssemblyExpert, NutExpert, SquareExpert
from carp.data.experts.stack import StackExpert, StackThreeExpert
from carp.data.experts.threading import ThreadingExpert

__all__ = [
    "CLOSE_GRIPPER_STEPS",
    "EMPTY_GRASP_WIDTH_M",
    "GRIPPER_CLOSED",
    "GRIPPER_OPEN",
    "GRIPPER_TILT_RAD",
    "HOME_YAW_RAD",
    "OPEN_GRIPPER_STEPS",
    "MotionLimits",
    "ScriptedExpert",
    "gripper_rotation",
    "nearest_symmetric_yaw",
    "wrap_angle",
    "wrap_angle_period",
    "yaw_of",
    "CanExpert",
    "LiftExpert",
    "NutAssemblyExpert",
    "NutExpert",
    "SquareExpert",
    "StackExpert",
    "StackThreeExpert",
    "ThreadingExpert",
    "EXPERTS",
    "make_expert",
]

EXPERTS: dict[str, type[ScriptedExpert]] = {
    "lift": LiftExpert,
    "can": CanExpert,
    "square": SquareExpert,
    "stack": StackExpert,
    "nut_assembly": NutAssemblyExpert,
    "stack_three": StackThreeExpert,
    "threading": ThreadingExpert,
}


def make_expert(task: str, env, limits: MotionLimits | None = None) -> ScriptedExpert:
    """The scripted expert for a task, bound to its env.

    Raises:
        ValueError: no expert for ``task``.
    """
    if task not in EXPERTS:
        raise ValueError(f"no scripted expert for task '{task}'; expected one of {sorted(EXPERTS)}")
    return EXPERTS[task](env, limits)
