"""Stack on the task seam: robosuite's ``Stack`` env, no per-episode measure."""

from carp.tasks.arms.task import RobosuiteArmTask

TASK = RobosuiteArmTask("stack", "Stack", object_obs_dim=23, expert="carp.tasks.stack.expert:StackExpert")
