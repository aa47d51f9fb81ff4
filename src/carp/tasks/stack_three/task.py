"""StackThree on the task seam: carp's ``StackThree`` env (`carp.tasks.stack_three.env`), no per-episode measure."""

from carp.tasks.arms.task import RobosuiteArmTask

TASK = RobosuiteArmTask(
    "stack_three",
    "StackThree",
    object_obs_dim=36,
    expert="carp.tasks.stack_three.expert:StackThreeExpert",
    env_module="carp.tasks.stack_three.env",
    paper_demos="any published demonstrations (the paper has no three-cube stack)",
)
