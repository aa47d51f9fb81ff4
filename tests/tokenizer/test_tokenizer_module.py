import pytest
import torch
import torch.nn.functional as F

import carp.tokenizer.quantizer as quantizer_module
from carp.tokenizer.quantizer import first_maximum_indices, phi_index_for_scale, resampling_matrix
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer


def test_forward_shapes_and_token_counts_per_scale(tiny_tokenizer, tiny_actions, tiny_spec):
    output = tiny_tokenizer(tiny_actions)
    assert output.reconstruction.shape == tiny_actions.shape
    assert output.loss.dim() == 0 and output.reconstruction_loss.dim() == 0 and output.vq_loss.dim() == 0
    assert [tuple(ids.shape) for ids in output.token_ids] == [(5, 2, 1), (5, 2, 2)]
    for ids in output.token_ids:
        assert ids.dtype == torch.long
        assert 0 <= int(ids.min()) and int(ids.max()) < tiny_spec.codebook_size
    assert tiny_tokenizer.encode_to_latent(tiny_actions).shape == (5, 2, 4, 2)


def test_default_spec_tokens_per_chunk():
    torch.manual_seed(0)
    tokenizer = MultiScaleActionTokenizer(TokenizerSpec(action_dim=10, codebook_size=16)).eval()
    actions = torch.rand(3, 16, 10) * 2 - 1
    token_ids = tokenizer.encode_to_ids(actions)
    assert [tuple(ids.shape) for ids in token_ids] == [(3, 10, 1), (3, 10, 2), (3, 10, 3), (3, 10, 4)]
    assert tokenizer.encode_to_sequence(actions).shape == (3, 100)
    assert tokenizer.teacher_forcing_sequence(token_ids).shape == (3, 100 - 10, 8)
    assert tokenizer.decode_ids(token_ids).shape == (3, 16, 10)


def test_loss_combines_reconstruction_and_vq_terms_summed_over_dimensions(tiny_tokenizer, tiny_actions):
    output = tiny_tokenizer(tiny_actions)
    assert torch.allclose(output.reconstruction_loss, F.mse_loss(output.reconstruction, tiny_actions))
    assert torch.allclose(output.loss, 2 * (output.reconstruction_loss + output.vq_loss))


def test_encode_and_decode_are_deterministic(tiny_tokenizer, tiny_actions):
    first_ids = tiny_tokenizer.encode_to_ids(tiny_actions)
    second_ids = tiny_tokenizer.encode_to_ids(tiny_actions.clone())
    for first, second in zip(first_ids, second_ids, strict=True):
        assert torch.equal(first, second)
    assert torch.equal(tiny_tokenizer.decode_ids(first_ids), tiny_tokenizer.decode_ids(second_ids))


def test_training_forward_reconstruction_equals_decoding_its_ids(tiny_tokenizer, tiny_actions):
    # The straight-through latent carries the values of f_hat, so both paths decode the same latent.
    output = tiny_tokenizer(tiny_actions)
    decoded = tiny_tokenizer.decode_ids(output.token_ids)
    assert torch.allclose(output.reconstruction, decoded, atol=1e-6)
    for forward_ids, encoded_ids in zip(output.token_ids, tiny_tokenizer.encode_to_ids(tiny_actions), strict=True):
        assert torch.equal(forward_ids, encoded_ids)


def test_sequence_layout_is_scale_then_position_then_dimension(tiny_tokenizer):
    # id = position * A + dimension makes every token's origin readable from its value.
    token_ids = [
        (torch.arange(scale)[None, None, :] * 2 + torch.arange(2)[None, :, None]).expand(3, 2, scale)
        for scale in (1, 2)
    ]
    sequence = tiny_tokenizer.ids_to_sequence(token_ids)
    assert sequence.shape == (3, 6)
    assert sequence[0].tolist() == [0, 1, 0, 1, 2, 3]
    assert torch.equal(sequence % 2, torch.arange(6).expand(3, 6) % 2)  # token i uses dimension i % A
    for original, restored in zip(token_ids, tiny_tokenizer.sequence_to_ids(sequence), strict=True):
        assert torch.equal(original, restored)


def test_sequence_round_trip_of_encoded_ids(tiny_tokenizer, tiny_actions):
    token_ids = tiny_tokenizer.encode_to_ids(tiny_actions)
    sequence = tiny_tokenizer.encode_to_sequence(tiny_actions)
    for original, restored in zip(token_ids, tiny_tokenizer.sequence_to_ids(sequence), strict=True):
        assert torch.equal(original, restored)


