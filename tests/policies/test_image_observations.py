"""Image observations through the family seam: every family conditions on the same camera encoder.

With an image encoder in its context, a family's network takes the cameras' features and the proprioception; the
encoder trains end to end with it, its settings and weights travel in the checkpoint, and images are required
(and refused by a state policy).
"""

import dataclasses

import numpy as np
import pytest
import torch

from carp.config import ImageEncoderConfig, TrainingConfig
from carp.policies.observations import observation_feature_dim
from carp.policies.registry import build_policy, get_family, load_policy, train_policy
from carp.training.loop import PolicyTrainingData
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS
from tests.policies.test_registry import TINY_CONFIGS, TINY_INFERENCE, tiny_context, tiny_data

TINY_IMAGES = ImageEncoderConfig(
    cameras=("agentview", "robot0_eye_in_hand"),
    image_size=40,
    crop_size=36,
    base_channels=16,
    num_keypoints=4,
    feature_dim=8,
)
WINDOWS = 16


def obs_batch() -> np.ndarray:
    """(3, To, Do) float32 proprioception."""
    return np.random.default_rng(1).normal(size=(3, OBS_STEPS, OBS_DIM)).astype(np.float32)


def image_context():
    return dataclasses.replace(tiny_context(), image_encoder=TINY_IMAGES)


def window_images(count: int = WINDOWS) -> np.ndarray:
    """(N, To, 2, 3, 40, 40) uint8 images of the windows, fixed per window index."""
    return np.random.default_rng(7).integers(0, 256, size=(count, OBS_STEPS, 2, 3, 40, 40), dtype=np.uint8)


def image_data() -> tuple[PolicyTrainingData, list[np.ndarray]]:
    """The tiny windows with a camera image source that records every batch of indices it is asked for."""
    images, asked = window_images(), []

    def read(indices: np.ndarray) -> np.ndarray:
        asked.append(np.array(indices))
        return images[indices]

    return dataclasses.replace(tiny_data(WINDOWS), images=read), asked


def test_feature_width_is_the_cameras_features_plus_the_proprioception():
    assert observation_feature_dim(OBS_DIM, None) == OBS_DIM
    assert observation_feature_dim(OBS_DIM, TINY_IMAGES) == 2 * 8 + OBS_DIM
    assert image_context().feature_dim == 19 and tiny_context().feature_dim == OBS_DIM


