"""An interrupted image ingestion resumes: demos rendered before the interruption are read back, not rendered again."""

from pathlib import Path

import numpy as np
import pytest
import zarr

from carp.data import camera_images, rendering
from carp.data.ingest import BUFFER_DIRNAME, ingest_demonstrations
from carp.data.render_cache import RenderCache, render_key
from carp.data.rendering import RenderSettings
from tests.conftest import IMAGE_KEYS, write_synthetic_file

PROPRIOCEPTION_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
LENGTHS = (30, 25, 40, 20)
SETTINGS = RenderSettings(image_size=6)


class FakeRenderer:
    """Stands in for the simulator: frames derived from each state, every rendered demo recorded.

    ``interrupt_at`` raises KeyboardInterrupt (a Ctrl-C) when that many demos have been rendered.
    """

    def __init__(self, interrupt_at: int | None = None) -> None:
        self.rendered_lengths: list[int] = []
        self.interrupt_at = interrupt_at

    def __call__(self, env, attrs, states, settings):
        if self.interrupt_at is not None and len(self.rendered_lengths) == self.interrupt_at:
            raise KeyboardInterrupt
        self.rendered_lengths.append(len(states))
        size = settings.image_size
        frames = {}
        for camera, key in enumerate(settings.image_keys):
            pattern = np.arange(size * size * 3).reshape(1, size, size, 3)
            values = np.abs(states[:, :1, None, None]) * 97 + camera * 31 + pattern
            frames[key] = (values % 256).astype(np.uint8)
        return frames


class FakeEnv:
    def close(self) -> None:
        pass


@pytest.fixture
def fake_renderer(monkeypatch):
    def install(interrupt_at: int | None = None) -> FakeRenderer:
        renderer = FakeRenderer(interrupt_at)
        monkeypatch.setattr(rendering, "render_states", renderer)
        monkeypatch.setattr(camera_images, "_make_env", lambda env_args: FakeEnv())
        return renderer

    return install


def _ingest(raw: Path, output: Path, staging: Path) -> None:
    ingest_demonstrations(raw, output, PROPRIOCEPTION_KEYS, staging_dir=staging, camera_settings=SETTINGS)


def _images(output: Path) -> dict[str, np.ndarray]:
    group = zarr.open_group(str(output / BUFFER_DIRNAME), mode="r")
    return {key: group[f"data/{key}"][:] for key in IMAGE_KEYS}


def test_an_interrupted_ingestion_renders_only_the_demos_it_had_not_rendered(tmp_path, fake_renderer):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, lengths=LENGTHS)  # states, no images: both cameras are rendered
    reference = tmp_path / "reference"
    uninterrupted = fake_renderer()
    _ingest(raw, reference, tmp_path / "reference-staging")
    assert uninterrupted.rendered_lengths == list(LENGTHS)

    staging, output = tmp_path / "staging", tmp_path / "processed"
    fake_renderer(interrupt_at=2)
    with pytest.raises(KeyboardInterrupt):
        _ingest(raw, output, staging)
    assert not output.exists()  # nothing half-written at the output
    cache_root = staging / f".{output.name}.render-cache"
    (cache_dir,) = list(cache_root.iterdir())
    assert sorted(path.name for path in cache_dir.iterdir()) == ["000000.npz", "000001.npz"]

    resumed = fake_renderer()
    _ingest(raw, output, staging)
    assert resumed.rendered_lengths == list(LENGTHS[2:])  # the first two demos came from the cache
    for key, images in _images(reference).items():
        np.testing.assert_array_equal(_images(output)[key], images)
    assert not cache_root.exists()  # removed once the output is in place
    assert [path.name for path in staging.iterdir()] == []


def test_a_damaged_entry_is_rendered_again_and_a_cache_of_other_inputs_is_dropped(tmp_path, fake_renderer):
    raw = tmp_path / "raw.hdf5"
    write_synthetic_file(raw, lengths=LENGTHS)
    staging, output = tmp_path / "staging", tmp_path / "processed"
    fake_renderer(interrupt_at=3)
    with pytest.raises(KeyboardInterrupt):
        _ingest(raw, output, staging)
    (cache_dir,) = list((staging / f".{output.name}.render-cache").iterdir())
    (cache_dir / "000001.npz").write_bytes(b"truncated")  # e.g. a disk that filled up
    resumed = fake_renderer()
    _ingest(raw, output, staging)
    assert resumed.rendered_lengths == [LENGTHS[1], LENGTHS[3]]

    # Another file (new states) gets a key of its own; opening its cache drops the entries of the old key.
    write_synthetic_file(raw, lengths=LENGTHS, seed=1)
    fake_renderer(interrupt_at=1)
    with pytest.raises(KeyboardInterrupt):
        _ingest(raw, output, staging)
    (new_dir,) = list((staging / f".{output.name}.render-cache").iterdir())
    stale = new_dir.parent / "0123456789abcdef"
    stale.mkdir()
    (stale / "000000.npz").write_bytes(b"old")
    fake_renderer(interrupt_at=2)
    with pytest.raises(KeyboardInterrupt):
        _ingest(raw, output, staging)
    assert [path.name for path in new_dir.parent.iterdir()] == [new_dir.name]
    assert (output / BUFFER_DIRNAME).exists()  # the earlier complete output is still in place


def test_the_key_follows_the_states_the_models_and_the_settings():
    rng = np.random.default_rng(0)
    demos = [({"seed": 1}, rng.normal(size=(5, 4))), ({"seed": 2}, rng.normal(size=(3, 4)))]
    env_args = {"env_name": "Lift"}
    key = render_key(env_args, demos, SETTINGS)
    assert key == render_key(env_args, [(dict(a), s.copy()) for a, s in demos], SETTINGS)
    changed_state = [demos[0], (demos[1][0], demos[1][1] + 1e-9)]
    assert render_key(env_args, changed_state, SETTINGS) != key
    assert render_key(env_args, [demos[0], ({"seed": 3}, demos[1][1])], SETTINGS) != key
    assert render_key(env_args, demos, RenderSettings(image_size=6, shadows=True)) != key
    assert render_key(env_args, demos, RenderSettings(image_size=7)) != key
    assert render_key({"env_name": "Can"}, demos, SETTINGS) != key


def test_an_entry_of_other_shapes_is_not_used(tmp_path):
    cache = RenderCache(tmp_path / "cache", "k", SETTINGS)
    frames = {key: np.zeros((4, 6, 6, 3), dtype=np.uint8) for key in SETTINGS.image_keys}
    cache.save(0, frames)
    assert cache.load(0, steps=4) is not None
    assert cache.load(0, steps=5) is None  # another demo length than saved
    assert cache.load(1, steps=4) is None
    assert [path.name for path in cache.directory.iterdir()] == ["000000.npz"]  # no temporary file left
