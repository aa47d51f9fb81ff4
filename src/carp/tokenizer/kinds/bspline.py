"""B-spline control points quantized to bins (BEAST, Zhou et al. 2025, arXiv 2506.06072): fixed length, no training.

Each dimension of a chunk is fitted, by least squares, with a clamped uniform B-spline of degree p (3 by default) and
K control points on the chunk's time axis mapped to [0, 1]; the K control points of every dimension are then each
quantized to N uniform bins over that dimension's control-point range on the training windows (the normalized range
[-1, 1] before fitting). Decoding evaluates the spline at the H steps. A clamped spline passes through its first and
last control points, and any polynomial of degree <= p is reproduced exactly before quantization.

Token layout: control-point-major, ``[point 0: d0..d(A-1), point 1: ...]``, L = K * A, V = N.

Deviations from BEAST: the bins span each dimension's fitted control-point range instead of a fixed [-1, 1], and no
continuity constraint ties consecutive chunks (each chunk is fitted alone, as the other kinds tokenize it).
The basis comes from `scipy.interpolate.BSpline.design_matrix`.
"""

from pathlib import Path

import numpy as np
import torch
from einops import rearrange
from scipy.interpolate import BSpline

from carp.tokenizer.kinds.base import (
    DecodedChunks,
    TokenBatch,
    TokensPerChunk,
    check_chunks,
    expect_kind,
    write_kind_file,
)
from carp.tokenizer.kinds.bins import UniformBins, repaired_ids

KIND = "bspline"


def clamped_uniform_basis(action_horizon: int, control_points: int, degree: int) -> np.ndarray:
    """(H, K) values of the K clamped uniform B-spline basis functions of ``degree`` at H equally spaced times."""
    if not degree + 1 <= control_points <= action_horizon:
        raise ValueError(
            f"control_points must be in [degree + 1, H] = [{degree + 1}, {action_horizon}], got {control_points}"
        )
    interior = np.linspace(0.0, 1.0, control_points - degree + 1)
    knots = np.concatenate([np.zeros(degree), interior, np.ones(degree)])  # K + degree + 1 knots
    times = np.linspace(0.0, 1.0, action_horizon)
    return BSpline.design_matrix(times, knots, degree).toarray()


class BSplineTokenizer:
    """K quantized control points of a clamped uniform B-spline per action dimension.

    Args:
        action_dim: A.
        action_horizon: H.
        control_points: K per dimension, in [degree + 1, H].
        degree: p of the spline.
        bins: N per control point (the vocabulary).
    """

    kind = KIND

    def __init__(
        self, action_dim: int, action_horizon: int, control_points: int = 8, degree: int = 3, bins: int = 256
    ) -> None:
        self.action_dim, self.action_horizon = action_dim, action_horizon
        self.control_points, self.degree = control_points, degree
        self.basis = torch.as_tensor(clamped_uniform_basis(action_horizon, control_points, degree))  # (H, K)
        self.fitting = torch.linalg.pinv(self.basis)  # (K, H), the least-squares fit
        self.bins = UniformBins(np.full(action_dim, -1.0), np.full(action_dim, 1.0), bins)

    @classmethod
    def from_config(cls, config, action_dim: int, action_horizon: int) -> "BSplineTokenizer":
        """Built from a `carp.config.tokenizer_kinds.BSplineConfig`."""
        return cls(action_dim, action_horizon, config.control_points, config.degree, config.bins)

    @property
    def vocabulary_size(self) -> int:
        """V = N."""
        return self.bins.count

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """L = K * A."""
        return TokensPerChunk.fixed(self.control_points * self.action_dim)

    def control_points_of(self, chunks: torch.Tensor) -> torch.Tensor:
        """Least-squares control points (B, K, A) float64 of chunks (B, H, A)."""
        check_chunks(chunks, self.action_horizon, self.action_dim)
        return torch.einsum("kh,bha->bka", self.fitting, chunks.double())

    def curve(self, control_points: torch.Tensor) -> torch.Tensor:
        """The spline (B, H, A) float32 through control points (B, K, A)."""
        return torch.einsum("hk,bka->bha", self.basis, control_points.double()).float()

    def fit(self, windows: torch.Tensor) -> None:
        """Set each dimension's bins over the full range of the training windows' (N, H, A) control points."""
        points = self.control_points_of(windows).numpy()
        self.bins = UniformBins.over(points, self.bins.count, 0.0, 100.0)

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """(B, K * A) bin ids of the chunks' (B, H, A) control points, control-point-major."""
        return TokenBatch.fixed(rearrange(self.bins.to_ids(self.control_points_of(chunks)), "b k a -> b (k a)"))

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """The spline (B, H, A) through the bin centres; ids outside [0, N) are clipped and their rows flagged."""
        length = self.control_points * self.action_dim
        ids, invalid = repaired_ids(tokens, length, self.bins.count)
        points = self.bins.to_values(rearrange(ids, "b (k a) -> b k a", a=self.action_dim))
        return DecodedChunks(self.curve(points), invalid)

    def save(self, directory: Path) -> None:
        """Write ``kind.json`` with the control-point ranges."""
        settings = {
            "action_dim": self.action_dim,
            "action_horizon": self.action_horizon,
            "control_points": self.control_points,
            "degree": self.degree,
            "bins": self.bins.to_settings(),
        }
        write_kind_file(directory, KIND, settings)

    @classmethod
    def load(cls, directory: Path) -> "BSplineTokenizer":
        """Read a folder written by :meth:`save`."""
        settings = expect_kind(directory, KIND)
        bins = UniformBins.from_settings(settings["bins"])
        tokenizer = cls(
            settings["action_dim"],
            settings["action_horizon"],
            settings["control_points"],
            settings["degree"],
            bins.count,
        )
        tokenizer.bins = bins
        return tokenizer
