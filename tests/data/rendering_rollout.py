"""Run in a fresh interpreter with MUJOCO_GL set (mujoco reads it at import): a short scripted rollout rendered live,
the same states rendered again in a new env (its model rebuilt from the seed, and loaded from the model XML as
robomimic stores it), and the first state as robosuite's own camera observation and as our
renderer with robosuite's settings (shadows, reflections, skybox, anti-aliasing).

Usage: python tests/data/rendering_rollout.py TASK STEPS SEED OUTPUT.npz; also writes OUTPUT.json with the messages
of the renderer's refusals.
"""

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from carp.data.camera_images import render_demos
from carp.data.rendering import CameraRenderer, RenderingError, RenderSettings, load_demo_model
from carp.tasks import get_task
from carp.tasks.arms import simulation


def _message(action) -> str:
    try:
        action()
    except RenderingError as error:
        return str(error)
    return "no error"


def main() -> None:
    task, steps, seed, output = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
    settings = RenderSettings()
    task_spec = get_task(task)
    env_args = task_spec.make_env_args("absolute")
    env = task_spec.make_env(env_args)
    simulation.reset_env(env, seed)
    expert = task_spec.make_expert(env, seed)
    model_xml = env.sim.model.get_xml()  # what robomimic stores as a demo's model_file
    live: dict[str, list[np.ndarray]] = {key: [] for key in settings.image_keys}
    states = []
    with CameraRenderer(env.sim.model._model, settings) as renderer:
        for _ in range(steps):
            states.append(env.sim.get_state().flatten())
            for key, image in renderer.render(states[-1]).items():
                live[key].append(image)
            env.step(expert.act())
        messages = {
            "short state": _message(lambda: renderer.render(states[0][:-1])),
            "unknown camera": _message(lambda: CameraRenderer(env.sim.model._model, RenderSettings(cameras=("top",)))),
            "no model": _message(lambda: load_demo_model(env, {})),
        }
    env.close()
    from_seed, from_xml = render_demos(
        env_args, [({"seed": seed}, np.stack(states)), ({"model_file": model_xml}, np.stack(states))], settings
    )
    camera_env = simulation.make_env(env_args, camera_names=settings.cameras, image_size=settings.image_size)
    observation = simulation.reset_env(camera_env, seed)
    same_first_state = bool(np.array_equal(camera_env.sim.get_state().flatten(), states[0]))
    robosuite_settings = replace(settings, shadows=True, reflections=True, skybox=True, anti_aliasing=True)
    with CameraRenderer(camera_env.sim.model._model, robosuite_settings) as renderer:
        with_extras = renderer.render(states[0])
    camera_env.close()
    arrays = {}
    for key in settings.image_keys:
        arrays[f"live_{key}"] = np.stack(live[key])
        arrays[f"states_{key}"] = from_seed[key]
        arrays[f"xml_{key}"] = from_xml[key]
        arrays[f"robosuite_{key}"] = observation[key]
        arrays[f"extras_{key}"] = with_extras[key]
    np.savez(output, **arrays)
    output.with_suffix(".json").write_text(json.dumps({**messages, "same first state": same_first_state}))


if __name__ == "__main__":
    main()
