import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from carp.data import rendering
from carp.data.rendering import RenderingError, RenderSettings, offscreen_backend

ROLLOUT = Path(__file__).with_name("rendering_rollout.py")
KEYS = ("agentview_image", "robot0_eye_in_hand_image")


def test_render_settings_default_to_robomimics_cameras_without_extras():
    settings = RenderSettings()
    assert settings.image_keys == KEYS and settings.image_size == 84
    assert not (settings.shadows or settings.reflections or settings.skybox or settings.anti_aliasing)
    with pytest.raises(ValueError, match=r"cameras=\['agentview', 'agentview'\]: must name at least one camera"):
        RenderSettings(cameras=("agentview", "agentview"))
    with pytest.raises(ValueError, match="image_size=0: must be >= 1"):
        RenderSettings(image_size=0)


def test_offscreen_backend_prefers_egl_and_names_the_packages_when_none_is_installed(monkeypatch):
    assert offscreen_backend() in ("egl", "osmesa")
    monkeypatch.setattr(
        rendering.ctypes.util, "find_library", lambda name: "libOSMesa.so.8" if name == "OSMesa" else None
    )
    assert offscreen_backend() == "osmesa"
    monkeypatch.setattr(rendering.ctypes.util, "find_library", lambda name: None)
    with pytest.raises(RenderingError, match="install libegl1, libegl-mesa0 and libgl1-mesa-dri"):
        offscreen_backend()


def _run(*arguments: str, backend: str) -> subprocess.CompletedProcess:
    # mujoco reads MUJOCO_GL when first imported, so rendering runs in a fresh interpreter.
    return subprocess.run(
        [sys.executable, *arguments],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "MUJOCO_GL": backend},
    )


@pytest.mark.slow
@pytest.mark.parametrize("task", ["lift", "can"])
def test_stored_states_render_the_live_frames_exactly_and_upright(tmp_path, task):
    output = tmp_path / "frames.npz"
    completed = _run(str(ROLLOUT), task, "12", "7", str(output), backend=offscreen_backend())
    assert completed.returncode == 0, completed.stderr[-3000:]
    frames = np.load(output)
    for key in KEYS:
        live, from_states = frames[f"live_{key}"], frames[f"states_{key}"]
        assert live.dtype == from_states.dtype == np.uint8
        assert live.shape == from_states.shape == (12, 84, 84, 3)
        # Pixel-exact: the stored states, in the model rebuilt from the demo's seed, reproduce what was seen live.
        np.testing.assert_array_equal(from_states, live)
        # The model XML (robomimic's model_file) writes numbers with fewer digits than the model holds, so poses move
        # by a rounding error: pixels on edges and fine textures may change, the pictures stay the same. Tolerance:
        # under 2% of the pixels differ, by 0.25 intensity levels (of 255) on average over the images.
        difference = np.abs(frames[f"xml_{key}"].astype(np.float64) - live)
        assert (difference.max(axis=-1) > 0).mean() < 0.02 and difference.mean() < 0.25
        assert (live[0] != live[-1]).any(axis=-1).sum() > 50  # the arm moved: the frames are not all the same
        assert len(np.unique(live[0].reshape(-1, 3), axis=0)) > 20  # a rendered scene, not a blank frame
    checks = json.loads(output.with_suffix(".json").read_text())
    # robosuite's own observation (its default IMAGE_CONVENTION "opengl") is bottom-up; flipped, it is exactly what
    # our renderer draws with robosuite's settings, and our default settings leave out only the extras.
    assert checks["same first state"]
    for key in KEYS:
        theirs = frames[f"robosuite_{key}"]
        np.testing.assert_array_equal(frames[f"extras_{key}"], theirs[::-1])
        assert np.abs(frames[f"extras_{key}"].astype(np.float64) - theirs).mean() > 20.0
        assert np.abs(frames[f"states_{key}"][0].astype(np.float64) - theirs[::-1]).mean() < 10.0
    assert checks["short state"].startswith("state shape=(")
    assert "expected (" in checks["short state"] and "(time, qpos, qvel)" in checks["short state"]
    assert checks["unknown camera"].startswith("cameras ['top'] are not in the model (it has [")
    assert checks["no model"] == ("the demo has neither a 'model_file' nor a 'seed' attribute: its model is unknown")


@pytest.mark.slow
def test_renderer_refuses_when_mujoco_has_no_offscreen_backend():
    script = (
        "from carp.tasks import get_task; from carp.tasks.arms import simulation;"
        "from carp.data.rendering import CameraRenderer, RenderSettings;"
        "env = simulation.make_env(get_task('lift').make_env_args('absolute')); env.reset();"
        "CameraRenderer(env.sim.model._model, RenderSettings())"
    )
    completed = _run("-c", script, backend="disable")
    assert completed.returncode != 0
    assert "RenderingError: MuJoCo's OpenGL backend is 'disabled', not one of ['egl', 'osmesa']: set MUJOCO_GL" in (
        completed.stderr
    )
