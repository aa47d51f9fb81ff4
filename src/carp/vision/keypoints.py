"""Spatial-softmax keypoint head (Levine et al., "End-to-End Training of Deep Visuomotor Policies", 2016).

A 1 x 1 convolution maps the trunk's features to K heat maps; a softmax over each map's positions gives a
distribution whose expected (x, y) position, in coordinates from -1 (left, top) to 1 (right, bottom), is one
keypoint. As robomimic's ``SpatialSoftmax`` used by Diffusion Policy, with its defaults: a fixed temperature of 1 and
no keypoint noise.
"""

import torch
from einops import rearrange
from torch import Tensor, nn


class SpatialSoftmax(nn.Module):
    """Feature map (N, C, h, w) -> K expected keypoint positions (N, K, 2), each coordinate in [-1, 1]."""

    def __init__(self, in_channels: int, num_keypoints: int) -> None:
        super().__init__()
        self.project = nn.Conv2d(in_channels, num_keypoints, 1)

    def forward(self, features: Tensor) -> Tensor:
        """Expected position of each keypoint's softmax over the feature map's positions.

        Args:
            features: (N, C, h, w) float.

        Returns:
            (N, K, 2) float keypoints, (x, y) with x along the width and y along the height, in [-1, 1]; a map of
            one position (h = w = 1) puts every keypoint at 0.
        """
        height, width = features.shape[-2:]
        logits = rearrange(self.project(features), "n k h w -> n k (h w)")
        attention = torch.softmax(logits.float(), dim=-1).to(features.dtype)  # softmax in float32 under autocast
        grid_y, grid_x = torch.meshgrid(_axis(height, features), _axis(width, features), indexing="ij")
        positions = torch.stack([grid_x.reshape(-1), grid_y.reshape(-1)], dim=-1)  # (h w, 2)
        return attention @ positions  # (N, K, 2)


def _axis(size: int, like: Tensor) -> Tensor:
    """(size,) evenly spaced coordinates from -1 to 1; the centre, 0, for a single position."""
    if size == 1:
        return like.new_zeros(1)
    return torch.linspace(-1.0, 1.0, size, device=like.device, dtype=like.dtype)
