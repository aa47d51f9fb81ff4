"""The (1, k) convolutions over channels-last (B, A * channels, 1, T) images are per-dimension 1-D convolutions."""

import pytest
import torch
import torch.nn.functional as F
from einops import rearrange

from carp.tokenizer.autoencoder import grouped_conv, grouped_norm, grouped_upsampling


def channels_last_image(sequence: torch.Tensor) -> torch.Tensor:
    """(B, channels, T) -> (B, channels, 1, T) in channels-last memory."""
    return sequence[:, :, None, :].contiguous(memory_format=torch.channels_last)


def test_grouped_conv_is_a_conv1d_over_time_per_dimension():
    torch.manual_seed(0)
    sequence = torch.randn(3, 2 * 4, 8)  # (B, A * in, T) with A = 2, in = 4
    for stride, expected_length in ((1, 8), (2, 4)):
        conv = grouped_conv(2, 4, 5, stride=stride)
        output = conv(channels_last_image(sequence))
        assert output.shape == (3, 2 * 5, 1, expected_length)
        # Dimension 1's outputs depend only on its own input channels and weights.
        weight, bias = conv.weight[5:, :, 0], conv.bias[5:]  # (out, in, k), (out,)
        expected = F.conv1d(sequence[:, 4:], weight, bias, stride=stride, padding=1)
        assert torch.allclose(output[:, 5:, 0], expected, atol=1e-6)


def test_grouped_upsampling_doubles_the_length_like_conv_transpose1d():
    torch.manual_seed(0)
    sequence = torch.randn(3, 2 * 4, 4)
    upsampling = grouped_upsampling(2, 4)
    output = upsampling(channels_last_image(sequence))
    assert output.shape == (3, 8, 1, 8)
    expected = F.conv_transpose1d(sequence, upsampling.weight[:, :, 0], upsampling.bias, stride=2, padding=1, groups=2)
    assert torch.allclose(output[:, :, 0], expected, atol=1e-6)


def test_grouped_norm_keeps_statistics_per_sample_and_dimension():
    image = channels_last_image(torch.randn(3, 2 * 4, 8) * 5 + 3)
    normalized = rearrange(grouped_norm(2, 4)(image), "b (a c) 1 t -> b a (c t)", a=2)
    assert torch.allclose(normalized.mean(dim=-1), torch.zeros(3, 2), atol=1e-5)
    assert torch.allclose(normalized.var(dim=-1, unbiased=False), torch.ones(3, 2), atol=1e-4)


def test_tokenizer_keeps_time_major_memory_end_to_end(tiny_tokenizer, tiny_actions):
    # The speed of the vectorized module rests on these views: no layout copies between the convolutions.
    latent = tiny_tokenizer.encode_to_latent(tiny_actions)  # (B, A, C, l)
    assert rearrange(latent, "b a c t -> b t a c").is_contiguous()
    for conv in tiny_tokenizer.modules():
        if isinstance(conv, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            assert conv.weight.is_contiguous(memory_format=torch.channels_last)
    quantizer = tiny_tokenizer.quantizer
    token_ids = quantizer.encode(latent)
    for tensor in (
        quantizer.resample(latent, 1, mode="area"),
        quantizer.scale_contribution(token_ids[0], 0),
        quantizer.quantize(latent)[0],
        tiny_tokenizer.ids_to_latent(token_ids),
    ):
        assert rearrange(tensor, "b a c t -> b t a c").is_contiguous()
    quantized = tiny_tokenizer.ids_to_latent(token_ids)
    assert tiny_tokenizer.decode_latent(quantized).is_contiguous()  # (B, H, A)


@pytest.mark.parametrize(("channels", "length"), [(2, 16), (8, 4)])
def test_grouped_norm_keeps_the_channels_last_layout_forward_and_backward(channels, length):
    # The convolutions around it read and write time-major memory; a layout change here would cost copies.
    hidden = torch.randn(5, 3 * channels, 1, length).contiguous(memory_format=torch.channels_last).requires_grad_()
    output = grouped_norm(3, channels)(hidden)
    assert output.is_contiguous(memory_format=torch.channels_last)
    output.backward(torch.randn_like(output))
    assert hidden.grad.is_contiguous(memory_format=torch.channels_last)
