"""Tasks by name: the registry knows each task's name and where its task object is, and imports it on demand.

Each task has a folder here (``carp.tasks.<name>``) holding its task object (`carp.tasks.base.Task`, in its ``task``
module), its scripted expert, its measures and, where carp defines it, its environment; the robosuite arm tasks share
`carp.tasks.arms`. A new task is such a folder and one line in `TASK_ENTRIES`. Task modules import their simulator only
inside the functions that need it, so reading this registry (the params' validation does) stays cheap: listing the
names imports no task module at all.

A name the registry does not know is a task without a simulator when its demos are a LeRobotDataset folder
(`resolve_task`): the module `OFFLINE_TASKS` names builds it from the dataset's ``meta/info.json``, and rebuilds it
from the env_args the collect stage stores (`task_for_env_args`).
"""

import importlib
from collections.abc import Mapping
from pathlib import Path

from carp.tasks.base import Task, load_entry

TASK_ENTRIES: dict[str, str] = {
    "lift": "carp.tasks.lift.task:TASK",
    "can": "carp.tasks.can.task:TASK",
    "square": "carp.tasks.square.task:TASK",
    "stack": "carp.tasks.stack.task:TASK",
    "nut_assembly": "carp.tasks.nut_assembly.task:TASK",
    "stack_three": "carp.tasks.stack_three.task:TASK",
    "threading": "carp.tasks.threading.task:TASK",
    "pusht": "carp.tasks.pusht.task:TASK",
}
"""Task name -> ``module:attribute`` of its task object, imported on first use."""

TASK_NAMES: tuple[str, ...] = tuple(TASK_ENTRIES)

OFFLINE_TASKS = "carp.tasks.offline"
"""The module of tasks without a simulator: ``ENV_NAME``, ``task_from_source(name, folder)`` and
``task_from_env_args(env_args)``."""


def get_task(name: str) -> Task:
    """The task registered as ``name``.

    Raises:
        ValueError: an unknown name, listing the known ones.
    """
    if name not in TASK_ENTRIES:
        raise ValueError(f"unknown task '{name}'; expected one of {list(TASK_NAMES)}")
    return load_entry(TASK_ENTRIES[name])


def resolve_task(name: str, demo_source: str | Path | None = None) -> Task:
    """The task ``name`` of a run whose demos for it come from ``demo_source`` (its ``data.raw_files`` entry).

    A registered name is that task, whatever the demos; any other name is a task without a simulator, described by
    the LeRobotDataset folder ``demo_source`` (`carp.tasks.offline`).

    Raises:
        ValueError: an unknown name without demos, or whose demos are no LeRobotDataset folder (a typo'd task name);
            the message lists the registered names.
    """
    if name in TASK_ENTRIES:
        return get_task(name)
    offline = importlib.import_module(OFFLINE_TASKS)
    if demo_source is None:
        raise ValueError(
            f"unknown task '{name}': expected one of {list(TASK_NAMES)}, or a task without a simulator whose "
            f"data.raw_files.{name} names a LeRobotDataset folder"
        )
    try:
        return offline.task_from_source(name, Path(demo_source))
    except ValueError as error:
        raise ValueError(
            f"'{name}' is not a registered task {list(TASK_NAMES)}, and as a task without a simulator it needs a "
            f"LeRobotDataset folder: {error}"
        ) from None


def task_for_env_args(env_args: Mapping) -> Task:
    """The task whose demo files carry these env_args (matched by ``env_name``).

    Raises:
        ValueError: env_args of no registered task, naming its ``env_name``.
    """
    env_name = env_args.get("env_name")
    offline = importlib.import_module(OFFLINE_TASKS)
    if env_name == offline.ENV_NAME:
        return offline.task_from_env_args(env_args)
    for name in TASK_NAMES:
        task = get_task(name)
        if task.env_name == env_name:
            return task
    known = {get_task(name).env_name: name for name in TASK_NAMES}
    raise ValueError(f"env_args name env '{env_name}', which no task runs; known: {known}")
