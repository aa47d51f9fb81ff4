"""Rate and distortion measured alike for every kind."""

import math

import pytest
import torch

from carp.tokenizer.kinds.base import PADDING_ID
from carp.tokenizer.kinds.binning import BinningTokenizer
from carp.tokenizer.rate_distortion import measure_rate_distortion, token_entropy_bits
from tests.tokenizer.kinds.conftest import A, H


def test_the_entropy_of_uniformly_used_tokens_is_log2_of_their_count_and_ignores_padding():
    ids = torch.tensor([[0, 1, 2, 3], [4, 5, 6, 7]])
    assert token_entropy_bits(ids) == pytest.approx(3.0)
    padded = torch.tensor([[0, 1, PADDING_ID], [2, 3, PADDING_ID]])
    assert token_entropy_bits(padded) == pytest.approx(2.0)
    assert token_entropy_bits(torch.zeros(2, 3, dtype=torch.long)) == 0.0


def test_binning_rate_and_error_are_what_its_bins_imply():
    tokenizer = BinningTokenizer(A, H, bins=4)  # bins over [-1, 1], centres -0.75, -0.25, 0.25, 0.75
    chunks = torch.full((5, H, A), 0.5)
    chunks[:, :, 1] = -0.25
    measured = measure_rate_distortion(tokenizer, chunks)
    assert measured.bits_per_chunk == H * A * math.log2(4) == 96
    assert measured.tokens_mean == measured.tokens_p95 == H * A
    # Two tokens in use, dimension 1's a third of the time: entropy h(1/3) bits per token.
    third = 1 / 3
    entropy = -(third * math.log2(third) + (1 - third) * math.log2(1 - third))
    assert measured.entropy_bits_per_chunk == pytest.approx(H * A * entropy)
    # 0.5 decodes to 0.25 (0.25 of the 2-wide range = 12.5%), -0.25 to itself.
    assert measured.rmse_percent_range == pytest.approx((12.5, 0.0, 12.5))
    assert (measured.worst_rmse_percent, measured.invalid_rate) == (pytest.approx(12.5), 0.0)
    assert measured.encode_ms > 0 and measured.decode_ms > 0


def test_no_windows_is_an_error():
    with pytest.raises(ValueError, match="at least one window"):
        measure_rate_distortion(BinningTokenizer(A, H), torch.zeros(0, H, A))
