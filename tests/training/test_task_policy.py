import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import zarr

from carp.config import DataConfig, ImageEncoderConfig, TrainingConfig
from carp.data.dataset import TaskWindows
from carp.data.ingest import BUFFER_DIRNAME, ingest_demonstrations
from carp.data.normalizer import MinMaxNormalizer
from carp.data.rendering import RenderSettings
from carp.data.replay_buffer import ReplayBuffer
from carp.evaluation.offline import held_out_action_errors
from carp.policies.carp.config import CarpConfig
from carp.policies.diffusion.config import DiffusionUNetConfig
from carp.policies.registry import load_policy
from carp.tokenizer.artifact import TokenizerMismatchError
from carp.tracking.registry import TokenizerReference
from carp.training.checkpoint import CheckpointError
from carp.training.policy_inputs import (
    MultiTaskPolicyInputs,
    ReferencedTokenizer,
    TaskPolicyInputs,
    load_task_policy_inputs,
)
from carp.training.task_policy import PolicyTrainingRequest, TaskPolicyOutputs, train_and_write
from tests.conftest import write_synthetic_file
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, TINY_ARCHITECTURE, tiny_artifact, tiny_tokenizer

HORIZON, ACTION_DIM = 8, 2
DATA = DataConfig(obs_steps=OBS_STEPS, action_horizon=HORIZON, action_steps=4)
CONFIG = CarpConfig(**TINY_ARCHITECTURE, warmup_steps=2)


class RecordingRun:
    """Stands in for a tracking run: keeps what was logged."""

    run_id = "run-123"

    def __init__(self) -> None:
        self.metrics: list[tuple[dict[str, float], int | None]] = []
        self.artifacts: list[tuple[Path, str | None]] = []

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        self.metrics.append((dict(metrics), step))

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        self.artifacts.append((path, artifact_path))


def _inputs() -> TaskPolicyInputs:
    rng = np.random.default_rng(0)
    artifact = tiny_artifact(tiny_tokenizer())
    windows = TaskWindows(
        train_obs=rng.normal(size=(40, OBS_STEPS, OBS_DIM)),
        train_actions=rng.uniform(-1, 1, size=(40, HORIZON, ACTION_DIM)),
        valid_obs=rng.normal(size=(6, OBS_STEPS, OBS_DIM)),
        valid_actions=rng.uniform(-1, 1, size=(6, HORIZON, ACTION_DIM)),
        obs_normalizer=MinMaxNormalizer(np.full(OBS_DIM, -3.0), np.full(OBS_DIM, 3.0)),
        action_normalizer=MinMaxNormalizer(np.full(ACTION_DIM, -1.0), np.full(ACTION_DIM, 1.0)),
        # Only the attributes are read: the obs keys and widths recorded in the checkpoint's serving protocol.
        buffer=ReplayBuffer(
            np.zeros((0, OBS_DIM)),
            np.zeros((0, ACTION_DIM)),
            np.zeros(0, np.int64),
            np.zeros(0, bool),
            attrs={"obs_keys": ["object", "robot0_eef_pos"], "obs_widths": [1, 2]},
        ),  # fmt: skip
    )
    reference = TokenizerReference("carp-tokenizer-test", "1", "default", "run", artifact.sha256)
    return TaskPolicyInputs("lift", reference, artifact, windows)


def test_trained_policy_and_its_reports_are_written_and_logged(tmp_path):
    inputs, run = _inputs(), RecordingRun()
    outputs = TaskPolicyOutputs(tmp_path / "models" / "policy.pt", tmp_path / "reports")
    # The task's own epoch count wins over `epochs`.
    training = TrainingConfig(epochs=1, batch_size=16, epochs_per_task={"lift": 3})
    request = PolicyTrainingRequest("carp", CONFIG, training, DATA, tmp_path / "states", torch.device("cpu"))
    metrics = train_and_write(request, inputs, outputs, run)

    history = pd.read_csv(outputs.report_dir / "history.csv")
    assert history["epoch"].tolist() == [1, 2, 3]
    assert [step for _, step in run.metrics[:3]] == [1, 2, 3]
    assert run.metrics[3] == ({key: metrics[key] for key in metrics if key.startswith("valid_")}, None)
    assert metrics["final_loss"] == pytest.approx(history["loss"].iloc[-1])
    assert metrics["final_token_accuracy"] == pytest.approx(history["token_accuracy"].iloc[-1])
    assert json.loads((outputs.report_dir / "metrics.json").read_text()) == pytest.approx(metrics)
    assert run.artifacts == [(outputs.checkpoint, "checkpoint")]

    policy = load_policy(outputs.checkpoint)
    assert policy.metadata["task"] == "lift" and policy.metadata["mlflow_run_id"] == "run-123"
    assert policy.metadata["tokenizer"] == asdict(inputs.reference)
    assert policy.metadata["serving"] == {
        "format": 1,
        "observations": "state",
        "obs_keys": ["object", "robot0_eef_pos"],
        "obs_widths": [1, 2],
        "obs_steps": OBS_STEPS,
        "action_horizon": HORIZON,
        "action_steps": 4,
        "cameras": [],
        "image_size": None,
    }
    windows = inputs.windows
    again = held_out_action_errors(policy, windows.valid_obs, windows.valid_actions, OBS_STEPS, DATA.action_steps)
    assert again == pytest.approx({key: metrics[key] for key in again}, rel=1e-5)
    assert sorted(p.name for p in outputs.report_dir.iterdir()) == ["history.csv", "metrics.json"]


