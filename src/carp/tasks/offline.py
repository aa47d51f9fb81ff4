"""Tasks without a simulator: a LeRobotDataset of a robot carp has no environment for, trained on and scored offline.

A name in ``tasks`` that the registry does not know becomes such a task when ``data.raw_files.<name>`` names a
LeRobotDataset folder (`carp.tasks.resolve_task`). Everything the task says about itself comes from the dataset's
``meta/info.json``:

- the action: the ``action`` feature, taken as recorded (absolute, the identity `ActionFormat`); its width is ``A``
  and its space is named ``<robot_type>-abs<A>`` (the task's name where the dataset records no robot type), so that
  a registered tokenizer is shared only by tasks of one robot and width;
- the observation: every low-dimensional ``observation.<key>`` feature, in the file's order, as obs key ``<key>``
  (the reader maps ``state`` back to ``observation.state``); camera features are not read;
- the control rate: the dataset's ``fps``.

The collect stage stores this description as the env_args of ``data/raw/<task>.hdf5`` (``env_name`` `ENV_NAME`), so
ingestion and later stages rebuild the same task from the file alone (`task_from_env_args`). The task has no
environment, expert or success check: its ``evaluation`` is `carp.tasks.base.OFFLINE`, and the evaluate stage
scores a policy by its action error on the held-out episodes (`carp.evaluation.offline`) instead of rolling it out.
"""

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carp.data.lerobot import INFO_PATH
from carp.tasks.base import OFFLINE, ActionFormat, NoMeasure

ENV_NAME = "carp/offline"
"""The ``env_name`` of an offline task's env_args: no environment carp can build."""

NAME_PATTERN = re.compile(r"[a-z][a-z0-9_]*")
"""A task name is part of paths, DVC stage names (``collect@<task>``) and MLflow names: lower-case words only."""

ACTION_FEATURE = "action"
OBSERVATION_PREFIX = "observation."
LOW_DIM_DTYPES = ("float16", "float32", "float64", "int8", "int16", "int32", "int64", "uint8", "bool")


class NoSimulatorError(ValueError):
    """Something that needs an environment was asked of a task without one."""


