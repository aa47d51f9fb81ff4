"""Uniform bins over a per-dimension range: the scalar quantizer of the binning and B-spline kinds."""

from dataclasses import dataclass

import numpy as np
import torch

from carp.tokenizer.kinds.base import TokenBatch


@dataclass(frozen=True)
class UniformBins:
    """``count`` equal bins over [low, high] of each of the last axis's dimensions; values decode to bin centres.

    A value outside the range is clipped into its end bin, so the round-trip error is at most half a bin width
    inside the range.

    Attributes:
        low: (A,) lower end of each dimension's range.
        high: (A,) upper end, above ``low``.
        count: N, bins per dimension (token ids 0..N-1).
    """

    low: np.ndarray
    high: np.ndarray
    count: int

    def __post_init__(self) -> None:
        if self.count < 2:
            raise ValueError(f"need at least 2 bins, got {self.count}")
        if np.any(np.asarray(self.high) <= np.asarray(self.low)):
            raise ValueError(f"every range needs high > low, got low={self.low}, high={self.high}")

    @classmethod
    def over(cls, values: np.ndarray, count: int, lower_percentile: float, upper_percentile: float) -> "UniformBins":
        """Bins over the percentiles of ``values`` (..., A) per dimension, widened to 1e-6 where a dimension is flat."""
        flat = np.asarray(values, dtype=np.float64).reshape(-1, values.shape[-1])
        low = np.percentile(flat, lower_percentile, axis=0)
        high = np.percentile(flat, upper_percentile, axis=0)
        # A constant dimension (a gripper never used) has low == high; any small width reproduces it.
        high = np.maximum(high, low + 1e-6)
        return cls(low, high, count)

    @property
    def width(self) -> np.ndarray:
        """(A,) width of one bin per dimension."""
        return (self.high - self.low) / self.count

    def to_ids(self, values: torch.Tensor) -> torch.Tensor:
        """Bin ids (..., A) long of values (..., A)."""
        low = torch.as_tensor(self.low, dtype=torch.float64)
        width = torch.as_tensor(self.width, dtype=torch.float64)
        ids = torch.floor((values.double() - low) / width)
        return ids.clamp(0, self.count - 1).long()

    def to_values(self, ids: torch.Tensor) -> torch.Tensor:
        """Bin centres (..., A) float32 of bin ids (..., A)."""
        low = torch.as_tensor(self.low, dtype=torch.float64)
        width = torch.as_tensor(self.width, dtype=torch.float64)
        return (low + (ids.double() + 0.5) * width).float()

    def to_settings(self) -> dict:
        """JSON values for a kind file."""
        return {"low": self.low.tolist(), "high": self.high.tolist(), "count": self.count}

    @classmethod
    def from_settings(cls, settings: dict) -> "UniformBins":
        """Rebuild from :meth:`to_settings` output."""
        return cls(np.asarray(settings["low"], np.float64), np.asarray(settings["high"], np.float64), settings["count"])


def repaired_ids(tokens: TokenBatch, length: int, vocabulary_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A fixed-length kind's ids (B, L) long, made decodable, and (B,) bool flags of the rows that needed it.

    A row of another length than L is truncated or padded with id 0, and an id outside [0, V) is clipped into it.
    """
    ids = tokens.ids[:, :length]
    invalid = (tokens.lengths != length) | ((ids < 0) | (ids >= vocabulary_size)).any(dim=1)
    if ids.shape[1] < length:
        ids = torch.nn.functional.pad(ids, (0, length - ids.shape[1]), value=0)
    return ids.clamp(0, vocabulary_size - 1), invalid
