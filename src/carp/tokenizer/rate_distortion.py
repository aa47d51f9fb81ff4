"""Rate and distortion of any tokenizer kind, measured the same way for every kind (docs/benchmarks.md).

Rate: bits per chunk, the mean tokens per chunk times log2(V) (what a policy's output layer must be able to say),
and the empirical entropy of the tokens actually used on the windows times the mean token count (what the tokens
carry). Distortion: RMSE of the round trip in percent of each dimension's normalization range (the normalized range
[-1, 1] spans 2 units), its mean and worst dimension. Also the encode and decode time per chunk and the share of
rows the decoding had to repair (`carp.tokenizer.kinds.base.DecodedChunks`).
"""

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from carp.tokenizer.kinds.base import PADDING_ID, ActionTokenizer

MEASURE_BATCH_SIZE = 1024


@dataclass(frozen=True)
class RateDistortion:
    """One tokenizer's rate and distortion on a set of windows.

    Attributes:
        kind: the tokenizer kind.
        vocabulary_size: V.
        tokens_mean: mean tokens per chunk on the windows.
        tokens_p95: 95th percentile of tokens per chunk.
        bits_per_chunk: ``tokens_mean * log2(V)``.
        entropy_bits_per_chunk: ``tokens_mean`` times the entropy (bits) of the used tokens' frequencies.
        rmse_percent_range: (A,) round-trip RMSE per dimension, % of its normalization range.
        encode_ms: wall time to encode one chunk, in milliseconds (batches of up to 1024).
        decode_ms: wall time to decode one chunk.
        invalid_rate: share of chunks whose decoding was repaired.
    """

    kind: str
    vocabulary_size: int
    tokens_mean: float
    tokens_p95: float
    bits_per_chunk: float
    entropy_bits_per_chunk: float
    rmse_percent_range: tuple[float, ...]
    encode_ms: float
    decode_ms: float
    invalid_rate: float

    @property
    def rmse_percent_mean(self) -> float:
        """Mean over dimensions of the RMSE in % of range."""
        return float(np.mean(self.rmse_percent_range))

    @property
    def worst_dimension(self) -> int:
        """Index of the dimension with the largest RMSE."""
        return int(np.argmax(self.rmse_percent_range))

    @property
    def worst_rmse_percent(self) -> float:
        """The largest per-dimension RMSE in % of range."""
        return float(np.max(self.rmse_percent_range))


def token_entropy_bits(ids: torch.Tensor) -> float:
    """Entropy in bits of the frequencies of the ids in ``ids`` (any shape), :data:`PADDING_ID` left out."""
    used = ids[ids != PADDING_ID]
    if used.numel() == 0:
        return 0.0
    counts = torch.bincount(used - used.min()).double()
    probabilities = counts[counts > 0] / counts.sum()
    return float(-(probabilities * probabilities.log2()).sum())


def measure_rate_distortion(tokenizer: ActionTokenizer, windows: torch.Tensor) -> RateDistortion:
    """Round-trip held-out windows (N, H, A) of normalized actions through ``tokenizer`` and measure it.

    Raises:
        ValueError: no windows.
    """
    if len(windows) == 0:
        raise ValueError("need at least one window to measure a tokenizer")
    windows = windows.float()
    decoded, ids, lengths, invalid = [], [], [], []
    encode_seconds = decode_seconds = 0.0
    for batch in torch.split(windows, MEASURE_BATCH_SIZE):
        start = time.perf_counter()
        tokens = tokenizer.encode(batch)
        encode_seconds += time.perf_counter() - start
        start = time.perf_counter()
        result = tokenizer.decode(tokens)
        decode_seconds += time.perf_counter() - start
        decoded.append(result.actions.float())
        ids.append(tokens.ids.reshape(-1))
        lengths.append(tokens.lengths)
        invalid.append(result.invalid)
    errors = (torch.cat(decoded) - windows).double() / 2.0  # (N, H, A) in fractions of the range
    rmse = 100.0 * errors.pow(2).mean(dim=(0, 1)).sqrt()
    counts = torch.cat(lengths).double()
    tokens_mean = float(counts.mean())
    vocabulary_size = tokenizer.vocabulary_size
    return RateDistortion(
        kind=tokenizer.kind,
        vocabulary_size=vocabulary_size,
        tokens_mean=tokens_mean,
        tokens_p95=float(np.percentile(counts.numpy(), 95)),
        bits_per_chunk=tokens_mean * math.log2(vocabulary_size),
        entropy_bits_per_chunk=tokens_mean * token_entropy_bits(torch.cat(ids)),
        rmse_percent_range=tuple(rmse.tolist()),
        encode_ms=1000.0 * encode_seconds / len(windows),
        decode_ms=1000.0 * decode_seconds / len(windows),
        invalid_rate=float(torch.cat(invalid).double().mean()),
    )
