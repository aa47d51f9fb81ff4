"""The vectorized tokenizer must compute exactly what A independent single-dimension tokenizers compute."""

import pytest
import torch

from carp.tokenizer.per_dimension import (
    merge_single_dimension_tokenizers,
    single_dimension_spec,
    split_into_single_dimension_tokenizers,
)
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

NUM_DIMENSIONS = 3


@pytest.fixture
def spec() -> TokenizerSpec:
    # Four scales so every phi conv and both resampling paths take part.
    return TokenizerSpec(
        action_dim=NUM_DIMENSIONS, action_horizon=16, scales=(1, 2, 3, 4), codebook_size=16, latent_channels=4
    )


@pytest.fixture
def singles(spec) -> list[MultiScaleActionTokenizer]:
    tokenizers = []
    for dimension in range(NUM_DIMENSIONS):
        torch.manual_seed(100 + dimension)
        tokenizer = MultiScaleActionTokenizer(single_dimension_spec(spec))
        with torch.no_grad():  # codes of a trained scale, so the cosine search has clear winners
            tokenizer.quantizer.codebook.normal_()
        tokenizers.append(tokenizer.eval())
    return tokenizers


@pytest.fixture
def actions() -> torch.Tensor:
    steps = torch.linspace(0, 1, 16)
    generator = torch.Generator().manual_seed(3)
    phases = torch.rand(6, 1, NUM_DIMENSIONS, generator=generator) * 6
    return torch.sin(3 * steps[None, :, None] + phases) * 0.9  # (B, H, A) smooth, within [-1, 1]


def per_dimension(singles, actions, method):
    return [getattr(single, method)(actions[:, :, d : d + 1]) for d, single in enumerate(singles)]


def test_latents_ids_and_reconstructions_agree(singles, actions):
    merged = merge_single_dimension_tokenizers(singles).eval()

    expected_latent = torch.cat(per_dimension(singles, actions, "encode_to_latent"), dim=1)  # (B, A, C, l)
    assert torch.allclose(merged.encode_to_latent(actions), expected_latent, atol=1e-5)

    merged_ids = merged.encode_to_ids(actions)
    single_ids = per_dimension(singles, actions, "encode_to_ids")
    for scale_index, ids in enumerate(merged_ids):
        assert torch.equal(ids, torch.cat([single[scale_index] for single in single_ids], dim=1))
    assert len({int(ids.max()) for ids in merged_ids}) > 1, "codes should vary for the comparison to mean much"

    expected_f_hat = torch.cat(
        [single.ids_to_latent([ids[:, d : d + 1] for ids in merged_ids]) for d, single in enumerate(singles)], dim=1
    )
    assert torch.allclose(merged.ids_to_latent(merged_ids), expected_f_hat, atol=1e-5)

    expected_reconstruction = torch.cat(
        [single.decode_ids([ids[:, d : d + 1] for ids in merged_ids]) for d, single in enumerate(singles)], dim=2
    )
    assert torch.allclose(merged.decode_ids(merged_ids), expected_reconstruction, atol=1e-5)

    expected_inputs = [
        torch.cat(per_scale, dim=1)
        for per_scale in zip(
            *[
                single.teacher_forcing_inputs([ids[:, d : d + 1] for ids in merged_ids])
                for d, single in enumerate(singles)
            ],
            strict=True,
        )
    ]
    for merged_input, expected_input in zip(merged.teacher_forcing_inputs(merged_ids), expected_inputs, strict=True):
        assert torch.allclose(merged_input, expected_input, atol=1e-5)


def test_training_loss_and_gradients_equal_independent_models(singles, actions):
    merged = merge_single_dimension_tokenizers(singles).train()
    merged_output = merged(actions)
    merged_output.loss.backward()
    single_losses = []
    for dimension, single in enumerate(singles):
        single.train()
        output = single(actions[:, :, dimension : dimension + 1])
        output.loss.backward()
        single_losses.append(output.loss)
    assert torch.allclose(merged_output.loss, torch.stack(single_losses).sum(), atol=1e-5)
    single_parameters = [dict(single.named_parameters()) for single in singles]
    for name, parameter in merged.named_parameters():
        expected = [parameters[name].grad for parameters in single_parameters]
        if parameter.grad is None:  # e.g. a phi conv no scale selects
            assert all(gradient is None for gradient in expected), name
            continue
        assert torch.allclose(parameter.grad, torch.cat(expected, dim=0), atol=1e-5, rtol=1e-4), name


def test_split_inverts_merge(singles, spec):
    merged = merge_single_dimension_tokenizers(singles)
    assert merged.spec == spec
    for original, restored in zip(singles, split_into_single_dimension_tokenizers(merged), strict=True):
        assert restored.spec == original.spec
        for (name, expected), actual in zip(original.state_dict().items(), restored.state_dict().values(), strict=True):
            assert torch.equal(expected, actual), name


def test_merge_rejects_mismatched_specs(singles):
    other = MultiScaleActionTokenizer(TokenizerSpec(action_dim=1, codebook_size=32, latent_channels=4))
    with pytest.raises(ValueError, match="every tokenizer must share one spec with action_dim=1"):
        merge_single_dimension_tokenizers([*singles, other])
