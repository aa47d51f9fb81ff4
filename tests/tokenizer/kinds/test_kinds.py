"""Each kind's own error bound or property on smooth synthetic chunks."""

import numpy as np
import pytest
import torch

from carp.tokenizer.kinds.base import TokenBatch
from carp.tokenizer.kinds.binning import BinningTokenizer
from carp.tokenizer.kinds.bspline import BSplineTokenizer
from carp.tokenizer.kinds.fast import FastTokenizer
from carp.tokenizer.kinds.fsq import FiniteScalarQuantizer, FsqTokenizer
from carp.tokenizer.kinds.joint_msvq import JointMsvqTokenizer
from carp.tokenizer.kinds.residual_vq import ResidualVqTokenizer
from tests.tokenizer.kinds.conftest import A, H, smooth_chunks


def test_binning_errs_at_most_half_a_bin_inside_the_range(training_chunks, held_out_chunks):
    tokenizer = BinningTokenizer(A, H, bins=32, lower_percentile=0.0, upper_percentile=100.0)
    tokenizer.fit(torch.cat([training_chunks, held_out_chunks]))
    errors = (tokenizer.decode(tokenizer.encode(held_out_chunks)).actions - held_out_chunks).abs()
    half_bin = torch.as_tensor(tokenizer.bins.width / 2, dtype=torch.float32)
    assert (errors <= half_bin + 1e-6).all()
    assert (errors.amax(dim=(0, 1)) > 0.5 * half_bin).all()  # the bound is tight, not vacuous


def test_binning_takes_its_range_from_the_percentiles_and_clips_outside_it(training_chunks):
    tokenizer = BinningTokenizer(A, H, bins=16, lower_percentile=5.0, upper_percentile=95.0)
    tokenizer.fit(training_chunks)
    flat = training_chunks.reshape(-1, A).double().numpy()
    np.testing.assert_allclose(tokenizer.bins.low, np.percentile(flat, 5.0, axis=0))
    np.testing.assert_allclose(tokenizer.bins.high, np.percentile(flat, 95.0, axis=0))
    outside = torch.full((1, H, A), 5.0)
    assert (tokenizer.encode(outside).ids == 15).all()


def test_a_cubic_is_reproduced_exactly_by_the_spline_and_within_half_a_bin_once_quantized():
    time = torch.linspace(0.0, 1.0, H, dtype=torch.float64)
    coefficients = torch.tensor([[0.2, -0.5, 0.1], [0.6, 1.1, -0.4], [-0.9, 0.3, 0.8], [0.5, -0.7, -0.2]])
    cubic = sum(coefficients[power] * time[:, None] ** power for power in range(4))[None].float()  # (1, H, A)
    tokenizer = BSplineTokenizer(A, H, control_points=5, degree=3, bins=64)
    np.testing.assert_allclose(tokenizer.curve(tokenizer.control_points_of(cubic)), cubic, atol=1e-6)
    tokenizer.fit(torch.cat([cubic, smooth_chunks(50, seed=3)]))
    errors = (tokenizer.decode(tokenizer.encode(cubic)).actions - cubic).abs()
    # The basis is a partition of unity, so a control-point error of at most half a bin stays below it on the curve.
    assert (errors <= torch.as_tensor(tokenizer.bins.width / 2, dtype=torch.float32) + 1e-6).all()


def test_a_spline_needs_between_degree_plus_one_and_h_control_points():
    with pytest.raises(ValueError, match=r"control_points must be in .* = \[4, 16\], got 3"):
        BSplineTokenizer(A, H, control_points=3)
    with pytest.raises(ValueError, match=r"got 17"):
        BSplineTokenizer(A, H, control_points=17)


def test_fast_is_near_lossless_at_a_high_scale_and_coarser_at_a_low_one(training_chunks, held_out_chunks):
    errors = {}
    for scale in (2.0, 200.0):
        tokenizer = FastTokenizer(A, H, scale=scale, vocabulary_size=2048)
        tokenizer.fit(training_chunks)
        decoded = tokenizer.decode(tokenizer.encode(held_out_chunks)).actions
        errors[scale] = float((decoded - held_out_chunks).abs().max())
    # Rounding each orthonormal coefficient errs by at most 0.5 / scale, and the inverse DCT preserves the norm.
    assert errors[200.0] <= 0.5 / 200.0 * H**0.5
    assert errors[2.0] > 10 * errors[200.0]


def test_fast_compresses_smooth_chunks_below_one_token_per_value(training_chunks, held_out_chunks):
    tokenizer = FastTokenizer(A, H, scale=10.0, vocabulary_size=256)
    tokenizer.fit(training_chunks)
    lengths = tokenizer.encode(held_out_chunks).lengths.double()
    assert lengths.mean() < 0.5 * H * A
    assert tokenizer.tokens_per_chunk.mean < 0.5 * H * A
    assert tokenizer.tokens_per_chunk.mean <= tokenizer.tokens_per_chunk.p95 <= tokenizer.tokens_per_chunk.maximum


