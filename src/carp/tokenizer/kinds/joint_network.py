"""What the kinds that encode all action dimensions jointly share: 1-D convolutions over time and a training loop.

`fsq` and `joint_msvq` map a chunk (B, H, A), its A dimensions as input channels, to a latent at H / 2**n positions
with the same small network (a convolution, n stride-2 convolutions, a convolution; the decoder mirrors it with
transposed convolutions), and fit it the same way: Adam on the reconstruction loss of random batches.
"""

from collections.abc import Callable

import torch
from torch import nn


def temporal_convolutions(
    in_channels: int, hidden_channels: int, out_channels: int, halvings: int, transposed: bool
) -> nn.Sequential:
    """Convolutions (B, in, T) -> (B, out, T / 2**halvings), or -> (B, out, T * 2**halvings) when ``transposed``."""
    resample = nn.ConvTranspose1d if transposed else nn.Conv1d
    layers: list[nn.Module] = [nn.Conv1d(in_channels, hidden_channels, 3, padding=1), nn.GELU()]
    for _ in range(halvings):
        layers += [resample(hidden_channels, hidden_channels, 4, stride=2, padding=1), nn.GELU()]
    layers.append(nn.Conv1d(hidden_channels, out_channels, 3, padding=1))
    return nn.Sequential(*layers)


def fit_by_adam(
    module: nn.Module,
    windows: torch.Tensor,
    loss_of_batch: Callable[[torch.Tensor], torch.Tensor],
    steps: int,
    batch_size: int,
    learning_rate: float,
    seed: int,
    after_step: Callable[[int], None] | None = None,
) -> None:
    """Minimize ``loss_of_batch`` over random batches of windows (N, H, A) with Adam; leaves ``module`` in eval mode.

    Batches are drawn with replacement from a generator seeded with ``seed``, so a fit is reproducible.
    ``after_step(step)`` runs after each optimizer step (0-based), e.g. to re-seed unused codes.
    """
    generator = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.Adam(module.parameters(), lr=learning_rate)
    module.train()
    for step in range(steps):
        batch = windows[torch.randint(len(windows), (batch_size,), generator=generator)]
        loss = loss_of_batch(batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if after_step is not None:
            after_step(step)
    module.eval()
