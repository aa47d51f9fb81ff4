"""Crops of image batches: a random square per image in training, the centred square in evaluation.

As Diffusion Policy's ``CropRandomizer`` (84 -> 76 pixels on robomimic images): random crops are an augmentation
that makes the encoder tolerate small shifts of the camera image, and evaluation sees the centre crop, the mean of
the training crops' positions.
"""

import torch
from torch import Tensor, nn


def random_crop(images: Tensor, size: int, generator: torch.Generator | None = None) -> Tensor:
    """A square of side ``size`` at an independent uniformly random position in each image.

    Args:
        images: (N, C, h, w) images, any dtype.
        size: crop side in pixels, at most ``min(h, w)``.
        generator: source of the offsets; ``None`` uses torch's global generator (seeded by ``torch.manual_seed``).

    Returns:
        (N, C, size, size) crops, same dtype and device.
    """
    count, _, height, width = images.shape
    _check_size(size, height, width)
    tops = torch.randint(0, height - size + 1, (count,), generator=generator, device=generator_device(generator))
    lefts = torch.randint(0, width - size + 1, (count,), generator=generator, device=generator_device(generator))
    offsets = torch.arange(size)
    rows = (tops[:, None] + offsets).to(images.device)  # (N, size)
    columns = (lefts[:, None] + offsets).to(images.device)  # (N, size)
    batch = torch.arange(count, device=images.device)[:, None, None]
    crops = images.permute(0, 2, 3, 1)[batch, rows[:, :, None], columns[:, None, :]]  # (N, size, size, C)
    return crops.permute(0, 3, 1, 2)


def center_crop(images: Tensor, size: int) -> Tensor:
    """The centred square of side ``size`` of every image (rounded towards the top left when not exact).

    Args:
        images: (N, C, h, w) images.
        size: crop side in pixels, at most ``min(h, w)``.

    Returns:
        (N, C, size, size) crops.
    """
    height, width = images.shape[-2:]
    _check_size(size, height, width)
    top, left = (height - size) // 2, (width - size) // 2
    return images[..., top : top + size, left : left + size]


def generator_device(generator: torch.Generator | None) -> torch.device:
    """The device a generator draws on (the CPU for the global generator)."""
    return generator.device if generator is not None else torch.device("cpu")


def _check_size(size: int, height: int, width: int) -> None:
    if not 1 <= size <= min(height, width):
        raise ValueError(f"crop size {size} does not fit images of {height} x {width} pixels")


class ImageCrop(nn.Module):
    """Random crops in training mode, centre crops in evaluation mode (``module.train()`` / ``module.eval()``)."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.size = size

    def forward(self, images: Tensor) -> Tensor:
        """Crop a batch.

        Args:
            images: (N, C, h, w) images.

        Returns:
            (N, C, size, size) crops.
        """
        if self.training:
            return random_crop(images, self.size)
        return center_crop(images, self.size)
