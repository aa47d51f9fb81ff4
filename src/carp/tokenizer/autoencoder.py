"""Per-dimension 1-D convolutional encoder and decoder, vectorized over the A action dimensions.

Every tensor here is laid out (B, A * channels, T) with the channels of dimension d at [d * channels, (d + 1) *
channels). Convolutions use `groups=A` and GroupNorm uses one group per dimension, so no weight or statistic mixes two
dimensions: the module computes A independent networks in one kernel launch per layer. A consequence used by
`carp.tokenizer.per_dimension`: every parameter is the concatenation along axis 0 of the A per-dimension parameters.

Architecture after DESIGN.md section 3, itself after the official CARP code (ZhefeiGong/carp, `svqvae/basic_vae.py`).
Deviations from CARP: two residual blocks before each down-sampling (CARP puts one before and one after), a symmetric
padded stride-2 convolution for down-sampling (CARP pads one step on the right), a kernel-4 transposed convolution for
up-sampling (CARP: kernel 3 with output padding) and a GroupNorm + SiLU before the decoder's output convolution.
"""

import torch
import torch.nn.functional as F
from torch import nn

from carp.tokenizer.spec import TokenizerSpec


def grouped_norm(num_dimensions: int, channels: int) -> nn.GroupNorm:
    """GroupNorm with one group per action dimension over (B, A * channels, T) tensors."""
    return nn.GroupNorm(num_groups=num_dimensions, num_channels=num_dimensions * channels, eps=1e-6)


def grouped_conv(num_dimensions: int, in_channels: int, out_channels: int, kernel_size: int = 3) -> nn.Conv1d:
    """Length-preserving convolution applied to each dimension's channels separately."""
    return nn.Conv1d(
        num_dimensions * in_channels,
        num_dimensions * out_channels,
        kernel_size=kernel_size,
        padding=kernel_size // 2,
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
        """Map (B, A * in_channels, T) to (B, A * out_channels, T)."""
        update = self.conv_in(F.silu(self.norm_in(hidden)))
        update = self.conv_out(F.silu(self.norm_out(update)))
        return self.skip(hidden) + update


class ActionEncoder(nn.Module):
    """Encode each dimension's normalized action chunk (B, A, H) into a latent (B, A * C, l)."""

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
                    nn.Conv1d(
                        num_dimensions * level_channels,
                        num_dimensions * level_channels,
                        kernel_size=3,
                        stride=2,
                        padding=1,
                        groups=num_dimensions,
                    ),
                )
            )
            channels = level_channels
        self.levels = nn.Sequential(*levels)
        self.norm_out = grouped_norm(num_dimensions, channels)
        self.conv_out = grouped_conv(num_dimensions, channels, spec.latent_channels)

    def forward(self, actions: torch.Tensor) -> torch.Tensor:
        """Encode (B, A, H) normalized actions (time last) into latents (B, A * C, l)."""
        hidden = self.conv_in(actions)  # (B, A * ch, H)
        hidden = self.levels(hidden)  # (B, A * ch * mult[-1], l)
        return self.conv_out(F.silu(self.norm_out(hidden)))  # (B, A * C, l)


class ActionDecoder(nn.Module):
    """Mirror of `ActionEncoder`: decode latents (B, A * C, l) into action chunks (B, A, H)."""

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
                    # kernel 4, stride 2, padding 1 doubles the length exactly: (T - 1) * 2 - 2 + 4 = 2T.
                    nn.ConvTranspose1d(
                        num_dimensions * channels,
                        num_dimensions * channels,
                        kernel_size=4,
                        stride=2,
                        padding=1,
                        groups=num_dimensions,
                    ),
                    ResidualBlock(num_dimensions, channels, next_channels),
                    ResidualBlock(num_dimensions, next_channels, next_channels),
                )
            )
            channels = next_channels
        self.levels = nn.Sequential(*levels)
        self.norm_out = grouped_norm(num_dimensions, channels)
        self.conv_out = grouped_conv(num_dimensions, channels, 1)

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        """Decode latents (B, A * C, l) into normalized actions (B, A, H) (time last)."""
        hidden = self.conv_in(F.silu(self.norm_in(latent)))  # (B, A * ch * mult[-1], l)
        hidden = self.levels(hidden)  # (B, A * ch, H)
        return self.conv_out(F.silu(self.norm_out(hidden)))  # (B, A, H)
