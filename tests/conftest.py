"""Shared tiny factories: synthetic robomimic files and tiny model settings."""

from pathlib import Path

import numpy as np
import pytest
import torch

from carp.data.robomimic_io import Episode, write_demonstrations
from tests.pipeline.shared_workspaces import lift_demos, lift_pipeline, pusht_pipeline  # noqa: F401 (end-to-end tier)

OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
OBS_WIDTHS = {"object": 10, "robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2}
IMAGE_KEYS = ("agentview_image", "robot0_eye_in_hand_image")


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tests share two cores with other work; one thread keeps timings stable and avoids oversubscription."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def make_episode(steps: int, rng: np.random.Generator) -> Episode:
    """A smooth synthetic episode with absolute 7-D actions (canonical axis-angle, angle < pi)."""
    time = np.linspace(0.0, 1.0, steps)[:, None]
    position = 0.1 * np.sin(2 * np.pi * time * rng.uniform(0.5, 1.5, size=3)) + rng.normal(size=3) * 0.05
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = 2.0 + 0.5 * np.sin(3 * time)  # (T, 1), stays below pi
    axis_angle = axis[None, :] * angle
    gripper = np.where(time > 0.5, 1.0, -1.0)
    actions = np.concatenate([position, axis_angle, gripper], axis=1)
    obs = {key: rng.normal(size=(steps, width)).cumsum(axis=0) * 0.01 for key, width in OBS_WIDTHS.items()}
    return Episode(
        obs=obs,
        actions=actions,
        states=rng.normal(size=(steps, 5)),
        rewards=np.zeros(steps),
        dones=np.zeros(steps, dtype=np.int64),
        attrs={"seed": int(rng.integers(1 << 30))},
    )


def write_synthetic_file(
    path: Path, lengths=(30, 25, 40, 20), seed: int = 0, image_size: int | None = None
) -> list[Episode]:
    """Write a robomimic-schema file with one synthetic episode per length; returns the episodes.

    With ``image_size``, every episode also has uint8 (T, image_size, image_size, 3) noise images under
    :data:`IMAGE_KEYS`, drawn after the other values so that those stay the same.
    """
    rng = np.random.default_rng(seed)
    episodes = [make_episode(length, rng) for length in lengths]
    if image_size is not None:
        for episode in episodes:
            for key in IMAGE_KEYS:
                episode.obs[key] = rng.integers(0, 256, (episode.length, image_size, image_size, 3), dtype=np.uint8)
    env_args = {"env_name": "Lift", "type": 1, "env_kwargs": {"robots": ["Panda"]}}
    write_demonstrations(path, episodes, env_args, file_attrs={"expert": "synthetic"}, valid_fraction=0.25)
    return episodes


@pytest.fixture
def synthetic_file(tmp_path: Path) -> Path:
    """A small valid robomimic-schema file with 4 demos (one of them held out in mask/valid)."""
    path = tmp_path / "raw.hdf5"
    write_synthetic_file(path)
    return path


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Modules holding slow tests run first (each module keeps its order): under pytest-xdist with
    ``--no-loadscope-reorder`` (the Makefile's) the long end-to-end modules start at once and the quick ones fill the
    workers' time at the end."""
    slow_modules = {item.nodeid.split("::")[0] for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.nodeid.split("::")[0] not in slow_modules)
