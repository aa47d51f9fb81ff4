import numpy as np
import pytest
import zarr

from carp.data.demo_sources import LEROBOT, ROBOMIMIC, demo_format, import_demos
from carp.data.robomimic_io import read_demonstrations
from carp.data.robomimic_schema import DatasetError
from tests.conftest import write_synthetic_file
from tests.data.lerobot.fixtures import ENV_ARGS, FIXTURES, OBS_KEYS, TASKS, VERSIONS, data_file, fixture_copy, inputs


def test_the_format_is_chosen_by_what_the_path_holds(tmp_path):
    assert demo_format(FIXTURES / "v3.0") is LEROBOT and demo_format(FIXTURES / "v2.1") is LEROBOT
    write_synthetic_file(tmp_path / "raw.hdf5")
    assert demo_format(tmp_path / "raw.hdf5") is ROBOMIMIC
    (tmp_path / "folder" / "meta").mkdir(parents=True)
    assert demo_format(tmp_path / "folder") is ROBOMIMIC  # no meta/info.json: refused as "not a file"
    with pytest.raises(DatasetError, match=r"folder: not a file"):
        import_demos(tmp_path / "folder", tmp_path / "out.hdf5", OBS_KEYS)


@pytest.mark.parametrize("version", VERSIONS)
def test_a_lerobot_dataset_becomes_a_robomimic_file_with_its_values_and_tasks(tmp_path, version):
    destination = tmp_path / "raw" / "pusht.hdf5"
    import_demos(FIXTURES / version, destination, OBS_KEYS, action_dim=2, env_name="PushT", env_args=lambda: ENV_ARGS)
    demos = read_demonstrations(destination, OBS_KEYS, action_dim=2, env_name="PushT")
    given = inputs(version)
    assert demos.names == ["demo_0", "demo_1", "demo_2"] and demos.masks == {"train": demos.names}
    for index, episode in enumerate(demos.episodes):
        assert np.array_equal(episode.actions, given[f"action_{index}"])
        assert np.array_equal(episode.obs["state"], given[f"observation.state_{index}"])
        assert episode.attrs["lerobot_episode_index"] == index
    assert demos.attrs["lerobot_tasks"] == f'["{TASKS[0]}", "{TASKS[1]}"]'


def test_a_damaged_dataset_leaves_the_destination_as_it_was(tmp_path):
    root = fixture_copy("v3.0", tmp_path)
    data_file(root, 0).write_bytes(b"damaged")
    destination = tmp_path / "raw" / "pusht.hdf5"
    destination.parent.mkdir()
    destination.write_bytes(b"previous")
    staging = tmp_path / "staging"
    with pytest.raises(DatasetError, match=r"file-000\.parquet: cannot be read as Parquet"):
        import_demos(root, destination, OBS_KEYS, action_dim=2, staging_dir=staging, env_args=lambda: ENV_ARGS)
    assert destination.read_bytes() == b"previous"
    assert not staging.exists() or not list(staging.iterdir())


def test_the_filter_key_must_name_a_split(tmp_path):
    with pytest.raises(DatasetError, match=r"filter key 'mask/valid' not found \(masks: \['train'\]\)"):
        import_demos(FIXTURES / "v3.0", tmp_path / "out.hdf5", OBS_KEYS, filter_key="valid", env_args=lambda: ENV_ARGS)
    assert not (tmp_path / "out.hdf5").exists()


def test_a_lerobot_camera_is_stored_as_the_image_key_ingestion_reads(tmp_path):
    destination = tmp_path / "raw" / "pusht.hdf5"
    import_demos(FIXTURES / "v2.1", destination, OBS_KEYS, env_args=lambda: ENV_ARGS, cameras=("top",), image_size=32)
    demos = read_demonstrations(destination, (*OBS_KEYS, "top_image"))
    assert [episode.obs["top_image"].shape for episode in demos.episodes] == [
        (12, 32, 32, 3),
        (9, 32, 32, 3),
        (15, 32, 32, 3),
    ]


def test_an_imported_camera_ingests_into_the_image_buffer(tmp_path):
    from carp.data.ingest import BUFFER_DIRNAME, ingest_demonstrations
    from carp.data.rendering import RenderSettings
    from carp.tasks.pusht.env import make_env_args

    raw = tmp_path / "raw" / "pusht.hdf5"
    demos = import_demos(
        FIXTURES / "v3.0", raw, OBS_KEYS, action_dim=2, env_args=make_env_args, cameras=("top",), image_size=32
    )
    ingest_demonstrations(
        raw, tmp_path / "processed", OBS_KEYS, camera_settings=RenderSettings(cameras=("top",), image_size=32)
    )
    stored = zarr.open(str(tmp_path / "processed" / BUFFER_DIRNAME), mode="r")["data/top_image"][:]
    assert np.array_equal(stored, np.concatenate([episode.obs["top_image"] for episode in demos.episodes]))
