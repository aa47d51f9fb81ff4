"""Per-step uniform binning (RT-2, Brohan et al. 2023; OpenVLA, Kim et al. 2024): one token per dimension per step.

Each of the H x A values of a chunk is replaced by the index of its bin among N uniform bins over its dimension's
robust range, the 1st to 99th percentile of the training actions by default (OpenVLA's choice; RT-2 uses the full
range). Token layout: step-major, ``[step 0: d0..d(A-1), step 1: ...]``, L = H * A, V = N shared by all dimensions
(one vocabulary as in both papers). Without fitting, the range is the normalized range [-1, 1].
"""

from pathlib import Path

import numpy as np
import torch
from einops import rearrange

from carp.tokenizer.kinds.base import (
    DecodedChunks,
    TokenBatch,
    TokensPerChunk,
    check_chunks,
    expect_kind,
    write_kind_file,
)
from carp.tokenizer.kinds.bins import UniformBins, repaired_ids

KIND = "binning"


class BinningTokenizer:
    """N uniform bins per action dimension, one token per step and dimension.

    Args:
        action_dim: A.
        action_horizon: H.
        bins: N, bins per dimension (the vocabulary).
        lower_percentile: percentile of the training actions where the range starts, in [0, 50).
        upper_percentile: percentile where it ends, in (50, 100].
    """

    kind = KIND

    def __init__(
        self,
        action_dim: int,
        action_horizon: int,
        bins: int = 256,
        lower_percentile: float = 1.0,
        upper_percentile: float = 99.0,
    ) -> None:
        self.action_dim, self.action_horizon = action_dim, action_horizon
        self.lower_percentile, self.upper_percentile = lower_percentile, upper_percentile
        self.bins = UniformBins(np.full(action_dim, -1.0), np.full(action_dim, 1.0), bins)

    @classmethod
    def from_config(cls, config, action_dim: int, action_horizon: int) -> "BinningTokenizer":
        """Built from a `carp.config.tokenizer_kinds.BinningConfig`."""
        return cls(action_dim, action_horizon, config.bins, config.lower_percentile, config.upper_percentile)

    @property
    def vocabulary_size(self) -> int:
        """V = N."""
        return self.bins.count

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """L = H * A."""
        return TokensPerChunk.fixed(self.action_horizon * self.action_dim)

    def fit(self, windows: torch.Tensor) -> None:
        """Set each dimension's range from the percentiles of training windows (N, H, A)."""
        check_chunks(windows, self.action_horizon, self.action_dim)
        self.bins = UniformBins.over(
            windows.double().numpy(), self.bins.count, self.lower_percentile, self.upper_percentile
        )

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """(B, H * A) bin ids of chunks (B, H, A), step-major."""
        check_chunks(chunks, self.action_horizon, self.action_dim)
        return TokenBatch.fixed(rearrange(self.bins.to_ids(chunks), "b h a -> b (h a)"))

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """Bin centres (B, H, A); a row with ids outside [0, N) is clipped into range and flagged."""
        length = self.action_horizon * self.action_dim
        ids, invalid = repaired_ids(tokens, length, self.bins.count)
        values = self.bins.to_values(rearrange(ids, "b (h a) -> b h a", a=self.action_dim))
        return DecodedChunks(values, invalid)

    def save(self, directory: Path) -> None:
        """Write ``kind.json`` with the ranges."""
        write_kind_file(directory, KIND, self._settings())

    def _settings(self) -> dict:
        return {
            "action_dim": self.action_dim,
            "action_horizon": self.action_horizon,
            "lower_percentile": self.lower_percentile,
            "upper_percentile": self.upper_percentile,
            "bins": self.bins.to_settings(),
        }

    @classmethod
    def load(cls, directory: Path) -> "BinningTokenizer":
        """Read a folder written by :meth:`save`."""
        settings = expect_kind(directory, KIND)
        bins = UniformBins.from_settings(settings["bins"])
        tokenizer = cls(
            settings["action_dim"],
            settings["action_horizon"],
            bins.count,
            settings["lower_percentile"],
            settings["upper_percentile"],
        )
        tokenizer.bins = bins
        return tokenizer