def test_fast_repairs_and_flags_sequences_of_the_wrong_coefficient_count(training_chunks, held_out_chunks):
    tokenizer = FastTokenizer(A, H, scale=10.0, vocabulary_size=256)
    tokenizer.fit(training_chunks)
    rows = tokenizer.encode(held_out_chunks[:4]).sequences()
    single = next(
        token for token in range(tokenizer.vocabulary_size) if len(tokenizer.encoding.id_to_token(token)) == 1
    )
    broken = [rows[0], rows[1][:-1], rows[2] + [single] * 5, []]
    decoded = tokenizer.decode(TokenBatch.from_sequences(broken))
    assert decoded.invalid.tolist() == [False, True, True, True]
    assert decoded.invalid_count == 3
    assert decoded.actions.shape == (4, H, A) and torch.isfinite(decoded.actions).all()
    assert torch.equal(decoded.actions[3], torch.zeros(H, A))  # nothing decodes to all-zero coefficients


def test_fast_refuses_a_vocabulary_smaller_than_its_alphabet(training_chunks):
    with pytest.raises(ValueError, match=r"vocabulary_size 8 is below the \d+ integers the coefficients take"):
        FastTokenizer(A, H, scale=10.0, vocabulary_size=8).fit(training_chunks)


def test_fast_cannot_encode_before_it_is_fitted(held_out_chunks):
    with pytest.raises(RuntimeError, match="fit it on training windows first"):
        FastTokenizer(A, H).encode(held_out_chunks)


def test_fsq_ids_and_values_are_one_code_each():
    quantizer = FiniteScalarQuantizer((8, 6, 5))
    latent = torch.randn(400, 4, 3, generator=torch.Generator().manual_seed(0)) * 3
    values, ids = quantizer(latent)
    assert torch.equal(quantizer.values(ids), values)
    assert ids.min() >= 0 and ids.max() < 240 and len(ids.unique()) > 150
    every = quantizer.values(torch.arange(240))
    assert len({tuple(row.tolist()) for row in every}) == 240


def test_fsq_training_lowers_the_reconstruction_error(training_chunks, held_out_chunks):
    untrained = FsqTokenizer(A, H, levels=(8, 6, 5), downsampling=2, hidden_channels=16, steps=1)
    trained = FsqTokenizer(A, H, levels=(8, 6, 5), downsampling=2, hidden_channels=16, steps=150, batch_size=64)
    trained.fit(training_chunks)
    error = {
        name: float((model.decode(model.encode(held_out_chunks)).actions - held_out_chunks).pow(2).mean())
        for name, model in (("untrained", untrained), ("trained", trained))
    }
    assert error["trained"] < 0.5 * error["untrained"]


def test_the_joint_multi_scale_vq_has_one_token_per_scale_position_and_learns(training_chunks, held_out_chunks):
    settings = {"scales": (1, 2, 4), "codebook_size": 32, "latent_channels": 4, "hidden_channels": 16}
    untrained = JointMsvqTokenizer(A, H, steps=1, **settings)
    trained = JointMsvqTokenizer(A, H, steps=150, batch_size=64, learning_rate=3e-3, **settings)
    trained.fit(training_chunks)
    tokens = trained.encode(held_out_chunks)
    assert tokens.ids.shape == (len(held_out_chunks), 1 + 2 + 4)
    error = {
        name: float((model.decode(model.encode(held_out_chunks)).actions - held_out_chunks).pow(2).mean())
        for name, model in (("untrained", untrained), ("trained", trained))
    }
    assert error["trained"] < 0.75 * error["untrained"]  # a joint codebook learns slowly; this much takes 150 steps


def test_the_residual_vq_tokens_are_vq_bets_codes_and_more_layers_err_less(training_chunks, held_out_chunks):
    # A light commitment: the default (VQ-BeT's 5) holds the encoder near the coarse codes, which a 300-step fit of
    # these chunks does not outgrow; the claim here is about layers, not about that weight.
    settings = {
        "num_codes": 16,
        "latent_width": 16,
        "hidden_width": 64,
        "steps": 300,
        "batch_size": 64,
        "commitment_weight": 1.0,
    }
    error = {}
    for layers in (1, 4):
        tokenizer = ResidualVqTokenizer(A, H, num_layers=layers, **settings)
        tokenizer.fit(training_chunks)
        tokens = tokenizer.encode(held_out_chunks)
        assert tokens.ids.shape == (len(held_out_chunks), layers)
        # The kind is the VQ-BeT family's network: its tokens are the codes, its chunks the decoded codes.
        assert torch.equal(tokens.ids, tokenizer.module.encode_to_ids(held_out_chunks))
        decoded = tokenizer.decode(tokens).actions
        assert torch.equal(decoded, tokenizer.module.decode_ids(tokens.ids))
        error[layers] = float((decoded - held_out_chunks).pow(2).mean())
    assert error[4] < 0.8 * error[1]


def test_the_residual_vq_repairs_and_flags_ids_outside_a_layers_codebook(training_chunks, held_out_chunks):
    tokenizer = ResidualVqTokenizer(A, H, num_layers=2, num_codes=8, latent_width=8, hidden_width=16, steps=5)
    tokenizer.fit(training_chunks)
    tokens = tokenizer.encode(held_out_chunks[:3])
    broken = tokens.ids.clone()
    broken[0, 1] = 8  # past the codebook
    short = TokenBatch(broken, torch.tensor([2, 1, 2]))  # row 1 lacks its second layer's code
    decoded = tokenizer.decode(short)
    assert decoded.invalid.tolist() == [True, True, False] and torch.isfinite(decoded.actions).all()
    assert torch.equal(decoded.actions[2], tokenizer.decode(tokens).actions[2])
