"""What the Panda arm tasks share on the task seam: `RobosuiteArmTask`, their action formats and their frames.

Each arm task (Lift, Can, Square, Stack, NutAssembly, StackThree, Threading) is a `RobosuiteArmTask` in its own
folder (``carp.tasks.<name>.task``), which names its robosuite env, the width of its ``object`` observation, its
scripted expert (a `carp.tasks.arms.expert.ScriptedExpert`), the module defining its env class when carp defines it,
and its per-episode measure. They run on `carp.tasks.arms.simulation`. An action is the OSC controller's 7-D input; with
``data.controller: absolute`` the policy learns its 10-D form with a continuous 6-D rotation (`carp.data.rotation`).
"""

import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from carp.data.rotation import (
    ABSOLUTE_ACTION_DIM,
    ROT6D_ACTION_DIM,
    absolute_to_rot6d_actions,
    rot6d_to_absolute_actions,
)
from carp.tasks.arms import simulation
from carp.tasks.base import ROLLOUTS, ActionFormat, EpisodeMeasure, Expert, NoMeasure, load_entry

ABSOLUTE_ACTIONS = ActionFormat(
    space=f"panda-abs{ROT6D_ACTION_DIM}",
    stored_dim=ABSOLUTE_ACTION_DIM,
    policy_dim=ROT6D_ACTION_DIM,
    to_policy=absolute_to_rot6d_actions,
    to_env=rot6d_to_absolute_actions,
    dimension_names=("x", "y", "z", "rot0", "rot1", "rot2", "rot3", "rot4", "rot5", "gripper"),
)
DELTA_ACTIONS = ActionFormat(
    space=f"panda-delta{ABSOLUTE_ACTION_DIM}",
    stored_dim=ABSOLUTE_ACTION_DIM,
    policy_dim=ABSOLUTE_ACTION_DIM,
    dimension_names=("dx", "dy", "dz", "drx", "dry", "drz", "gripper"),
)
_ACTION_FORMATS = {"absolute": ABSOLUTE_ACTIONS, "delta": DELTA_ACTIONS}


VIDEO_SIZE = 256
"""Height and width of rollout video frames, in pixels."""


def video_settings(camera: str):
    """How rollout videos are drawn: `camera` at `VIDEO_SIZE` pixels, with shadows, reflections, skybox, anti-aliasing.

    Videos are for people, so they get the full look; an image policy's cameras keep their own lean settings. They go
    through `carp.data.rendering.CameraRenderer` like the policy's cameras because robosuite's offscreen renderer
    draws without making its OpenGL context current: beside another context in the process (the policy's cameras)
    it would draw into that one and read back garbage.
    """
    from carp.data.rendering import RenderSettings

    return RenderSettings(
        cameras=(camera,), image_size=VIDEO_SIZE, shadows=True, reflections=True, skybox=True, anti_aliasing=True
    )


class _StateFrames:
    """Draws a robosuite env's current MuJoCo state with `carp.data.rendering.CameraRenderer`.

    Every reset of a robosuite env builds a new model (object sizes and placements), so one is opened per episode.
    """

    def __init__(self, env, settings, layout: Callable[[dict[str, np.ndarray]], np.ndarray]) -> None:
        from carp.data.rendering import CameraRenderer

        self.env = env
        self.renderer = CameraRenderer(env.sim.model._model, settings)
        self.layout = layout

    def frame(self) -> np.ndarray:
        """The frame of the env's current state."""
        return self.layout(self.renderer.render(self.env.sim.get_state().flatten()))

    def close(self) -> None:
        """Release the renderer's OpenGL context."""
        self.renderer.close()