def test_a_multi_task_policy_trains_on_the_same_path_with_errors_per_task(tmp_path):
    single = _inputs()
    inputs = MultiTaskPolicyInputs(single.reference, single.artifact, {"lift": single.windows, "can": single.windows})
    run = RecordingRun()
    outputs = TaskPolicyOutputs(tmp_path / "policy.pt", tmp_path / "reports")
    training = TrainingConfig(epochs=1, batch_size=16, epochs_per_task={"can": 2})
    request = PolicyTrainingRequest("carp", CONFIG, training, DATA, tmp_path / "states", torch.device("cpu"))
    metrics = train_and_write(request, inputs, outputs, run)
    # The most epochs any task gets alone; errors per task on its own held-out windows.
    assert pd.read_csv(outputs.report_dir / "history.csv")["epoch"].tolist() == [1, 2]
    assert {key.split("/")[0] for key in metrics if "/" in key} == {"lift", "can"}
    policy = load_policy(outputs.checkpoint)
    assert policy.tasks.names == ("lift", "can") and "task" not in policy.metadata
    policy.select_task("can")
    windows = single.windows
    again = held_out_action_errors(policy, windows.valid_obs, windows.valid_actions, OBS_STEPS, DATA.action_steps)
    assert again == pytest.approx({key: metrics[f"can/{key}"] for key in again}, rel=1e-5)


def _tokenizer(reference: Path, codebook_size: int) -> ReferencedTokenizer:
    """The tokenizer beside `reference`, checked against the test's action space, scales (1, 2) and `codebook_size`."""
    return ReferencedTokenizer(reference.parent / "tokenizer", reference, "test-abs2", (1, 2), codebook_size)


def _tokenizer_files(directory: Path, recorded_sha256: str | None = None) -> Path:
    artifact = tiny_artifact(tiny_tokenizer())
    (directory / "tokenizer").mkdir(parents=True)
    torch.save(artifact.to_payload(), directory / "tokenizer" / "tokenizer.pt")
    reference = TokenizerReference("carp-tokenizer-test", "1", "default", "run", recorded_sha256 or artifact.sha256)
    reference.save(directory / "tokenizer_ref.json")
    return directory / "tokenizer_ref.json"


