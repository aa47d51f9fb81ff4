"""Lift on the task seam: robosuite's ``Lift`` env, no per-episode measure."""

from carp.tasks.arms.task import RobosuiteArmTask

TASK = RobosuiteArmTask("lift", "Lift", object_obs_dim=10, expert="carp.tasks.lift.expert:LiftExpert")
