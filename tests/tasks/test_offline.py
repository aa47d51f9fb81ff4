"""Tasks without a simulator: a name the registry does not know, described by its LeRobotDataset's meta/info.json,
rebuilt from the env_args the collect stage stores, and refused when it is a typo or its folder is no dataset."""

import json
import shutil
from pathlib import Path

import pytest

from carp.tasks import get_task, resolve_task, task_for_env_args
from carp.tasks.base import OFFLINE, ROLLOUTS
from carp.tasks.offline import ENV_NAME, NoSimulatorError, OfflineTask, task_from_source

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "lerobot"


def copy_info(tmp_path: Path, change) -> Path:
    """A dataset folder holding only the v3.0 fixture's info.json, changed by `change(info)`."""
    info = json.loads((FIXTURES / "v3.0/meta/info.json").read_text())
    change(info)
    (tmp_path / "meta").mkdir(parents=True)
    (tmp_path / "meta/info.json").write_text(json.dumps(info))
    return tmp_path


def test_the_task_comes_from_the_datasets_features_in_either_version():
    task = resolve_task("my_robot", FIXTURES / "v3.0")
    assert task == resolve_task("my_robot", str(FIXTURES / "v2.1"))
    assert isinstance(task, OfflineTask) and task.evaluation == OFFLINE
    # The camera feature and LeRobot's bookkeeping columns are no observation; the order is the file's.
    assert task.default_obs_keys == ("state", "environment_state") and not task.configurable_obs_keys
    assert (task.control_frequency_hz, task.supports_cameras) == (10, False)
    actions = task.action_format("absolute")
    assert (actions.space, actions.stored_dim, actions.policy_dim, actions.dimension_names) == (
        "pusht-abs2",
        2,
        2,
        ("x", "y"),
    )
    assert actions.to_policy is actions.to_env  # taken as recorded


def test_the_stored_env_args_rebuild_the_same_task_and_registered_names_stay_registered():
    task = resolve_task("my_robot", FIXTURES / "v3.0")
    env_args = json.loads(json.dumps(task.make_env_args("absolute")))  # as the HDF5 attribute stores it
    assert env_args["env_name"] == ENV_NAME
    assert task_for_env_args(env_args) == task
    # A registered name is its task, whatever its demos are.
    assert resolve_task("pusht", FIXTURES / "v3.0") is get_task("pusht")
    assert get_task("lift").evaluation == get_task("pusht").evaluation == ROLLOUTS


def test_a_dataset_without_robot_type_or_action_names_takes_the_task_name_and_numbered_dimensions(tmp_path):
    def change(info):
        info["robot_type"] = None
        info["features"]["action"]["names"] = None

    task = task_from_source("arm_b", copy_info(tmp_path, change))
    assert task.space == "arm_b-abs2" and task.dimension_names == ("a0", "a1")


def test_a_typo_a_folder_that_is_no_dataset_and_a_bad_name_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"unknown task 'lfit': expected one of \['lift'.*data.raw_files.lfit"):
        resolve_task("lfit")
    (tmp_path / "lift.hdf5").write_bytes(b"")
    with pytest.raises(ValueError, match=r"'my_robot' is not a registered task .*lift.hdf5: not a LeRobotDataset"):
        resolve_task("my_robot", tmp_path / "lift.hdf5")
    with pytest.raises(ValueError, match="task name 'My-Robot': must be lower-case"):
        resolve_task("My-Robot", FIXTURES / "v3.0")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda info: info["features"].pop("action"), r"key 'features.action': expected a numeric feature"),
        (lambda info: info["features"]["action"].update(shape=[2, 1]), r"key 'features.action'"),
        (
            lambda info: [info["features"].pop(f"observation.{key}") for key in ("state", "environment_state")],
            "no low-dimensional observation",
        ),
        (lambda info: info.update(fps=0), "key 'fps'=0"),
    ],
)
def test_an_info_json_without_actions_observations_or_rate_is_refused_naming_the_key(tmp_path, change, message):
    with pytest.raises(ValueError, match=message) as error:
        task_from_source("my_robot", copy_info(tmp_path, change))
    assert "meta/info.json" in str(error.value)


def test_whatever_needs_a_simulator_is_refused_naming_the_task(tmp_path):
    task = resolve_task("my_robot", shutil.copytree(FIXTURES / "v3.0/meta", tmp_path / "meta").parent)
    for call in (
        lambda: task.make_env(task.make_env_args("absolute")),
        lambda: task.reset(None, 0),
        lambda: task.is_success(None),
        lambda: task.make_expert(None, 0),
    ):
        with pytest.raises(NoSimulatorError, match="task 'my_robot' has no simulator"):
            call()
    with pytest.raises(ValueError, match="my_robot: controller 'delta': a task without a simulator takes its actions"):
        task.action_format("delta")
    assert task.measure().values() == {} and task.versions() == {}
