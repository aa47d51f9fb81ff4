"""How a policy turns its normalized observations into the per-step features its network is conditioned on.

Every family conditions on (B, To, F) features; the observation kind decides what produces them, once for all
families:

- ``state``: the normalized low-dim observations themselves (F = Do); no parameters, so a state policy's weights and
  seeded initialization are what they were before observation kinds existed.
- ``image``: the camera encoder of :mod:`carp.vision` (a ResNet trunk and keypoint head per camera) over the images,
  concatenated with the normalized proprioception (F = cameras * feature_dim + Do), trained end to end with the
  family's network.

A multi-task policy (`carp.policies.tasks`) wraps either kind in :class:`TaskConditionedObservations`: a learned
embedding of the task id, concatenated to every observation step's features (F grows by its width), as CARP's
multi-task setting conditions on a learnable task embedding concatenated with the observations. This is the one place
a policy is conditioned on its task, so every family is multi-task capable; a single-task policy has no embedding, and
its weights and seeded initialization do not change.

A checkpoint records the kind and the encoder's config and weights (:func:`encoder_checkpoint`), so
:func:`restore_observation_encoder` rebuilds the same encoder; checkpoints from before observation kinds load as
``state``.
"""

import dataclasses
from typing import Any

import numpy as np
import torch
from einops import rearrange
from torch import Tensor, nn

from carp.config.image_encoder import ImageEncoderConfig
from carp.vision.encoder import ImageEncoder


def _refuse_task_ids(task_ids: Tensor | None) -> None:
    if task_ids is not None:
        raise ValueError("this policy is single-task but task ids were given")


class StateObservations(nn.Module):
    """``state``: the normalized observations are the features (F = Do).

    Args:
        obs_dim: `Do`.
    """

    kind = "state"

    def __init__(self, obs_dim: int) -> None:
        super().__init__()
        self.obs_dim = obs_dim
        self.output_dim = obs_dim

    def forward(self, obs: Tensor, images: Tensor | None = None, task_ids: Tensor | None = None) -> Tensor:
        """(B, To, Do) normalized observations -> the same tensor.

        Raises:
            ValueError: images or task ids were given (this policy was trained without cameras, on one task).
        """
        _refuse_task_ids(task_ids)
        if images is not None:
            raise ValueError("this policy was trained on state observations and takes no images")
        return obs

    def config_dict(self) -> None:
        """No settings besides `Do` (which the normalizer stores)."""
        return None


class CameraObservations(nn.Module):
    """``image``: per-camera encoder features, then the normalized proprioception (F = cameras * feature_dim + Do).

    Args:
        obs_dim: `Do`, proprioception features per step.
        config: the camera encoder's settings (cameras, image size, crop, trunk width, keypoints).
    """

    kind = "image"

    def __init__(self, obs_dim: int, config: ImageEncoderConfig) -> None:
        super().__init__()
        self.obs_dim = obs_dim
        self.config = config
        self.encoder = ImageEncoder(config, proprioception_dim=obs_dim)
        self.output_dim = self.encoder.output_dim

    def forward(self, obs: Tensor, images: Tensor | None = None, task_ids: Tensor | None = None) -> Tensor:
        """Encode the cameras of every observation step and append the proprioception.

        Args:
            obs: (B, To, Do) normalized proprioception.
            images: (B, To, cameras, 3, h, w) uint8 RGB images, cameras in the config's order (the layout of
                `carp.data.image_windows.ImageWindows.images`).
            task_ids: must be None (a single-task encoder).

        Returns:
            (B, To, F) float features.

        Raises:
            ValueError: no images, or images of another layout, camera count, size or dtype; task ids.
        """
        _refuse_task_ids(task_ids)
        if images is None:
            raise ValueError(f"this policy sees cameras {list(self.config.cameras)}; images are required")
        size = self.config.image_size
        expected = (*obs.shape[:2], len(self.config.cameras), 3, size, size)
        if tuple(images.shape) != expected or images.dtype != torch.uint8:
            raise ValueError(
                f"images shape {tuple(images.shape)}, dtype {images.dtype}: expected (B, To, cameras, 3, h, w) = "
                f"{expected} uint8"
            )
        per_camera = {
            key: rearrange(images[:, :, index], "b t rgb h w -> b t h w rgb")
            for index, key in enumerate(self.encoder.image_keys)
        }
        return self.encoder(per_camera, obs)  # (B, To, F)

    def config_dict(self) -> dict[str, Any]:
        """The encoder's settings, as a checkpoint stores them."""
        return dataclasses.asdict(self.config)


