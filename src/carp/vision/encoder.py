"""Observation encoder for image policies: one ResNet trunk and keypoint head per camera, plus proprioception.

Diffusion Policy's and CARP's image experiments encode each camera separately (no shared weights), crop 84 -> 76
pixels (random in training, centred in evaluation), reduce the trunk's feature map to spatial-softmax keypoints,
project them to 64 features, and concatenate the cameras' features with the low-dimensional proprioception
(end-effector pose, gripper). The encoder is trained end to end with the policy. Deviation: images are scaled to
[-1, 1] here (Diffusion Policy's image normalizer does the same with a separate module).
"""

from collections.abc import Mapping

import torch
from einops import rearrange
from torch import Tensor, nn

from carp.config.image_encoder import ImageEncoderConfig
from carp.vision.crop import ImageCrop
from carp.vision.keypoints import SpatialSoftmax
from carp.vision.resnet import ResNetTrunk


class CameraEncoder(nn.Module):
    """uint8 images of one camera -> (N, feature_dim) features: crop, ResNet trunk, spatial softmax, projection."""

    def __init__(self, config: ImageEncoderConfig) -> None:
        super().__init__()
        self.crop = ImageCrop(config.crop_size)
        self.trunk = ResNetTrunk(config.base_channels)
        self.keypoints = SpatialSoftmax(self.trunk.out_channels, config.num_keypoints)
        self.project = nn.Linear(2 * config.num_keypoints, config.feature_dim)

    def forward(self, images: Tensor) -> Tensor:
        """Encode a batch of images.

        Args:
            images: (N, h, w, 3) uint8 RGB images, upright, as the robomimic schema stores them.

        Returns:
            (N, feature_dim) float features.
        """
        pixels = rearrange(images, "n h w c -> n c h w")
        pixels = self.crop(pixels).float() / 127.5 - 1.0  # crop the uint8 images first: fewer pixels to convert
        keypoints = self.keypoints(self.trunk(pixels))  # (N, K, 2)
        return self.project(rearrange(keypoints, "n k xy -> n (k xy)"))


class ImageEncoder(nn.Module):
    """Camera images and proprioception -> one feature vector per observation step.

    Attributes:
        image_keys: obs keys of the cameras, ``<camera>_image``, in the config's camera order.
        output_dim: ``len(cameras) * feature_dim + proprioception_dim``.
    """

    def __init__(self, config: ImageEncoderConfig, proprioception_dim: int) -> None:
        super().__init__()
        if proprioception_dim < 0:
            raise ValueError(f"proprioception_dim={proprioception_dim}: must be >= 0")
        self.config = config
        self.image_keys = config.image_keys
        self.cameras = nn.ModuleDict({key: CameraEncoder(config) for key in self.image_keys})
        self.output_dim = len(self.image_keys) * config.feature_dim + proprioception_dim
        self.proprioception_dim = proprioception_dim

    def forward(self, images: Mapping[str, Tensor], proprioception: Tensor) -> Tensor:
        """Encode observations with any leading batch dimensions (e.g. (B, To)).

        Args:
            images: obs key -> (*batch, image_size, image_size, 3) uint8 images, one entry per camera.
            proprioception: (*batch, proprioception_dim) float, already normalized.

        Returns:
            (*batch, output_dim) float: the cameras' features in config order, then the proprioception.

        Raises:
            ValueError: a camera is missing, an image is not uint8, or an image or the proprioception has the wrong
                shape.
        """
        batch = proprioception.shape[:-1]
        if proprioception.shape[-1] != self.proprioception_dim:
            raise ValueError(
                f"proprioception shape {tuple(proprioception.shape)}: expected (..., {self.proprioception_dim})"
            )
        expected = (*batch, self.config.image_size, self.config.image_size, 3)
        features = []
        for key in self.image_keys:
            if key not in images:
                raise ValueError(f"images: missing camera key '{key}' (have {sorted(images)})")
            if images[key].dtype != torch.uint8 or tuple(images[key].shape) != expected:
                raise ValueError(
                    f"images['{key}'] shape {tuple(images[key].shape)}, dtype {images[key].dtype}: expected "
                    f"{expected} uint8"
                )
            flat = images[key].reshape(-1, *expected[-3:])  # (N, h, w, 3), N = prod(batch)
            features.append(self.cameras[key](flat).reshape(*batch, -1))  # (*batch, feature_dim)
        return torch.cat([*features, proprioception.to(features[0].dtype)], dim=-1)
