"""Panda arm tasks on the task seam: robosuite's Lift, Can, Square, Stack, NutAssembly; carp's StackThree, Threading.

They run on `carp.simulation` and share everything but their env class, their scripted expert and (Square,
NutAssembly, Threading) the insertion-offset measure. An action is the OSC controller's 7-D input; with
``data.controller: absolute`` the policy learns its 10-D form with a continuous 6-D rotation (`carp.data.rotation`).
"""

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from carp import simulation
from carp.data.rotation import (
    ABSOLUTE_ACTION_DIM,
    ROT6D_ACTION_DIM,
    absolute_to_rot6d_actions,
    rot6d_to_absolute_actions,
)
from carp.tasks.base import ROLLOUTS, ActionFormat, EpisodeMeasure, Expert, NoMeasure

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


def _insertion_offset() -> EpisodeMeasure:
    from carp.tasks.insertion_offset import InsertionOffset  # imported on use: the registry stays light

    return InsertionOffset()


def _nut_assembly_offsets() -> EpisodeMeasure:
    from carp.tasks.insertion_offset import NUT_ASSEMBLY_PAIRS, InsertionOffset

    return InsertionOffset(NUT_ASSEMBLY_PAIRS)


def _threading_offset() -> EpisodeMeasure:
    from carp.tasks.insertion_offset import THREADING_PAIRS, InsertionOffset

    return InsertionOffset(THREADING_PAIRS)


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
    """One of robosuite's Panda tasks; see `carp.tasks.base.Task` for what each member means."""

    name: str
    env_name: str
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

    def action_format(self, controller: str) -> ActionFormat:
        """`ABSOLUTE_ACTIONS` or `DELTA_ACTIONS`."""
        if controller not in _ACTION_FORMATS:
            raise ValueError(f"{self.name}: unknown controller '{controller}'; expected one of {list(_ACTION_FORMATS)}")
        return _ACTION_FORMATS[controller]

    def controller_of(self, env_args: Mapping) -> str:
        """``absolute`` or ``delta`` (`carp.simulation.controller_kind`)."""
        return simulation.controller_kind(env_args)

    def make_env_args(self, controller: str) -> dict:
        """`carp.simulation.make_env_args` for this task."""
        return simulation.make_env_args(self.name, controller)

    def make_env(self, env_args: Mapping, camera_names: Sequence[str] = (), image_size: int = 84):
        """`carp.simulation.make_env`."""
        return simulation.make_env(env_args, camera_names=camera_names, image_size=image_size)

    def reset(self, env, seed: int) -> Mapping[str, np.ndarray]:
        """`carp.simulation.reset_env`."""
        return simulation.reset_env(env, seed)

    def step(self, env, action: np.ndarray) -> tuple[Mapping[str, np.ndarray], float]:
        """One 20 Hz control step; robosuite's sparse reward."""
        observation, reward, _, _ = env.step(action)
        return observation, float(reward)

    def observations(self, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`carp.simulation.low_dim_observations`."""
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
        from carp.data.experts import EXPERTS

        return EXPERTS[self.name].name

    def make_expert(self, env, seed: int) -> Expert:
        """The task's scripted expert, reset for the episode (the script does not draw: ``seed`` is not read)."""
        from carp.data.experts import make_expert

        expert = make_expert(self.name, env)
        expert.reset()
        return expert

    def measure(self) -> EpisodeMeasure:
        """The nut tasks' and Threading's insertion offsets; nothing for Lift, Can, Stack and StackThree."""
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


TASKS = {
    "lift": RobosuiteArmTask("lift", simulation.TASK_ENV_NAMES["lift"]),
    "can": RobosuiteArmTask("can", simulation.TASK_ENV_NAMES["can"]),
    "square": RobosuiteArmTask("square", simulation.TASK_ENV_NAMES["square"], measure_factory=_insertion_offset),
    "stack": RobosuiteArmTask("stack", simulation.TASK_ENV_NAMES["stack"]),
    "nut_assembly": RobosuiteArmTask(
        "nut_assembly", simulation.TASK_ENV_NAMES["nut_assembly"], measure_factory=_nut_assembly_offsets
    ),
    "stack_three": RobosuiteArmTask(
        "stack_three",
        simulation.TASK_ENV_NAMES["stack_three"],
        paper_demos="any published demonstrations (the paper has no three-cube stack)",
    ),
    "threading": RobosuiteArmTask(
        "threading",
        simulation.TASK_ENV_NAMES["threading"],
        measure_factory=_threading_offset,
        paper_demos="any published demonstrations (the paper has no threading task)",
    ),
}
