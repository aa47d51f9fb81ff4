"""Finite scalar quantization (FSQ) of a temporally downsampled latent, as QueST tokenizes actions.

Sources: FSQ (Mentzer et al. 2023) and QueST (Mete et al. 2024, pairlab/QueST).

A small 1-D convolutional encoder maps a chunk (B, H, A), all dimensions together, to a latent of d = len(levels)
channels at H / ``downsampling`` positions; each channel is bounded with a tanh and rounded to ``levels[i]`` values
(straight-through gradient), and the d rounded values of a position form one token, their mixed-radix number, so
V = prod(levels) and L = H / ``downsampling``. A mirrored decoder rebuilds the chunk. Training minimizes the
reconstruction MSE with Adam; there is no codebook, hence no codebook loss or collapse.

Deviations from QueST: plain (not causal) convolutions, no transformer layers in the encoder and decoder, and a few
thousand CPU steps of training; the FSQ bound (tanh with an offset for even level counts) follows the FSQ paper.
"""

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from carp.tokenizer.kinds.base import (
    DecodedChunks,
    TokenBatch,
    TokensPerChunk,
    check_chunks,
)
from carp.tokenizer.kinds.bins import repaired_ids
from carp.tokenizer.kinds.joint_network import fit_by_adam, load_network, save_network, temporal_convolutions

KIND = "fsq"


