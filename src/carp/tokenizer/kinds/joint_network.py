"""What the kinds that encode all action dimensions jointly share: 1-D convolutions over time and a training loop.

`fsq` and `joint_msvq` map a chunk (B, H, A), its A dimensions as input channels, to a latent at H / 2**n positions
with the same small network (a convolution, n stride-2 convolutions, a convolution; the decoder mirrors it with
transposed convolutions), and fit it the same way: Adam on the reconstruction loss of random batches.
"""

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import nn

from carp.tokenizer.kinds.base import expect_kind, write_kind_file
from carp.training.checkpoint import atomic_torch_save, read_checkpoint


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


WEIGHTS_FILENAME = "weights.pt"
"""The network's weights beside ``kind.json`` in a trained kind's folder."""


def save_network(directory: Path, kind: str, settings: dict, module: nn.Module) -> None:
    """Write a trained kind's ``kind.json`` (its `settings`) and its network's weights, each atomically."""
    write_kind_file(directory, kind, settings)
    atomic_torch_save(module.state_dict(), Path(directory) / WEIGHTS_FILENAME)


def load_network(directory: Path, kind: str, build: Callable[[dict], Any], tuple_fields: tuple[str, ...]) -> Any:
    """The tokenizer `build` makes from the folder's settings (`tuple_fields` back to tuples), weights loaded strictly.

    `build(settings)` returns a tokenizer whose `module` holds the network.
    """
    settings = expect_kind(directory, kind)
    for name in tuple_fields:
        settings[name] = tuple(settings[name])
    tokenizer = build(settings)
    tokenizer.module.load_state_dict(read_checkpoint(Path(directory) / WEIGHTS_FILENAME, weights_only=True))
    return tokenizer