def test_teacher_forcing_matches_step_by_step_inference(tiny_tokenizer, tiny_actions):
    token_ids = tiny_tokenizer.encode_to_ids(tiny_actions)
    quantized = tiny_tokenizer.empty_latent(tiny_actions.shape[0])
    stepwise = []
    for scale_index, ids in enumerate(token_ids):
        quantized = tiny_tokenizer.embed_scale(quantized, ids, scale_index)
        if scale_index + 1 < len(token_ids):
            stepwise.append(tiny_tokenizer.next_scale_input(quantized, scale_index))
    forced = tiny_tokenizer.teacher_forcing_inputs(token_ids)
    assert [tuple(latent.shape) for latent in forced] == [(5, 2, 4, 2)]
    for expected, actual in zip(stepwise, forced, strict=True):
        assert torch.allclose(expected, actual)
    assert torch.allclose(quantized, tiny_tokenizer.ids_to_latent(token_ids))
    sequence = tiny_tokenizer.teacher_forcing_sequence(token_ids)
    assert sequence.shape == (5, 4, 4)  # (B, L - s_1 * A, C)
    # Position 1 of dimension 0 sits at token 2 of the scale-2 block.
    assert torch.allclose(sequence[:, 2], forced[0][:, 0, :, 1])


def test_next_scale_input_is_the_area_downsample_of_f_hat():
    torch.manual_seed(0)
    tokenizer = MultiScaleActionTokenizer(TokenizerSpec(action_dim=3, codebook_size=8)).eval()
    quantized = torch.randn(2, 3, 8, 4)
    expected = F.interpolate(quantized.reshape(2, 24, 4), size=3, mode="area").reshape(2, 3, 8, 3)
    assert torch.allclose(tokenizer.next_scale_input(quantized, 1), expected, atol=1e-6)
    with pytest.raises(ValueError, match=r"scale_index must be in \[0, 2\]"):
        tokenizer.next_scale_input(quantized, 3)


def test_gradients_reach_the_encoder_through_the_straight_through_estimator(tiny_spec, tiny_actions):
    torch.manual_seed(0)
    tokenizer = MultiScaleActionTokenizer(tiny_spec)
    tokenizer(tiny_actions).reconstruction_loss.backward()
    assert tokenizer.encoder.conv_in.weight.grad.abs().sum() > 0
    # Only the VQ loss trains the codebook and phi convs; the reconstruction alone leaves them untouched.
    assert tokenizer.quantizer.codebook.grad is None
    tokenizer.zero_grad()
    tokenizer(tiny_actions).loss.backward()
    assert tokenizer.quantizer.codebook.grad.abs().sum() > 0
    assert tokenizer.quantizer.phi_convs[0].weight.grad.abs().sum() > 0
    assert tokenizer.decoder.conv_out.weight.grad.abs().sum() > 0


@pytest.mark.parametrize(
    ("source", "target", "mode"),
    [(4, 1, "area"), (4, 3, "area"), (1, 4, "bicubic"), (3, 4, "bicubic"), (2, 4, "bicubic")],
)
def test_resampling_matrices_reproduce_interpolate(source, target, mode):
    values = torch.randn(2, 5, source)
    matrix = resampling_matrix(source, target, mode)
    if mode == "area":
        expected = F.interpolate(values, size=target, mode="area")
    else:
        expected = F.interpolate(values[..., None], size=(target, 1), mode="bicubic", align_corners=False)[..., 0]
    assert torch.allclose(values @ matrix.T, expected, atol=1e-6)


def test_phi_convs_are_shared_by_nearest_relative_depth():
    assert [phi_index_for_scale(k, 4) for k in range(4)] == [0, 1, 2, 3]
    assert [phi_index_for_scale(k, 2) for k in range(2)] == [0, 3]
    assert [phi_index_for_scale(k, 3) for k in range(3)] == [0, 1, 3]  # the middle tie goes to the coarser conv
    assert [phi_index_for_scale(k, 6) for k in range(6)] == [0, 0, 1, 2, 3, 3]
    assert phi_index_for_scale(0, 1) == 0


def test_phi_is_half_identity_half_convolution(tiny_tokenizer):
    hidden = torch.randn(3, 2, 4, 2)
    quantizer = tiny_tokenizer.quantizer
    conv = quantizer.phi_convs[quantizer.phi_of_scale[1]]
    image = hidden.reshape(3, 8, 1, 2)  # (B, A * C, 1, l)
    expected = 0.5 * image + 0.5 * conv(image)
    assert torch.allclose(quantizer.phi(1, hidden), expected.reshape(3, 2, 4, 2))


def test_nearest_codes_use_cosine_similarity(tiny_tokenizer):
    quantizer = tiny_tokenizer.quantizer
    with torch.no_grad():
        quantizer.codebook.zero_()
        quantizer.codebook[:, 3, 0] = 0.01  # tiny code pointing along channel 0
        quantizer.codebook[:, 5, 1] = 100.0  # huge code at a right angle
    residual = torch.zeros(1, 2, 4, 1)
    residual[:, :, 0] = 0.5  # nearer to code 3 in angle, and L2 would pick the zero codes first
    assert quantizer.nearest_codes(residual).flatten().tolist() == [3, 3]