class TaskConditionedObservations(nn.Module):
    """A multi-task policy's encoder: the kind's features, then a learned task embedding at every step.

    Args:
        observations: the encoder of the observation kind (``state`` or ``image``).
        num_tasks: task ids the embedding has rows for; >= 2.
        embedding_dim: `E`, width of the task embedding.
    """

    def __init__(self, observations: "StateObservations | CameraObservations", num_tasks: int, embedding_dim: int):
        super().__init__()
        self.observations = observations
        self.kind = observations.kind
        self.obs_dim = observations.obs_dim
        self.num_tasks = num_tasks
        # Default N(0, 1) rows: distinct tasks start apart, on the scale of the [-1, 1] normalized observations.
        self.task_embedding = nn.Embedding(num_tasks, embedding_dim)
        self.output_dim = observations.output_dim + embedding_dim

    def forward(self, obs: Tensor, images: Tensor | None = None, task_ids: Tensor | None = None) -> Tensor:
        """The observation kind's (B, To, F - E) features with the task's (E,) embedding appended to every step.

        Args:
            obs: (B, To, Do) normalized low-dim observations.
            images: as the observation kind takes them.
            task_ids: (B,) long task ids in [0, num_tasks) (the policy and the training loop check the range; a
                value check here would stop the ONNX export, which traces this forward).

        Returns:
            (B, To, F) float features.

        Raises:
            ValueError: no task ids, or not one per sample.
        """
        if task_ids is None:
            raise ValueError(f"this policy is multi-task ({self.num_tasks} tasks): pass task ids")
        if tuple(task_ids.shape) != (obs.shape[0],):
            raise ValueError(f"task ids must have shape (B,) = ({obs.shape[0]},), got {tuple(task_ids.shape)}")
        features = self.observations(obs, images)  # (B, To, F - E)
        embedding = self.task_embedding(task_ids).to(features.dtype)  # (B, E)
        steps = embedding.unsqueeze(1).expand(-1, features.shape[1], -1)  # (B, To, E)
        return torch.cat((features, steps), dim=-1)  # (B, To, F)

    def config_dict(self) -> dict[str, Any] | None:
        """The observation kind's settings (the tasks are recorded in the policy's metadata)."""
        return self.observations.config_dict()


ObservationEncoder = StateObservations | CameraObservations | TaskConditionedObservations


def observation_feature_dim(obs_dim: int, image_encoder: ImageEncoderConfig | None, task_embedding_dim: int = 0) -> int:
    """`F` the family's network is conditioned on, without building the encoder.

    Args:
        obs_dim: `Do`, the low-dim features per step (the whole state, or the proprioception with cameras).
        image_encoder: the camera encoder's settings, or None for state observations.
        task_embedding_dim: width of a multi-task policy's task embedding; 0 for a single-task policy.
    """
    if image_encoder is None:
        return obs_dim + task_embedding_dim
    return len(image_encoder.cameras) * image_encoder.feature_dim + obs_dim + task_embedding_dim


def build_observation_encoder(
    obs_dim: int, image_encoder: ImageEncoderConfig | None, num_tasks: int = 0, task_embedding_dim: int = 0
) -> ObservationEncoder:
    """The encoder of the observation kind (``state`` without an image encoder config, ``image`` with one).

    With `num_tasks` > 0 it is wrapped in a :class:`TaskConditionedObservations` of `task_embedding_dim`.
    """
    encoder = StateObservations(obs_dim) if image_encoder is None else CameraObservations(obs_dim, image_encoder)
    if num_tasks == 0:
        return encoder
    return TaskConditionedObservations(encoder, num_tasks, task_embedding_dim)


def encoder_checkpoint(encoder: ObservationEncoder) -> dict[str, Any]:
    """The checkpoint entries of `encoder`: its kind and settings, and its weights (none for ``state``)."""
    return {
        "observations": {"kind": encoder.kind, "image_encoder": encoder.config_dict()},
        "observation_encoder_state": encoder.state_dict(),
    }


def checkpoint_image_encoder(checkpoint: dict[str, Any]) -> ImageEncoderConfig | None:
    """The camera encoder settings a checkpoint records, or None for a state policy (also one written before kinds).

    Raises:
        ValueError: an unknown observation kind.
    """
    observations = checkpoint.get("observations") or {"kind": "state"}
    kind = observations.get("kind")
    if kind == "state":
        return None
    if kind == "image":
        return ImageEncoderConfig(**observations["image_encoder"])
    raise ValueError(f"observations.kind={kind!r}: must be 'state' or 'image'")


def restore_observation_encoder(encoder: ObservationEncoder, checkpoint: dict[str, Any]) -> None:
    """Load the encoder weights a checkpoint holds into `encoder`, strictly (a state policy has none)."""
    encoder.load_state_dict(checkpoint.get("observation_encoder_state", {}), strict=True)


def as_image_tensor(images: np.ndarray | Tensor | None, device: torch.device) -> Tensor | None:
    """Images as a uint8 tensor on `device` (None stays None); the dtype is checked by the encoder."""
    return None if images is None else torch.as_tensor(images).to(device)
