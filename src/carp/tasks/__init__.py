"""Tasks by name: the registry knows each task's name and the module holding it, and imports that module on demand.

A new task is a module with a `Task` object (`carp.tasks.base`) and one line here. Task modules import their simulator
only inside the functions that need it, so reading this registry (the params' validation does) stays cheap.
"""

import importlib
from collections.abc import Mapping

from carp.tasks.base import Task

TASK_MODULES: dict[str, str] = {
    "lift": "carp.tasks.robosuite_arms",
    "can": "carp.tasks.robosuite_arms",
    "square": "carp.tasks.robosuite_arms",
    "stack": "carp.tasks.robosuite_arms",
    "nut_assembly": "carp.tasks.robosuite_arms",
    "stack_three": "carp.tasks.robosuite_arms",
    "threading": "carp.tasks.robosuite_arms",
    "pusht": "carp.tasks.pusht_task",
}
"""Task name -> module whose ``TASKS`` mapping holds the task under that name."""

TASK_NAMES: tuple[str, ...] = tuple(TASK_MODULES)


def get_task(name: str) -> Task:
    """The task registered as ``name``.

    Raises:
        ValueError: an unknown name, listing the known ones.
    """
    if name not in TASK_MODULES:
        raise ValueError(f"unknown task '{name}'; expected one of {list(TASK_NAMES)}")
    return importlib.import_module(TASK_MODULES[name]).TASKS[name]


def task_for_env_args(env_args: Mapping) -> Task:
    """The task whose demo files carry these env_args (matched by ``env_name``).

    Raises:
        ValueError: env_args of no registered task, naming its ``env_name``.
    """
    env_name = env_args.get("env_name")
    for name in TASK_NAMES:
        task = get_task(name)
        if task.env_name == env_name:
            return task
    known = {get_task(name).env_name: name for name in TASK_NAMES}
    raise ValueError(f"env_args name env '{env_name}', which no task runs; known: {known}")
