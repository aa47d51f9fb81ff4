"""Per-dimension 1-D convolutional encoder and decoder, vectorized over the A action dimensions.

Layout: every tensor here is (B, A * channels, 1, T) in `torch.channels_last` memory format, with the channels of
dimension d at [d * channels, (d + 1) * channels). Memory therefore runs (B, T, A, channels): time-major, as action
chunks (B, H, A) already are, so the encoder's input and the decoder's output are views of the action tensors. A 1-D
convolution over time is a 2-D convolution with a (1, k) kernel over this height-1 image. Why not `nn.Conv1d`: oneDNN
runs grouped convolutions with a few channels per group about twice as fast (forward + backward) in channels-last
layout, which PyTorch only offers for 4-D tensors.

Convolutions use `groups=A` and GroupNorm uses one group per dimension, so no weight or statistic mixes two
dimensions: the module computes A independent networks in one kernel launch per layer. A consequence used by
`carp.tokenizer.per_dimension`: every parameter is the concatenation along axis 0 of the A per-dimension parameters.

Architecture after the official CARP code (ZhefeiGong/carp, `svqvae/basic_vae.py`); docs/architecture.md, "Action
tokenizer", places it in the whole tokenizer.
Deviations from CARP: two residual blocks before each down-sampling (CARP puts one before and one after), a symmetric
padded stride-2 convolution for down-sampling (CARP pads one step on the right), a kernel-4 transposed convolution for
up-sampling (CARP: kernel 3 with output padding) and a GroupNorm + SiLU before the decoder's output convolution.
"""

import torch
import torch.nn.functional as F
from torch import nn

from carp.tokenizer.spec import TokenizerSpec


def grouped_norm(num_dimensions: int, channels: int) -> nn.GroupNorm:
    """GroupNorm with one group per action dimension over (B, A * channels, 1, T) tensors, keeping their layout.

    PyTorch's channels-last kernel runs on the time-major memory as it is; copying to the contiguous layout and back
    around its contiguous kernel costs more than it saves at these few channels per group.
    """
    return nn.GroupNorm(num_groups=num_dimensions, num_channels=num_dimensions * channels, eps=1e-6)


def grouped_conv(
    num_dimensions: int, in_channels: int, out_channels: int, kernel_size: int = 3, stride: int = 1
) -> nn.Conv2d:
    """Convolution over time applied to each dimension's channels separately, (B, A * in, 1, T) -> (B, A * out, 1, T').

    Padding kernel_size // 2 keeps the length for stride 1 and halves an even length for stride 2 with kernel 3.
    """
    return nn.Conv2d(
        num_dimensions * in_channels,
        num_dimensions * out_channels,
        kernel_size=(1, kernel_size),
        stride=(1, stride),
        padding=(0, kernel_size // 2),
        groups=num_dimensions,
    )


def grouped_upsampling(num_dimensions: int, channels: int) -> nn.ConvTranspose2d:
    """Transposed convolution that doubles the length, (B, A * ch, 1, T) -> (B, A * ch, 1, 2T), per dimension."""
    # kernel 4, stride 2, padding 1 doubles the length exactly: (T - 1) * 2 - 2 + 4 = 2T.
    return nn.ConvTranspose2d(
        num_dimensions * channels,
        num_dimensions * channels,
        kernel_size=(1, 4),
        stride=(1, 2),
        padding=(0, 1),
        groups=num_dimensions,
    )


class ResidualBlock(nn.Module):
    """Two (GroupNorm, SiLU, conv k=3) layers with a skip connection; 1x1 conv on the skip if channels change."""

    def __init__(self, num_dimensions: int, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.norm_in = grouped_norm(num_dimensions, in_channels)
        self.conv_in = grouped_conv(num_dimensions, in_channels, out_channels)
        self.norm_out = grouped_norm(num_dimensions, out_channels)
        self.conv_out = grouped_conv(num_dimensions, out_channels, out_channels)
        self.skip = (
            nn.Identity()
            if in_channels == out_channels
            else grouped_conv(num_dimensions, in_channels, out_channels, kernel_size=1)
        )

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """Map (B, A * in_channels, 1, T) to (B, A * out_channels, 1, T)."""
        update = self.conv_in(F.silu(self.norm_in(hidden)))
        update = self.conv_out(F.silu(self.norm_out(update)))
        return self.skip(hidden) + update


class ActionEncoder(nn.Module):
    """Encode each dimension's normalized action chunk (B, A, 1, H) into a latent (B, A * C, 1, l)."""

    def __init__(self, spec: TokenizerSpec) -> None:
        super().__init__()
        num_dimensions = spec.action_dim
        channels = spec.base_channels
        self.conv_in = grouped_conv(num_dimensions, 1, channels)
        levels = []
        for multiplier in spec.channel_mult:
            level_channels = spec.base_channels * multiplier
            levels.append(
                nn.Sequential(
                    ResidualBlock(num_dimensions, channels, level_channels),
                    ResidualBlock(num_dimensions, level_channels, level_channels),
                    grouped_conv(num_dimensions, level_channels, level_channels, stride=2),
                )
            )
            channels = level_channels
        self.levels = nn.Sequential(*levels)
        self.norm_out = grouped_norm(num_dimensions, channels)
        self.conv_out = grouped_conv(num_dimensions, channels, spec.latent_channels)

    def forward(self, actions: torch.Tensor) -> torch.Tensor:
        """Encode (B, A, 1, H) normalized actions (channels-last, time last) into latents (B, A * C, 1, l)."""
        hidden = self.conv_in(actions)  # (B, A * ch, 1, H)
        hidden = self.levels(hidden)  # (B, A * ch * mult[-1], 1, l)
        return self.conv_out(F.silu(self.norm_out(hidden)))  # (B, A * C, 1, l)


class ActionDecoder(nn.Module):
    """Mirror of `ActionEncoder`: decode latents (B, A * C, 1, l) into action chunks (B, A, 1, H)."""

    def __init__(self, spec: TokenizerSpec) -> None:
        super().__init__()
        num_dimensions = spec.action_dim
        level_channels = [spec.base_channels * multiplier for multiplier in spec.channel_mult]
        channels = level_channels[-1]
        self.norm_in = grouped_norm(num_dimensions, spec.latent_channels)
        self.conv_in = grouped_conv(num_dimensions, spec.latent_channels, channels)
        levels = []
        output_channels = [spec.base_channels, *level_channels[:-1]]
        for next_channels in reversed(output_channels):
            levels.append(
                nn.Sequential(
                    grouped_upsampling(num_dimensions, channels),
                    ResidualBlock(num_dimensions, channels, next_channels),
                    ResidualBlock(num_dimensions, next_channels, next_channels),
                )
            )
            channels = next_channels
        self.levels = nn.Sequential(*levels)
        self.norm_out = grouped_norm(num_dimensions, channels)
        self.conv_out = grouped_conv(num_dimensions, channels, 1)

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        """Decode latents (B, A * C, 1, l) (channels-last) into normalized actions (B, A, 1, H) (time last)."""
        hidden = self.conv_in(F.silu(self.norm_in(latent)))  # (B, A * ch * mult[-1], 1, l)
        hidden = self.levels(hidden)  # (B, A * ch, 1, H)
        return self.conv_out(F.silu(self.norm_out(hidden)))  # (B, A, 1, H)
