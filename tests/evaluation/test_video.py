import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from carp.evaluation.rollout import EpisodeResult
from carp.evaluation.runner import episode_videos, write_episode_videos

SCRIPT = """
import sys
from carp.tasks.arms import simulation
from carp.evaluation.rollout import run_episode
from carp.tasks import get_task
from carp.evaluation.runner import save_gif
from carp.evaluation.sources import ExpertSource

env = simulation.make_env(get_task("lift").make_env_args("absolute"), render_offscreen=True)
keys = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
result = run_episode(get_task("lift"), env, ExpertSource("lift"), 3000, keys, 2, 400, render_camera="agentview")
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


def _episode(seed, frames=3):
    shades = np.linspace(0, 255, frames).astype(np.uint8)
    return EpisodeResult(
        seed=seed,
        success=True,
        steps=frames,
        seconds=0.1,
        frames=[np.full((8, 8, 3), shade, np.uint8) for shade in shades],
    )


def test_a_new_evaluation_replaces_the_videos_of_the_last_one_and_leaves_other_policies_alone(tmp_path):
    first = write_episode_videos([_episode(7), _episode(8), _episode(9, frames=0)], tmp_path, "lift_carp")
    assert [path.name for path in first] == ["lift_carp_seed7.gif", "lift_carp_seed8.gif"]  # seed 9 was not recorded
    other = write_episode_videos([_episode(7)], tmp_path, "lift_next_token")
    second = write_episode_videos([_episode(12, frames=5)], tmp_path, "lift_carp")
    assert episode_videos(tmp_path, "lift_carp") == second == [tmp_path / "lift_carp_seed12.gif"]
    assert episode_videos(tmp_path, "lift_next_token") == other
    with Image.open(second[0]) as gif:
        assert gif.n_frames == 3  # every second of 5 frames
    assert write_episode_videos([_episode(12, frames=0)], tmp_path, "lift_carp") == []
    assert episode_videos(tmp_path, "lift_carp") == []  # video off: no stale episode stays behind
    assert not list(tmp_path.glob(".*.tmp"))


def test_videos_are_listed_in_seed_order_not_name_order(tmp_path):
    write_episode_videos([_episode(100), _episode(99), _episode(1000)], tmp_path, "can_carp")
    assert [path.stem for path in episode_videos(tmp_path, "can_carp")] == [
        "can_carp_seed99",
        "can_carp_seed100",
        "can_carp_seed1000",
    ]
