"""Can on the task seam: robosuite's ``PickPlaceCan`` env, no per-episode measure."""

from carp.tasks.arms.task import RobosuiteArmTask

TASK = RobosuiteArmTask("can", "PickPlaceCan", object_obs_dim=14, expert="carp.tasks.can.expert:CanExpert")
