"""NutAssembly on the task seam: robosuite's ``NutAssembly`` env, measured by each nut's insertion offset."""

from carp.tasks.arms.insertion_offset import InsertionOffset, NutOnPeg
from carp.tasks.arms.task import RobosuiteArmTask

NUT_ASSEMBLY_PAIRS = (NutOnPeg(0, "square_nut_"), NutOnPeg(1, "round_nut_"))
"""NutAssembly: each nut on its own peg, each measured apart."""


def insertion_offsets() -> InsertionOffset:
    """A fresh measure of both nuts' insertion offsets."""
    return InsertionOffset(NUT_ASSEMBLY_PAIRS)


TASK = RobosuiteArmTask(
    "nut_assembly",
    "NutAssembly",
    object_obs_dim=28,
    expert="carp.tasks.nut_assembly.expert:NutAssemblyExpert",
    measure_factory=insertion_offsets,
)
