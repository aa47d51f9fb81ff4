"""What the robosuite Panda arm tasks share: simulation, task object, expert base and insertion-offset measure.

`simulation` builds and resets the robosuite env from robomimic-style env_args, `task` is the task object every arm
task is an instance of, `expert` the scripted experts' base class and motion primitives, and `insertion_offset` the
precision measure of the tasks that insert one thing into another. Each arm task's own folder (``carp.tasks.<name>``)
holds its task object, its expert and, where carp defines it, its env.
"""