def test_inputs_refuse_an_unreferenced_or_mismatched_tokenizer_before_reading_the_task(tmp_path):
    missing_task = tmp_path / "processed" / "lift"
    reference = _tokenizer_files(tmp_path / "other", recorded_sha256="0" * 64)
    with pytest.raises(TokenizerMismatchError, match="not the sha256 000000000000"):
        load_task_policy_inputs(missing_task, _tokenizer(reference, 8), DATA)
    reference = _tokenizer_files(tmp_path / "same")
    (reference.parent / "tokenizer" / "tokenizer.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_task_policy_inputs(missing_task, _tokenizer(reference, 8), DATA)
    reference = _tokenizer_files(tmp_path / "fits")
    with pytest.raises(TokenizerMismatchError, match="codebook_size is 8 but the params ask for 16"):
        load_task_policy_inputs(missing_task, _tokenizer(reference, 16), DATA)
    with pytest.raises(FileNotFoundError, match="replay buffer not found"):
        load_task_policy_inputs(missing_task, _tokenizer(reference, 8), DATA)


# 36-pixel crops leave the trunk maps of two positions or more before every stride (bfloat16 convolution
# gradients of strided convolutions on one-position maps are not finite on CPU).
IMAGE_ENCODER = ImageEncoderConfig(image_size=40, crop_size=36, base_channels=16, num_keypoints=2, feature_dim=4)
PROPRIOCEPTION_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
IMAGE_DATA = DataConfig(obs_steps=1, action_horizon=16, action_steps=8)


@pytest.fixture(scope="module")
def image_task(tmp_path_factory) -> tuple[Path, Path]:
    """A task ingested with two 40 x 40 cameras from a synthetic file, and a tokenizer reference beside it."""
    folder = tmp_path_factory.mktemp("image-task")
    write_synthetic_file(folder / "raw.hdf5", lengths=(30, 25, 40, 20), image_size=40)
    ingest_demonstrations(
        folder / "raw.hdf5",
        folder / "processed" / "lift",
        PROPRIOCEPTION_KEYS,
        camera_settings=RenderSettings(image_size=40),
    )
    return folder / "processed" / "lift", _tokenizer_files(folder / "tokenizer-files")


@pytest.mark.slow
def test_an_image_policy_trains_on_the_buffers_camera_windows(image_task, tmp_path):
    task_dir, reference = image_task
    inputs = load_task_policy_inputs(task_dir, _tokenizer(reference, 8), IMAGE_DATA, IMAGE_ENCODER)
    # The image windows are the low-dim windows, in the same order, for both splits.
    windows = inputs.windows
    assert len(inputs.train_images) == len(windows.train_obs) and len(inputs.valid_images) == len(windows.valid_obs)
    for reader, obs in ((inputs.train_images, windows.train_obs), (inputs.valid_images, windows.valid_obs)):
        np.testing.assert_array_equal(reader.read(np.arange(len(obs))).proprioception, obs)

    run = RecordingRun()
    outputs = TaskPolicyOutputs(tmp_path / "policy.pt", tmp_path / "reports")
    config = DiffusionUNetConfig(
        down_dims=(16, 32), kernel_size=3, num_groups=8, step_embedding_dim=16, num_train_steps=10, warmup_steps=0
    )
    training = TrainingConfig(epochs=1, batch_size=32)
    request = PolicyTrainingRequest(
        "diffusion_unet", config, training, IMAGE_DATA, tmp_path / "states", torch.device("cpu")
    )
    metrics = train_and_write(request, inputs, outputs, run)
    assert np.isfinite(metrics["valid_action_rmse"]) and np.isfinite(metrics["final_loss"])
    policy = load_policy(outputs.checkpoint)
    assert policy.observation_encoder.config == IMAGE_ENCODER
    assert policy.obs_normalizer.num_features == windows.train_obs.shape[-1] == 9  # proprioception only
    protocol = policy.metadata["serving"]
    assert (protocol["observations"], protocol["obs_keys"], protocol["obs_widths"]) == (
        "image",
        list(PROPRIOCEPTION_KEYS),
        [3, 4, 2],
    )
    assert (protocol["cameras"], protocol["image_size"]) == (list(IMAGE_ENCODER.cameras), 40)
    assert protocol["control_frequency_hz"] == 20  # Lift's, from the buffer's env_args


def test_an_image_policy_refuses_a_buffer_of_other_cameras(image_task):
    task_dir, reference = image_task
    other = ImageEncoderConfig(cameras=("agentview",), image_size=40, crop_size=36, base_channels=16)
    with pytest.raises(ValueError, match=r"stores images \['agentview_image', 'robot0_eye_in_hand_image'\] at 40 px"):
        load_task_policy_inputs(task_dir, _tokenizer(reference, 8), IMAGE_DATA, other)


def test_inputs_refuse_a_buffer_ingested_before_it_recorded_its_observation_widths(tmp_path):
    write_synthetic_file(tmp_path / "raw.hdf5", lengths=(30, 25, 40, 20))
    task_dir = tmp_path / "processed" / "lift"
    ingest_demonstrations(tmp_path / "raw.hdf5", task_dir, PROPRIOCEPTION_KEYS)
    reference = _tokenizer_files(tmp_path / "tokenizer-files")
    store = zarr.open_group(str(task_dir / BUFFER_DIRNAME), mode="r+")
    del store.attrs["obs_widths"]  # what an ingestion before the serving protocol left
    with pytest.raises(ValueError, match=r"replay.zarr: attrs lack obs_widths .*run the ingest stage again") as error:
        load_task_policy_inputs(task_dir, _tokenizer(reference, 8), DATA)
    assert str(error.value).startswith(str(task_dir / BUFFER_DIRNAME)) and "\n" not in str(error.value)
