"""Threading on the task seam: carp's ``Threading`` env, measured by the needle's insertion offset.

The env is `carp.tasks.threading.env`, the insertion pair `carp.tasks.threading.insertion`.
"""

from carp.tasks.arms.insertion_offset import InsertionOffset
from carp.tasks.arms.task import RobosuiteArmTask
from carp.tasks.threading.insertion import THREADING_PAIRS


def insertion_offset() -> InsertionOffset:
    """A fresh measure of the needle's insertion offset."""
    return InsertionOffset(THREADING_PAIRS)


TASK = RobosuiteArmTask(
    "threading",
    "Threading",
    object_obs_dim=23,
    expert="carp.tasks.threading.expert:ThreadingExpert",
    env_module="carp.tasks.threading.env",
    measure_factory=insertion_offset,
    paper_demos="any published demonstrations (the paper has no threading task)",
)