@pytest.mark.slow
@pytest.mark.parametrize("name", list(TINY_CONFIGS))
def test_every_family_trains_its_camera_encoder_end_to_end_and_round_trips(name, tmp_path):
    config = TINY_CONFIGS[name]
    training = TrainingConfig(epochs=2, batch_size=8, checkpoint_every=1)
    teacher, teacher_family = None, get_family(name).teacher
    if teacher_family is not None:
        # A distilled family is given its teacher family's trained policy, on the same cameras.
        teacher_data, _ = image_data()
        teacher_config = TINY_CONFIGS[teacher_family]
        teacher = train_policy(teacher_family, teacher_config, training, image_context(), teacher_data, tmp_path / "t")
    data, asked = image_data()
    policy = train_policy(name, config, training, image_context(), data, tmp_path / "state", teacher=teacher)
    # Every batch read its own windows' images, and every window was read once per epoch.
    assert sorted(np.concatenate(asked).tolist()) == sorted(list(range(WINDOWS)) * 2)
    state_policy = build_policy(name, config, tiny_context())
    assert policy.num_parameters > state_policy.num_parameters

    torch.manual_seed(training.seed)
    untrained = build_policy(name, config, image_context())
    fresh = dict(untrained.observation_encoder.named_parameters())
    moved = [key for key, value in policy.observation_encoder.named_parameters() if not torch.equal(value, fresh[key])]
    assert moved, "the camera encoder did not train with the policy"

    policy.configure_inference(**TINY_INFERENCE.get(name, {}))
    path = tmp_path / "policy.pt"
    policy.save(path)
    loaded = load_policy(path)
    loaded.configure_inference(**TINY_INFERENCE.get(name, {}))
    assert loaded.observation_encoder.config == TINY_IMAGES
    # Loaded for inference: no module trains, so the crops are the centred ones and a repeated call repeats.
    assert [key for key, module in loaded.named_modules() if module.training] == []
    with torch.inference_mode():
        features = [loaded.observation_features(obs_batch(), OBS_STEPS, window_images(3)) for _ in range(2)]
    torch.testing.assert_close(features[0], features[1], rtol=0, atol=0)
    assert loaded.num_parameters == policy.num_parameters
    obs, images = obs_batch(), window_images(3)
    before = policy.predict_action_timed(obs, generator=torch.Generator().manual_seed(3), images=images)
    after = loaded.predict_action_timed(obs, generator=torch.Generator().manual_seed(3), images=images)
    np.testing.assert_array_equal(after.actions, before.actions)
    assert before.actions.shape == (3, 8, 2)
    # The camera encoder's time is reported as a part of the prediction's.
    assert 0 < before.encoding_seconds < before.prediction_seconds
    # The network is conditioned on the cameras: other images give other features; the proprioception comes last.
    with torch.inference_mode():
        features = loaded.observation_features(obs, OBS_STEPS, images)
        other = loaded.observation_features(obs, OBS_STEPS, 255 - images)
    assert features.shape == (3, OBS_STEPS, 19)
    assert not torch.allclose(features[..., :16], other[..., :16])
    torch.testing.assert_close(features[..., 16:], other[..., 16:])
    torch.testing.assert_close(features[..., 16:], loaded.obs_normalizer.normalize(torch.from_numpy(obs)))

    with pytest.raises(ValueError, match="images are required"):
        loaded.predict_action(obs)
    with pytest.raises(ValueError, match=r"expected \(B, To, cameras, 3, h, w\) = \(3, 2, 2, 3, 40, 40\) uint8"):
        loaded.predict_action(obs, images=images[:, :, :1])


@pytest.mark.parametrize("name", list(TINY_CONFIGS))
def test_a_state_policy_refuses_images_and_loads_without_observation_entries(name, tmp_path):
    torch.manual_seed(0)
    policy = build_policy(name, TINY_CONFIGS[name], tiny_context()).train(False)
    obs = np.random.default_rng(1).normal(size=(2, OBS_STEPS, OBS_DIM)).astype(np.float32)
    with pytest.raises(ValueError, match="trained on state observations and takes no images"):
        policy.predict_action(obs, images=window_images(2))
    checkpoint = policy.to_checkpoint()
    assert checkpoint["observations"] == {"kind": "state", "image_encoder": None}
    assert checkpoint["observation_encoder_state"] == {}
    # A checkpoint without the observation entries is a state policy.
    del checkpoint["observations"], checkpoint["observation_encoder_state"]
    torch.save(checkpoint, tmp_path / "policy.pt")
    loaded = load_policy(tmp_path / "policy.pt")
    loaded.configure_inference(**TINY_INFERENCE.get(name, {}))
    policy.configure_inference(**TINY_INFERENCE.get(name, {}))
    np.testing.assert_array_equal(
        loaded.predict_action(obs, generator=torch.Generator().manual_seed(2)),
        policy.predict_action(obs, generator=torch.Generator().manual_seed(2)),
    )


def test_an_unknown_observation_kind_is_refused(tmp_path):
    torch.manual_seed(0)
    checkpoint = build_policy("carp", TINY_CONFIGS["carp"], tiny_context()).to_checkpoint()
    checkpoint["observations"] = {"kind": "depth"}
    torch.save(checkpoint, tmp_path / "policy.pt")
    with pytest.raises(Exception, match="observations.kind='depth': must be 'state' or 'image'"):
        load_policy(tmp_path / "policy.pt")