@dataclass(frozen=True)
class OfflineTask:
    """A task known only from its demos; see `carp.tasks.base.Task` for what each member means.

    Attributes:
        name: the task's name in ``tasks``.
        space: the action space's name, ``<robot_type>-abs<A>``.
        action_dim: ``A``, the width of the dataset's ``action`` feature.
        dimension_names: the ``A`` action dimensions' names (the feature's ``names``, else ``a0``, ``a1``, ...).
        default_obs_keys: the low-dim observation keys, in the dataset's order.
        control_frequency_hz: the dataset's frames per second, rounded.
    """

    name: str
    space: str
    action_dim: int
    dimension_names: tuple[str, ...]
    default_obs_keys: tuple[str, ...]
    control_frequency_hz: int
    env_name: str = ENV_NAME
    # No episode runs, so there is no step limit to keep.
    default_max_steps: int = 0
    step_limit: int | None = None
    configurable_obs_keys: bool = False
    supports_cameras: bool = False
    score_measure: str | None = None
    paper_demos: str = "the recorded demonstrations"
    evaluation: str = OFFLINE

    def action_format(self, controller: str) -> ActionFormat:
        """The identity format of the recorded actions; only ``absolute`` (actions are taken as recorded)."""
        if controller != "absolute":
            raise ValueError(
                f"{self.name}: controller '{controller}': a task without a simulator takes its actions as recorded "
                "('absolute')"
            )
        return ActionFormat(self.space, self.action_dim, self.action_dim, dimension_names=self.dimension_names)

    def controller_of(self, env_args: Mapping) -> str:
        """Always ``absolute``."""
        return "absolute"

    def make_env_args(self, controller: str) -> dict:
        """The task's description as robomimic-style env_args, from which `task_from_env_args` rebuilds it."""
        self.action_format(controller)
        return {
            "env_name": ENV_NAME,
            "type": None,
            "env_kwargs": {
                "task": self.name,
                "action_space": self.space,
                "action_dim": self.action_dim,
                "dimension_names": list(self.dimension_names),
                "obs_keys": list(self.default_obs_keys),
                "control_frequency_hz": self.control_frequency_hz,
            },
        }

    def make_env(self, env_args: Mapping, camera_names: Sequence[str] = (), image_size: int = 84):
        """Refused: there is no environment."""
        raise self._no_simulator("an environment")

    def reset(self, env, seed: int) -> Mapping[str, np.ndarray]:
        """Refused: there is no environment."""
        raise self._no_simulator("a reset")

    def step(self, env, action: np.ndarray) -> tuple[Mapping[str, np.ndarray], float]:
        """Refused: there is no environment."""
        raise self._no_simulator("a step")

    def observations(self, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The low-dim observations, as float64 (T or 1, width) arrays flattened per key."""
        return {key: np.asarray(observation[key], dtype=np.float64).reshape(-1) for key in self.default_obs_keys}

    def is_success(self, env) -> bool:
        """Refused: success is the environment's check."""
        raise self._no_simulator("a success check")

    def simulator_state(self, env) -> np.ndarray:
        """Refused: there is no simulator state."""
        raise self._no_simulator("a simulator state")

    @property
    def expert_name(self) -> str:
        """There is no scripted expert: the demos are the dataset's."""
        return "none (recorded demonstrations)"

    def make_expert(self, env, seed: int):
        """Refused: there is no scripted expert."""
        raise self._no_simulator("a scripted expert")

    def measure(self) -> NoMeasure:
        """No per-episode measure."""
        return NoMeasure()

    def video(self, env, camera: str):
        """Refused: nothing to render."""
        raise self._no_simulator("videos")

    def cameras(self, env, settings):
        """Refused: nothing to render."""
        raise self._no_simulator("camera images")

    def versions(self) -> dict[str, str]:
        """No simulator packages."""
        return {}

    def _no_simulator(self, what: str) -> NoSimulatorError:
        return NoSimulatorError(f"task '{self.name}' has no simulator (demos from a LeRobotDataset): no {what}")


def task_from_source(name: str, source: Path) -> OfflineTask:
    """The offline task ``name`` of the LeRobotDataset folder ``source`` (its ``meta/info.json``).

    Raises:
        ValueError: a name that cannot be a task's, a folder that is no LeRobotDataset, or an ``info.json`` without
            a usable ``action`` feature or low-dim observation; the message names the file and the key.
    """
    if NAME_PATTERN.fullmatch(name) is None:
        raise ValueError(f"task name '{name}': must be lower-case letters, digits and '_', starting with a letter")
    info_file = Path(source) / INFO_PATH
    if not info_file.is_file():
        raise ValueError(f"{source}: not a LeRobotDataset folder (no {INFO_PATH})")
    try:
        info = json.loads(info_file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{info_file}: cannot be read as JSON ({error})") from None
    features = info.get("features") if isinstance(info, dict) else None
    if not isinstance(features, dict):
        raise ValueError(f"{info_file}: key 'features': expected an object")
    action = features.get(ACTION_FEATURE)
    if _width(action) is None:
        raise ValueError(f"{info_file}: key 'features.{ACTION_FEATURE}': expected a numeric feature of shape [A]")
    action_dim = _width(action)
    obs_keys = tuple(
        feature_name.removeprefix(OBSERVATION_PREFIX)
        for feature_name, feature in features.items()
        if feature_name.startswith(OBSERVATION_PREFIX) and _width(feature) is not None
    )
    if not obs_keys:
        raise ValueError(f"{info_file}: key 'features': no low-dimensional observation.<key> feature to observe")
    fps = info.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0:
        raise ValueError(f"{info_file}: key 'fps'={fps!r}: expected a positive number of frames per second")
    robot = info.get("robot_type")
    robot = re.sub(r"[^a-z0-9_]+", "_", robot.lower()).strip("_") if isinstance(robot, str) else ""
    names = action.get("names")
    dimension_names = (
        tuple(names)
        if isinstance(names, list) and len(names) == action_dim and all(isinstance(n, str) and n for n in names)
        else tuple(f"a{index}" for index in range(action_dim))
    )
    return OfflineTask(
        name=name,
        space=f"{robot or name}-abs{action_dim}",
        action_dim=action_dim,
        dimension_names=dimension_names,
        default_obs_keys=obs_keys,
        control_frequency_hz=max(1, round(fps)),
    )


def task_from_env_args(env_args: Mapping) -> OfflineTask:
    """The offline task whose `OfflineTask.make_env_args` gave ``env_args``.

    Raises:
        ValueError: env_args that do not describe one (naming the key).
    """
    kwargs = env_args.get("env_kwargs")
    try:
        return OfflineTask(
            name=str(kwargs["task"]),
            space=str(kwargs["action_space"]),
            action_dim=int(kwargs["action_dim"]),
            dimension_names=tuple(str(name) for name in kwargs["dimension_names"]),
            default_obs_keys=tuple(str(key) for key in kwargs["obs_keys"]),
            control_frequency_hz=int(kwargs["control_frequency_hz"]),
        )
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"env_args of env '{ENV_NAME}': env_kwargs lack or mistype {error}") from None


def _width(feature) -> int | None:
    """The width of a numeric 1-D feature of ``info.json``; None for any other (a camera, a missing feature)."""
    if not isinstance(feature, dict) or feature.get("dtype") not in LOW_DIM_DTYPES:
        return None
    shape = feature.get("shape")
    if not isinstance(shape, list) or len(shape) != 1 or not isinstance(shape[0], int) or shape[0] < 1:
        return None
    return shape[0]