@dataclass(frozen=True)
class RobosuiteArmTask:
    """One of the Panda arm tasks; see `carp.tasks.base.Task` for what the members it shares with every task mean.

    Attributes:
        object_obs_dim: width of robomimic's ``object`` observation (robosuite's ``object-state``).
        expert: ``module:attribute`` of the task's scripted expert class, imported on use.
        env_module: the module whose import registers the env class with robosuite, for an env carp defines; None for
            robosuite's own.
        measure_factory: builds a fresh per-episode measure (`measure`).
    """

    name: str
    env_name: str
    object_obs_dim: int
    expert: str
    env_module: str | None = None
    measure_factory: Callable[[], EpisodeMeasure] = NoMeasure
    default_max_steps: int = 400
    step_limit: int | None = None
    control_frequency_hz: int = simulation.CONTROL_FREQUENCY_HZ
    default_obs_keys: tuple[str, ...] = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
    configurable_obs_keys: bool = True
    supports_cameras: bool = True
    score_measure: str | None = None
    paper_demos: str = "robomimic's proficient-human demonstrations"
    evaluation: str = ROLLOUTS

    @property
    def low_dim_obs_dim(self) -> int:
        """Width of the default low-dim observation: ``object`` and the proprioception (`simulation.ROBOT_OBS_DIM`)."""
        return self.object_obs_dim + simulation.ROBOT_OBS_DIM

    def action_format(self, controller: str) -> ActionFormat:
        """`ABSOLUTE_ACTIONS` or `DELTA_ACTIONS`."""
        if controller not in _ACTION_FORMATS:
            raise ValueError(f"{self.name}: unknown controller '{controller}'; expected one of {list(_ACTION_FORMATS)}")
        return _ACTION_FORMATS[controller]

    def controller_of(self, env_args: Mapping) -> str:
        """``absolute`` or ``delta`` (`carp.tasks.arms.simulation.controller_kind`)."""
        return simulation.controller_kind(env_args)

    def make_env_args(self, controller: str) -> dict:
        """`carp.tasks.arms.simulation.make_env_args` for this task's env."""
        return simulation.make_env_args(self.env_name, controller)

    def make_env(self, env_args: Mapping, camera_names: Sequence[str] = (), image_size: int = 84):
        """`carp.tasks.arms.simulation.make_env`, after importing ``env_module`` (robosuite then knows its env class).

        Every process that builds an env passes here (evaluation workers, collection, ingestion from stored env_args).
        """
        if self.env_module is not None:
            importlib.import_module(self.env_module)
        return simulation.make_env(env_args, camera_names=camera_names, image_size=image_size)

    def reset(self, env, seed: int) -> Mapping[str, np.ndarray]:
        """`carp.tasks.arms.simulation.reset_env`."""
        return simulation.reset_env(env, seed)

    def step(self, env, action: np.ndarray) -> tuple[Mapping[str, np.ndarray], float]:
        """One 20 Hz control step; robosuite's sparse reward."""
        observation, reward, _, _ = env.step(action)
        return observation, float(reward)

    def observations(self, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`carp.tasks.arms.simulation.low_dim_observations`."""
        return simulation.low_dim_observations(observation)

    def is_success(self, env) -> bool:
        """The env's own success check (robosuite's)."""
        return simulation.is_success(env)

    def simulator_state(self, env) -> np.ndarray:
        """MuJoCo's flattened ``[time, qpos, qvel]``."""
        return np.array(env.sim.get_state().flatten())

    @property
    def expert_name(self) -> str:
        """The scripted expert's name, e.g. ``lift_scripted``."""
        return load_entry(self.expert).name

    def make_expert(self, env, seed: int) -> Expert:
        """The task's scripted expert, reset for the episode (the script does not draw: ``seed`` is not read)."""
        expert = load_entry(self.expert)(env)
        expert.reset()
        return expert

    def measure(self) -> EpisodeMeasure:
        """A fresh ``measure_factory()``: the nut tasks' and Threading's insertion offsets, nothing for the others."""
        return self.measure_factory()

    def video(self, env, camera: str) -> _StateFrames:
        """Frames of ``camera`` (`video_settings`), (256, 256, 3) uint8."""
        return _StateFrames(env, video_settings(camera), lambda images: images[f"{camera}_image"])

    def cameras(self, env, settings) -> _StateFrames:
        """The policy's cameras, (cameras, 3, h, w) uint8, drawn from the state as ingest draws a demo's."""
        from einops import rearrange

        def stacked(images: dict[str, np.ndarray]) -> np.ndarray:
            return np.stack([rearrange(images[key], "h w rgb -> rgb h w") for key in settings.image_keys])

        return _StateFrames(env, settings, stacked)

    def versions(self) -> dict[str, str]:
        """The versions of robosuite and MuJoCo."""
        import mujoco
        import robosuite

        return {"robosuite_version": robosuite.__version__, "mujoco_version": mujoco.__version__}