class FiniteScalarQuantizer(nn.Module):
    """Rounds each of d channels to its own number of levels; a position's d values make one token id.

    Args:
        levels: values per channel, each >= 2.
    """

    def __init__(self, levels: tuple[int, ...]) -> None:
        super().__init__()
        self.levels = tuple(levels)
        levels_tensor = torch.tensor(levels, dtype=torch.float64)
        # Odd counts round symmetrically around 0; even counts need a half-step offset to get exactly L values.
        self.register_buffer("half_width", ((levels_tensor - 1) * (1 + 1e-3) / 2).float(), persistent=False)
        self.register_buffer("offset", torch.where(levels_tensor % 2 == 0, 0.5, 0.0).float(), persistent=False)
        self.register_buffer("shift", torch.atanh(self.offset.double() / self.half_width.double()).float(), False)
        self.register_buffer("radix", torch.tensor([math.prod(levels[:i]) for i in range(len(levels))]), False)
        self.register_buffer("middle", torch.tensor([level // 2 for level in levels]), persistent=False)

    @property
    def codebook_size(self) -> int:
        """prod(levels)."""
        return math.prod(self.levels)

    def forward(self, latent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Quantized latent (B, T, d) in [-1, 1] (straight-through) and token ids (B, T) long of a latent (B, T, d)."""
        bounded = torch.tanh(latent + self.shift) * self.half_width - self.offset
        rounded = bounded + (torch.round(bounded) - bounded).detach()
        digits = torch.round(bounded).long() + self.middle  # (B, T, d) in [0, levels)
        return rounded / self.middle, (digits * self.radix).sum(dim=-1)

    def values(self, token_ids: torch.Tensor) -> torch.Tensor:
        """The quantized latent (B, T, d) of token ids (B, T)."""
        digits = (token_ids[..., None] // self.radix) % torch.tensor(self.levels)
        return (digits - self.middle).float() / self.middle


class FsqAutoencoder(nn.Module):
    """Encoder, FSQ and decoder over all A dimensions jointly.

    Args:
        action_dim: A.
        levels: FSQ levels, one per latent channel.
        downsampling: H / L, a power of two.
        hidden_channels: width of the convolutions.
    """

    def __init__(self, action_dim: int, levels: tuple[int, ...], downsampling: int, hidden_channels: int) -> None:
        super().__init__()
        halvings = int(math.log2(downsampling))
        self.encoder = temporal_convolutions(action_dim, hidden_channels, len(levels), halvings, transposed=False)
        self.quantizer = FiniteScalarQuantizer(levels)
        self.decoder = temporal_convolutions(len(levels), hidden_channels, action_dim, halvings, transposed=True)

    def encode(self, chunks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Quantized latent (B, L, d) and token ids (B, L) of chunks (B, H, A)."""
        latent = rearrange(self.encoder(rearrange(chunks, "b h a -> b a h")), "b d t -> b t d")
        return self.quantizer(latent)

    def decode(self, quantized: torch.Tensor) -> torch.Tensor:
        """Chunks (B, H, A) of a quantized latent (B, L, d)."""
        return rearrange(self.decoder(rearrange(quantized, "b t d -> b d t")), "b a h -> b h a")


class FsqTokenizer:
    """A trained :class:`FsqAutoencoder`: one token per latent position.

    Args:
        action_dim: A.
        action_horizon: H, divisible by ``downsampling``.
        levels: FSQ levels (V = their product).
        downsampling: H / L, a power of two.
        hidden_channels: width of the convolutions.
        steps: Adam steps of ``fit``.
        batch_size: windows per step.
        learning_rate: Adam's learning rate.
        seed: seeds initialization and batch sampling.
    """

    kind = KIND

    def __init__(
        self,
        action_dim: int,
        action_horizon: int,
        levels: tuple[int, ...] = (8, 6, 5),
        downsampling: int = 4,
        hidden_channels: int = 32,
        steps: int = 2000,
        batch_size: int = 256,
        learning_rate: float = 1e-3,
        seed: int = 0,
    ) -> None:
        if downsampling < 1 or downsampling & (downsampling - 1) or action_horizon % downsampling:
            raise ValueError(f"downsampling must be a power of two dividing H={action_horizon}, got {downsampling}")
        self.action_dim, self.action_horizon = action_dim, action_horizon
        self.settings = {
            "levels": list(levels),
            "downsampling": downsampling,
            "hidden_channels": hidden_channels,
            "steps": steps,
            "batch_size": batch_size,
            "learning_rate": learning_rate,
            "seed": seed,
        }
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.module = FsqAutoencoder(action_dim, tuple(levels), downsampling, hidden_channels).eval()

    @classmethod
    def from_config(cls, config, action_dim: int, action_horizon: int) -> "FsqTokenizer":
        """Built from a `carp.config.tokenizer_kinds.FsqConfig`."""
        return cls(
            action_dim,
            action_horizon,
            config.levels,
            config.downsampling,
            config.hidden_channels,
            config.steps,
            config.batch_size,
            config.learning_rate,
            config.seed,
        )

    @property
    def vocabulary_size(self) -> int:
        """V = prod(levels)."""
        return self.module.quantizer.codebook_size

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """L = H / downsampling."""
        return TokensPerChunk.fixed(self.action_horizon // self.settings["downsampling"])

    def fit(self, windows: torch.Tensor) -> None:
        """Train the autoencoder on windows (N, H, A) to minimize the reconstruction MSE."""
        check_chunks(windows, self.action_horizon, self.action_dim)
        module = self.module

        def loss_of_batch(batch: torch.Tensor) -> torch.Tensor:
            return F.mse_loss(module.decode(module.encode(batch)[0]), batch)

        settings = self.settings
        fit_by_adam(
            module,
            windows.float(),
            loss_of_batch,
            settings["steps"],
            settings["batch_size"],
            settings["learning_rate"],
            settings["seed"],
        )

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """(B, L) token ids of chunks (B, H, A)."""
        check_chunks(chunks, self.action_horizon, self.action_dim)
        with torch.inference_mode():
            return TokenBatch.fixed(self.module.encode(chunks.float())[1])

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """Chunks (B, H, A); ids outside [0, V) or rows of another length are repaired and flagged."""
        ids, invalid = repaired_ids(tokens, self.tokens_per_chunk.maximum, self.vocabulary_size)
        with torch.inference_mode():
            return DecodedChunks(self.module.decode(self.module.quantizer.values(ids)), invalid)

    def save(self, directory: Path) -> None:
        """Write ``kind.json`` and the weights ``weights.pt``."""
        settings = {"action_dim": self.action_dim, "action_horizon": self.action_horizon, **self.settings}
        save_network(directory, KIND, settings, self.module)

    @classmethod
    def load(cls, directory: Path) -> "FsqTokenizer":
        """Read a folder written by :meth:`save`, loading the weights strictly."""
        return load_network(directory, KIND, lambda settings: cls(**settings), ("levels",))
