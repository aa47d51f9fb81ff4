"""ResNet-18 convolutional trunk with GroupNorm, written here because torchvision cannot be installed beside torch.

Follows He et al., "Deep Residual Learning for Image Recognition" (2016), the 18-layer network with basic blocks
(two 3 x 3 convolutions each), and Diffusion Policy's change to it for training from scratch with small batches.
Deviations from the torchvision ``resnet18`` layout:

- GroupNorm with one group per 16 channels replaces BatchNorm (as Diffusion Policy's ``replace_bn_with_gn``): the
  statistics do not depend on the batch, so training and evaluation normalize alike. Its affine parameters are as
  many as BatchNorm's, so the trunk keeps the standard 11,176,512 parameters.
- No global pooling and no classifier: the trunk returns the last feature map for a spatial-softmax head.
- ``base_channels`` scales every width (64 is the standard network), which gives the light CPU variant.
"""

from torch import Tensor, nn

from carp.config.image_encoder import CHANNELS_PER_GROUP

STAGE_MULTIPLIERS = (1, 2, 4, 8)
BLOCKS_PER_STAGE = 2
# Stem stride 2, max pooling stride 2, then stride 2 in stages 2 to 4: a feature map is 1/32 of the image per side.
DOWNSAMPLING = 32


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm over ``channels`` with one group per :data:`CHANNELS_PER_GROUP` channels."""
    return nn.GroupNorm(channels // CHANNELS_PER_GROUP, channels)


class BasicBlock(nn.Module):
    """Two 3 x 3 convolutions with a residual connection; a strided 1 x 1 projection when the shape changes."""

    def __init__(self, in_channels: int, out_channels: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False)
        self.norm1 = group_norm(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False)
        self.norm2 = group_norm(out_channels)
        self.activation = nn.ReLU(inplace=True)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=False), group_norm(out_channels)
            )

    def forward(self, features: Tensor) -> Tensor:
        """Apply the block.

        Args:
            features: (N, C_in, h, w) float.

        Returns:
            (N, C_out, ceil(h / stride), ceil(w / stride)) float.
        """
        residual = self.activation(self.norm1(self.conv1(features)))
        residual = self.norm2(self.conv2(residual))
        return self.activation(residual + self.shortcut(features))


class ResNetTrunk(nn.Module):
    """ResNet-18 without pooling and classifier: a 7 x 7 stem, max pooling and four stages of two basic blocks.

    Attributes:
        out_channels: channels of the returned feature map, ``8 * base_channels``.
    """

    def __init__(self, base_channels: int = 64) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(3, base_channels, 7, stride=2, padding=3, bias=False),
            group_norm(base_channels),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, stride=2, padding=1),
        )
        stages = []
        in_channels = base_channels
        for index, multiplier in enumerate(STAGE_MULTIPLIERS):
            out_channels = base_channels * multiplier
            first_stride = 1 if index == 0 else 2
            blocks = [BasicBlock(in_channels, out_channels, first_stride)]
            blocks += [BasicBlock(out_channels, out_channels, 1) for _ in range(BLOCKS_PER_STAGE - 1)]
            stages.append(nn.Sequential(*blocks))
            in_channels = out_channels
        self.stages = nn.Sequential(*stages)
        self.out_channels = in_channels
        self._initialize()

    def _initialize(self) -> None:
        # He initialization for ReLU networks (fan-out mode, as the reference implementation) and identity norms.
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(module, nn.GroupNorm):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)

    def forward(self, images: Tensor) -> Tensor:
        """Feature map of a batch of images.

        Args:
            images: (N, 3, h, w) float, normalized to [-1, 1].

        Returns:
            (N, out_channels, ceil(h / 32), ceil(w / 32)) float; (N, 512, 3, 3) for 76 x 76 crops of the standard
            trunk.
        """
        return self.stages(self.stem(images))
