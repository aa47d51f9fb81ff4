"""What every task offers collection, ingestion, evaluation and the report: the seam between them and a simulator.

A task is a small object (`Task`) in its own folder, found by name through `carp.tasks.get_task`. Collection asks it
for the env, the seeded reset, the observations, the scripted expert and success; evaluation asks the same, plus its
per-episode measures and its video frames; ingestion and the policies ask its `ActionFormat`, how the actions stored in
a demo file map to the actions a policy learns and back. Nothing outside a task's folder tests a task's name.
"""

import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

ROLLOUTS = "rollouts"
"""A task's `Task.evaluation` when it has a simulator: the evaluate stage rolls policies out in it."""
OFFLINE = "offline"
"""A task's `Task.evaluation` without one: the evaluate stage scores action errors on held-out demos."""


def load_entry(entry: str) -> Any:
    """The attribute a ``module:attribute`` string names (`carp.tasks.TASK_ENTRIES`), its module imported on use."""
    module, attribute = entry.split(":")
    return getattr(importlib.import_module(module), attribute)


def lerobot_adapter(task: "Task") -> Any:
    """The task's ``lerobot_adapter`` (a `carp.data.lerobot.derived.FeatureAdapter`), None for a task without one.

    The collect stage hands it to the LeRobot reader, which uses it only when a dataset lacks the task's obs keys.
    """
    return getattr(task, "lerobot_adapter", None)


def _unchanged(actions: np.ndarray) -> np.ndarray:
    return actions


@dataclass(frozen=True)
class ActionFormat:
    """How a task's stored actions (the env's input) map to the actions a policy learns, and back.

    Attributes:
        space: the action space's name, e.g. ``panda-abs10``; a registered tokenizer carries it and a policy refuses a
            tokenizer of another space.
        stored_dim: width of an action in a demo file and of the env's input.
        policy_dim: ``A``, width of an action the policy learns and predicts.
        to_policy: (..., stored_dim) -> (..., policy_dim); a module-level function, so that worker processes can
            receive it.
        to_env: (..., policy_dim) -> (..., stored_dim), the inverse.
        dimension_names: the policy_dim dimensions' names, in the tokenizer's metrics and figures.
    """

    space: str
    stored_dim: int
    policy_dim: int
    to_policy: Callable[[np.ndarray], np.ndarray] = _unchanged
    to_env: Callable[[np.ndarray], np.ndarray] = _unchanged
    dimension_names: tuple[str, ...] = ()


class Expert(Protocol):
    """A scripted expert bound to one episode of an env that was just reset."""

    name: str

    def act(self) -> np.ndarray:
        """The next action, in the env's input format (`ActionFormat.stored_dim` wide)."""
        ...


class EpisodeMeasure(Protocol):
    """A task's own per-episode measures: `reset` after the episode's reset, `observe` after every control step."""

    def reset(self, env) -> None:
        """Start a new episode in `env` (after its reset)."""
        ...

    def observe(self, env, step: int) -> None:
        """Look at `env` after control step `step` (1-based)."""
        ...

    def values(self) -> dict[str, float]:
        """The episode's measures by name; NaN where the episode gave none."""
        ...


class NoMeasure:
    """The measure of a task that has none: no columns, no work per step."""

    def reset(self, env) -> None:
        """Nothing to prepare."""

    def observe(self, env, step: int) -> None:
        """Nothing to watch."""

    def values(self) -> dict[str, float]:
        """No values."""
        return {}


class FrameSource(Protocol):
    """Draws an env's current state as an image: rollout videos, or the cameras an image policy sees."""

    def frame(self) -> np.ndarray:
        """(h, w, 3) uint8 RGB for a video; (cameras, 3, h, w) uint8 for a policy's cameras."""
        ...

    def close(self) -> None:
        """Release the renderer."""
        ...


class Task(Protocol):
    """A task: its simulator, seeded resets, observations, expert, success, measures and action format.

    Attributes:
        name: the name in ``params.yaml`` (``tasks``) and in every per-task path.
        env_name: the ``env_name`` of the env_args stored in its demo files, which identifies the task of a file.
        default_max_steps: step limit of an evaluation episode unless ``eval.max_steps`` sets one.
        step_limit: a limit no episode may pass (the task's protocol), None for none.
        control_frequency_hz: control steps per second.
        default_obs_keys: the low-dim observation keys a policy sees by default, in order.
        configurable_obs_keys: whether ``data.obs_keys`` (and the image settings) choose the observation; a task with
            one fixed observation ignores them.
        supports_cameras: whether image observations can be rendered for it.
        score_measure: the per-episode measure the report gives as the task's score beside success (Push-T: the
            maximum reward), or None.
        paper_demos: the demonstrations the paper's figures for this task were trained on, which carp's scripted
            demos stand in for.
        evaluation: how the evaluate stage scores a policy on it: `ROLLOUTS` (episodes in its simulator) or `OFFLINE`
            (action errors on held-out demos, for a task without a simulator, `carp.tasks.offline`).

    A task may also offer ``lerobot_adapter``, a `carp.data.lerobot.derived.FeatureAdapter` deriving its obs keys
    from other features of a published LeRobotDataset (Push-T: from ``lerobot/pusht_keypoints``); see
    `lerobot_adapter`.
    """

    name: str
    env_name: str
    default_max_steps: int
    step_limit: int | None
    control_frequency_hz: int
    default_obs_keys: tuple[str, ...]
    configurable_obs_keys: bool
    supports_cameras: bool
    score_measure: str | None
    paper_demos: str
    evaluation: str

    def action_format(self, controller: str) -> ActionFormat:
        """The action format under ``controller`` (``data.controller``); ValueError naming it when unsupported."""
        ...

    def controller_of(self, env_args: Mapping) -> str:
        """The controller a file's env_args were collected with."""
        ...

    def make_env_args(self, controller: str) -> dict:
        """robomimic-style env_args (JSON-serializable), stored in every demo file."""
        ...

    def make_env(self, env_args: Mapping, camera_names: Sequence[str] = (), image_size: int = 84):
        """Build the env described by ``env_args`` (with these cameras as observations, where supported)."""
        ...

    def reset(self, env, seed: int) -> Mapping[str, np.ndarray]:
        """Reset so that the initial state is a function of ``seed`` only; returns the observation."""
        ...

    def step(self, env, action: np.ndarray) -> tuple[Mapping[str, np.ndarray], float]:
        """Execute one action (stored format); returns the observation after it and the step's reward."""
        ...

    def observations(self, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The low-dim observations of an env observation, key -> (width,) float64, named as in demo files."""
        ...

    def is_success(self, env) -> bool:
        """The task's success check on the env's current state."""
        ...

    def simulator_state(self, env) -> np.ndarray:
        """The flat simulator state stored with every demo step (``states``)."""
        ...

    @property
    def expert_name(self) -> str:
        """The scripted expert's name, stored in the attributes of the demo files it collects."""
        ...

    def make_expert(self, env, seed: int) -> Expert:
        """A scripted expert for the episode just reset with ``seed``."""
        ...

    def measure(self) -> EpisodeMeasure:
        """A fresh measure for one episode."""
        ...

    def video(self, env, camera: str) -> FrameSource:
        """Video frames of ``env`` (``camera`` where the task has several views)."""
        ...

    def cameras(self, env, settings) -> FrameSource:
        """The camera images an image policy sees (`carp.data.rendering.RenderSettings`), drawn as ingest drew them."""
        ...

    def versions(self) -> dict[str, str]:
        """Simulator package versions stored in a demo file's attributes, e.g. ``{"robosuite_version": "1.5.2"}``."""
        ...
