"""An image policy's rollout observes the cameras the way ingest stored them: one rendering function, same pixels."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from einops import rearrange

from carp.data.rendering import offscreen_backend

SCRIPT = Path(__file__).with_name("camera_rollout.py")
KEYS = ("agentview_image", "robot0_eye_in_hand_image")


@pytest.mark.slow
def test_rollout_cameras_are_the_ingested_frames_of_the_same_states(tmp_path):
    output = tmp_path / "rollout.npz"
    completed = subprocess.run(
        [sys.executable, str(SCRIPT), "10", "3", str(output)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "MUJOCO_GL": offscreen_backend()},
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    recorded = np.load(output)
    assert str(recorded["error"]) == "" and int(recorded["steps"]) == 10
    histories = recorded["histories"]  # (decisions, To, cameras, 3, h, w), one decision per step for the expert
    assert histories.shape == (10, 2, 2, 3, 40, 40) and histories.dtype == np.uint8
    for camera, key in enumerate(KEYS):
        ingested = rearrange(recorded[f"ingested_{key}"], "t h w rgb -> t rgb h w")  # rendered from the states
        # Pixel-exact: the newest image of every decision is the ingest rendering of the state it acted in.
        np.testing.assert_array_equal(histories[:, -1, camera], ingested)
        # The history is the previous step's image (the first one repeated at the reset), oldest first.
        np.testing.assert_array_equal(histories[1:, 0, camera], ingested[:-1])
        np.testing.assert_array_equal(histories[0, 0, camera], ingested[0])
        assert (ingested[0] != ingested[-1]).any()  # the arm moved
    # Rendering is timed per rendered step: the reset's frame and one per step.
    render_seconds = recorded["render_seconds"]
    assert render_seconds.shape == (11,) and (render_seconds > 0).all()
    # The video, drawn in the same process as the policy's cameras, shows the states it was recorded in.
    frames = recorded["frames"]
    assert frames.shape == (10, 256, 256, 3)
    np.testing.assert_array_equal(frames[:-1], recorded["video"])
