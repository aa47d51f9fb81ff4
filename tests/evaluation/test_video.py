import subprocess
import sys

import pytest
from PIL import Image

SCRIPT = """
import sys
from carp import simulation
from carp.evaluation.rollout import run_episode
from carp.evaluation.runner import save_gif
from carp.evaluation.sources import ExpertSource

env = simulation.make_env(simulation.make_env_args("lift"), render_offscreen=True)
keys = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
result = run_episode(env, ExpertSource("lift"), 3000, keys, 2, 400, render_camera="agentview")
assert result.success, result
save_gif(result.frames, sys.argv[1])
print(len(result.frames))
"""


@pytest.mark.slow
def test_offscreen_rendered_episode_becomes_a_gif(tmp_path):
    # MUJOCO_GL is read when mujoco is imported, so rendering runs in a fresh interpreter with EGL selected.
    path = tmp_path / "lift.gif"
    completed = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(path)],
        capture_output=True,
        text=True,
        timeout=300,
        env={"MUJOCO_GL": "egl", "PATH": "/usr/bin:/bin"},
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    steps = int(completed.stdout.strip().splitlines()[-1])
    with Image.open(path) as gif:
        assert gif.n_frames == (steps + 1) // 2  # every second frame is kept
        assert gif.size == (256, 256)
        gif.seek(gif.n_frames - 1)
        assert len(gif.convert("RGB").getcolors(maxcolors=1 << 24)) > 50  # a rendered scene, not a blank frame
