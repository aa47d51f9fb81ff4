"""Square on the task seam: robosuite's ``NutAssemblySquare`` env, measured by the nut's insertion offset."""

from carp.tasks.arms.insertion_offset import InsertionOffset, NutOnPeg
from carp.tasks.arms.task import RobosuiteArmTask

SQUARE_PAIRS = (NutOnPeg(0),)
"""NutAssemblySquare: the square nut on the square peg."""


def insertion_offset() -> InsertionOffset:
    """A fresh measure of the square nut's insertion offset."""
    return InsertionOffset(SQUARE_PAIRS)


TASK = RobosuiteArmTask(
    "square",
    "NutAssemblySquare",
    object_obs_dim=14,
    expert="carp.tasks.square.expert:SquareExpert",
    measure_factory=insertion_offset,
)
