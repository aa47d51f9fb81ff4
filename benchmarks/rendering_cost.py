"""Offscreen rendering cost per frame of the image observations, and a grid of sample frames per task.

For each task, runs the scripted expert for `--steps` control steps from one seed (as collection does), keeps the
simulator states, and renders both cameras (`agentview`, `robot0_eye_in_hand`) of every state with
`carp.data.rendering.CameraRenderer`, the function used for the datasets and for evaluation. Two settings per task:

- `lean`: carp's defaults, no shadows, reflections, skybox or multisample anti-aliasing;
- `robosuite`: all four on, which is what robosuite's own camera observations draw.

Columns: `setup ms` builds the renderer (OpenGL context, textures) for the demo's model, once per demo;
`ms/frame` is the median over the timed renders of one state into both cameras' images (the first render, which
compiles shaders, is not timed), `p90 ms` its 90th percentile, `frames/s` the reciprocal of the median. The backend
is MuJoCo's `MUJOCO_GL` (EGL when available, else OSMesa); on a machine without a GPU both run Mesa's software
rasterizer on the CPU. The `lean` frames of each task are saved as a grid PNG to check by eye that they look right.

Usage: python benchmarks/rendering_cost.py [--tasks lift can square] [--steps 40] [--image-size 84] [--repeats 2]
                                           [--grid-dir tmp/rendering] [--seed 0]
"""

import argparse
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

from carp.data.rendering import RenderingError, offscreen_backend

try:
    os.environ.setdefault("MUJOCO_GL", offscreen_backend())  # before mujoco is imported below
except RenderingError as error:
    print(f"error: {error}", file=sys.stderr)
    sys.exit(1)

from carp.data.collect import run_expert_episode  # noqa: E402
from carp.data.rendering import CameraRenderer, RenderSettings, load_demo_model, render_states  # noqa: E402
from carp.reporting.image_grid import save_frame_grid  # noqa: E402
from carp.tasks import TASK_NAMES, get_task  # noqa: E402

VARIANTS = {
    "lean": {},
    "robosuite": {"shadows": True, "reflections": True, "skybox": True, "anti_aliasing": True},
}


def percentile(values: list[float], fraction: float) -> float:
    """The `fraction` quantile (nearest rank) of `values`."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(fraction * (len(ordered) - 1))))]


def expert_states(task: str, steps: int, seed: int):
    """(T, S) states of one scripted episode of at most `steps` steps, and its demo attributes."""
    task_spec = get_task(task)
    env = task_spec.make_env(task_spec.make_env_args("absolute"))
    try:
        episode, _ = run_expert_episode(task_spec, env, seed, steps)
    finally:
        env.close()
    return episode.states, episode.attrs


def arm_env(task: str):
    """A fresh env of the arm task `task`, absolute controller."""
    task_spec = get_task(task)
    return task_spec.make_env(task_spec.make_env_args("absolute"))


def time_variant(task: str, states, attrs: dict, settings: RenderSettings, repeats: int) -> dict:
    """Setup time and per-frame render times of one task and setting."""
    env = arm_env(task)
    try:
        model = load_demo_model(env, attrs)
        started = time.perf_counter()
        renderer = CameraRenderer(model, settings)
        renderer.render(states[0])
        setup = time.perf_counter() - started
        seconds = []
        with renderer:
            for _ in range(repeats):
                for state in states:
                    started = time.perf_counter()
                    renderer.render(state)
                    seconds.append(time.perf_counter() - started)
    finally:
        env.close()
    return {"setup_ms": 1e3 * setup, "frame_ms": [1e3 * value for value in seconds]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["lift", "can", "square"], help="tasks to render")
    parser.add_argument("--steps", type=int, default=40, help="expert control steps rendered per task")
    parser.add_argument("--image-size", type=int, default=84, help="image height and width in pixels")
    parser.add_argument("--repeats", type=int, default=2, help="passes over the states per row")
    parser.add_argument("--grid-dir", type=Path, default=Path("tmp/rendering"), help="where the frame grids go")
    parser.add_argument("--seed", type=int, default=0, help="reset seed of the expert episode")
    args = parser.parse_args()
    arm_tasks = sorted(name for name in TASK_NAMES if get_task(name).supports_cameras)
    unknown = [task for task in args.tasks if task not in arm_tasks]
    if unknown:
        print(f"error: --tasks {unknown}: unknown; expected some of {arm_tasks}", file=sys.stderr)
        return 1
    if args.steps < 1 or args.image_size < 1 or args.repeats < 1:
        print("error: --steps, --image-size and --repeats must be >= 1", file=sys.stderr)
        return 1
    lean = RenderSettings(image_size=args.image_size)
    print(
        f"rendering cost, cameras {', '.join(lean.cameras)} at {args.image_size} x {args.image_size}, "
        f"MUJOCO_GL={os.environ['MUJOCO_GL']}, {args.steps} expert steps x {args.repeats} passes per row"
    )
    header = (
        f"| {'task':<6} | {'settings':<9} | {'frames':>6} | {'setup ms':>8} | {'ms/frame':>8} | {'p90 ms':>8} | "
        f"{'frames/s':>8} |"
    )
    print(header)
    print("|" + "|".join("-" * len(cell) for cell in header.split("|")[1:-1]) + "|")
    grids = []
    for task in args.tasks:
        states, attrs = expert_states(task, args.steps, args.seed)
        for name, changes in VARIANTS.items():
            timing = time_variant(task, states, attrs, replace(lean, **changes), args.repeats)
            median = statistics.median(timing["frame_ms"])
            print(
                f"| {task:<6} | {name:<9} | {len(timing['frame_ms']):>6} | {timing['setup_ms']:8.1f} | "
                f"{median:8.2f} | {percentile(timing['frame_ms'], 0.9):8.2f} | {1e3 / median:8.1f} |",
                flush=True,
            )
        env = arm_env(task)
        try:
            images = render_states(env, attrs, states, lean)
        finally:
            env.close()
        grids.append(save_frame_grid(images, args.grid_dir / f"{task}_frames.png", title=f"{task}, lean settings"))
    print("frame grids: " + ", ".join(str(path) for path in grids))
    return 0


if __name__ == "__main__":
    sys.exit(main())
