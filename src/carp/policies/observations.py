"""How a policy turns its normalized observations into the per-step features its network is conditioned on.

Every family conditions on (B, To, F) features; the observation kind decides what produces them, once for all
families:

- ``state``: the normalized low-dim observations themselves (F = Do); no parameters, so a state policy's weights and
  seeded initialization are what they were before observation kinds existed.
- ``image``: the camera encoder of :mod:`carp.vision` (a ResNet trunk and keypoint head per camera) over the images,
  concatenated with the normalized proprioception (F = cameras * feature_dim + Do), trained end to end with the
  family's network.

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

from carp.config import ImageEncoderConfig
from carp.vision.encoder import ImageEncoder


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

    def forward(self, obs: Tensor, images: Tensor | None = None) -> Tensor:
        """(B, To, Do) normalized observations -> the same tensor.

        Raises:
            ValueError: images were given (this policy was trained without cameras).
        """
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

    def forward(self, obs: Tensor, images: Tensor | None = None) -> Tensor:
        """Encode the cameras of every observation step and append the proprioception.

        Args:
            obs: (B, To, Do) normalized proprioception.
            images: (B, To, cameras, 3, h, w) uint8 RGB images, cameras in the config's order (the layout of
                `carp.data.image_windows.ImageWindows.images`).

        Returns:
            (B, To, F) float features.

        Raises:
            ValueError: no images, or images of another layout, camera count, size or dtype.
        """
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


ObservationEncoder = StateObservations | CameraObservations


def observation_feature_dim(obs_dim: int, image_encoder: ImageEncoderConfig | None) -> int:
    """`F` the family's network is conditioned on, without building the encoder.

    Args:
        obs_dim: `Do`, the low-dim features per step (the whole state, or the proprioception with cameras).
        image_encoder: the camera encoder's settings, or None for state observations.
    """
    if image_encoder is None:
        return obs_dim
    return len(image_encoder.cameras) * image_encoder.feature_dim + obs_dim


def build_observation_encoder(obs_dim: int, image_encoder: ImageEncoderConfig | None) -> ObservationEncoder:
    """The encoder of the observation kind: ``state`` without an image encoder config, ``image`` with one."""
    if image_encoder is None:
        return StateObservations(obs_dim)
    return CameraObservations(obs_dim, image_encoder)


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