@pytest.mark.parametrize("block_elements", [1, 1 << 18])  # one dimension per block, all dimensions at once
def test_nearest_codes_match_cosine_argmax_for_any_residual_length(tiny_tokenizer, monkeypatch, block_elements):
    monkeypatch.setattr(quantizer_module, "SEARCH_BLOCK_ELEMENTS", block_elements)
    quantizer = tiny_tokenizer.quantizer
    generator = torch.Generator().manual_seed(4)
    residual = torch.randn(6, 2, 4, 2, generator=generator)  # (B, A, C, s)
    cosine = F.cosine_similarity(
        residual.permute(0, 1, 3, 2)[:, :, :, None, :],  # (B, A, s, 1, C)
        quantizer.codebook.detach()[None, :, None, :, :],  # (1, A, 1, V, C)
        dim=-1,
    )  # (B, A, s, V)
    expected = cosine.argmax(dim=-1)
    assert torch.equal(quantizer.nearest_codes(residual), expected)
    assert torch.equal(quantizer.nearest_codes(residual * 1e3, quantizer.unit_codebook()), expected)


def test_restart_codes_only_touches_unused_codes(tiny_tokenizer):
    quantizer = tiny_tokenizer.quantizer
    before = quantizer.codebook.detach().clone()
    unused = torch.zeros(2, 8, dtype=torch.bool)
    unused[0, 1] = unused[1, 6] = True
    candidates = torch.full((2, 3, 4), 7.0)
    candidates[1] = -7.0
    restarted = quantizer.restart_codes(unused, candidates, torch.Generator().manual_seed(0))
    after = quantizer.codebook.detach()
    assert restarted == 2
    assert torch.equal(after[0, 1], torch.full((4,), 7.0)) and torch.equal(after[1, 6], torch.full((4,), -7.0))
    assert torch.equal(after[~unused], before[~unused])


def test_invalid_inputs_are_rejected_with_shapes(tiny_tokenizer):
    with pytest.raises(ValueError, match=r"actions must have shape \(B, H, A\) = \(B, 8, 2\), got \(4, 8, 3\)"):
        tiny_tokenizer.encode_to_ids(torch.zeros(4, 8, 3))
    with pytest.raises(ValueError, match=r"expected token ids for 2 scales, got 1"):
        tiny_tokenizer.decode_ids([torch.zeros(1, 2, 1, dtype=torch.long)])
    with pytest.raises(ValueError, match=r"token ids of scale index 1 must have shape"):
        tiny_tokenizer.ids_to_sequence([torch.zeros(1, 2, 1, dtype=torch.long), torch.zeros(1, 2, 3, dtype=torch.long)])
    with pytest.raises(ValueError, match=r"token sequence must have shape \(B, L\) = \(B, 6\)"):
        tiny_tokenizer.sequence_to_ids(torch.zeros(1, 5, dtype=torch.long))


def test_checkpoint_round_trip_and_version_check(tiny_tokenizer, tiny_actions):
    checkpoint = tiny_tokenizer.to_checkpoint()
    restored = MultiScaleActionTokenizer.from_checkpoint(checkpoint).eval()
    assert restored.spec == tiny_tokenizer.spec
    assert torch.equal(
        restored.decode_ids(restored.encode_to_ids(tiny_actions)),
        tiny_tokenizer.decode_ids(tiny_tokenizer.encode_to_ids(tiny_actions)),
    )
    with pytest.raises(ValueError, match=r"format_version 99, this code reads version 2"):
        MultiScaleActionTokenizer.from_checkpoint({**checkpoint, "format_version": 99})


def test_single_scale_has_no_teacher_forcing_inputs():
    tokenizer = MultiScaleActionTokenizer(
        TokenizerSpec(action_dim=2, action_horizon=4, scales=(1,), codebook_size=4, latent_channels=3)
    )
    token_ids = tokenizer.encode_to_ids(torch.zeros(2, 4, 2))
    assert tokenizer.teacher_forcing_inputs(token_ids) == []
    assert tokenizer.teacher_forcing_sequence(token_ids).shape == (2, 0, 3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_first_maximum_indices_match_torch_max_and_take_the_first_of_ties(dtype):
    scores = torch.randn(3, 40, 64, generator=torch.Generator().manual_seed(0)).to(dtype)
    scores[0, 0, [5, 9, 60]] = 100.0  # a three-way tie for the maximum: the first one wins
    found = first_maximum_indices(scores)
    assert found.dtype == torch.long and found.shape == (3, 40)
    assert torch.equal(found, scores.max(dim=-1).indices)
    assert found[0, 0] == 5
    transposed = scores.transpose(0, 1)  # not contiguous
    assert torch.equal(first_maximum_indices(transposed), transposed.max(dim=-1).indices)
