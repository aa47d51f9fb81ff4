"""Run in a fresh interpreter with MUJOCO_GL set (mujoco reads it at import): a short scripted Lift episode through
the evaluation's rollout loop with cameras, recording the image history the source receives at every decision and
the simulator state it was rendered from, and a video of the agent-view camera beside them; then the same states
rendered as ingest renders a demo's stored states, and with the video's settings.

Usage: python tests/evaluation/camera_rollout.py STEPS SEED OUTPUT.npz
"""

import sys
from pathlib import Path

import numpy as np

from carp.data.rendering import RenderSettings, render_states
from carp.evaluation.rollout import run_episode
from carp.evaluation.sources import ExpertSource
from carp.tasks import get_task
from carp.tasks.arms import simulation
from carp.tasks.arms.task import video_settings

SETTINGS = RenderSettings(image_size=40)
OBS_STEPS = 2


class RecordingExpert(ExpertSource):
    """The scripted expert, keeping the images it is shown and the state they were rendered from."""

    def __init__(self) -> None:
        super().__init__("lift")
        self.histories: list[np.ndarray] = []
        self.states: list[np.ndarray] = []

    def act(self, observation_history, env, images=None):
        self.histories.append(images)
        self.states.append(env.sim.get_state().flatten())
        return super().act(observation_history, env)


def main() -> None:
    steps, seed, output = int(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3])
    env_args = get_task("lift").make_env_args("absolute")
    env = simulation.make_env(env_args)
    source = RecordingExpert()
    result = run_episode(
        get_task("lift"),
        env,
        source,
        seed,
        ("robot0_eef_pos",),
        OBS_STEPS,
        steps,
        render_camera="agentview",
        cameras=SETTINGS,
    )
    states = np.stack(source.states)
    ingested = render_states(simulation.make_env(env_args), {"seed": seed}, states, SETTINGS)
    # The video frame after step i shows the state the next decision acted in.
    video = render_states(simulation.make_env(env_args), {"seed": seed}, states[1:], video_settings("agentview"))
    np.savez(
        output,
        histories=np.stack(source.histories),
        render_seconds=np.asarray(result.render_seconds),
        steps=result.steps,
        frames=np.stack(result.frames),
        video=video["agentview_image"],
        error=result.error,
        **{f"ingested_{key}": images for key, images in ingested.items()},
    )


if __name__ == "__main__":
    main()
