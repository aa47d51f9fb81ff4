"""Sinusoidal embedding of the diffusion step, as both Diffusion Policy denoisers use it.

Transformer-style position encoding applied to the step index t: half the channels are `sin(t * f_i)`, half
`cos(t * f_i)`, with frequencies falling geometrically from 1 to 1/10000 (DP's `SinusoidalPosEmb`). The frequencies
are a buffer computed once, not per call.
"""

import torch
from torch import nn

MAX_PERIOD = 10_000.0


class SinusoidalStepEmbedding(nn.Module):
    """Map diffusion steps (N,) to (N, dim) sinusoids.

    Args:
        dim: embedding width, even and >= 4 (so that at least two frequencies span the range).
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        if dim < 4 or dim % 2:
            raise ValueError(f"step embedding width must be an even integer >= 4, got {dim}")
        half = dim // 2
        exponents = torch.arange(half, dtype=torch.float32) / (half - 1)
        self.register_buffer("frequencies", MAX_PERIOD**-exponents, persistent=False)  # (dim / 2,)

    def forward(self, steps: torch.Tensor) -> torch.Tensor:
        """Embed steps.

        Args:
            steps: (N,) integer or float diffusion steps.

        Returns:
            (N, dim) float32, sines then cosines.
        """
        angles = steps.to(self.frequencies.dtype)[:, None] * self.frequencies  # (N, dim / 2)
        return torch.cat((angles.sin(), angles.cos()), dim=-1)  # (N, dim)


def step_encoder(dim: int) -> nn.Sequential:
    """DP-C's diffusion-step encoder: sinusoids, then Linear(dim, 4 dim), Mish, Linear(4 dim, dim); (N,) -> (N, dim)."""
    return nn.Sequential(
        SinusoidalStepEmbedding(dim),
        nn.Linear(dim, 4 * dim),
        nn.Mish(),
        nn.Linear(4 * dim, dim),
    )
