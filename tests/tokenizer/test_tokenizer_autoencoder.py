"""The (1, k) convolutions over channels-last (B, A * channels, 1, T) images are per-dimension 1-D convolutions."""

import functools

import pytest
import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from carp.tokenizer.autoencoder import (
    cpu_single_group_rows,
    grouped_conv,
    grouped_norm,
    grouped_upsampling,
    on_batch_rows,
    stride1_downsampling,
    two_phase_upsampling,
)
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer


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


def assert_same_values_and_gradients(output, expected, inputs):
    """`output` equals `expected` (both channels-last), and so do their gradients with respect to `inputs`."""
    assert output.shape == expected.shape
    assert output.is_contiguous(memory_format=torch.channels_last)
    assert torch.allclose(output, expected, atol=1e-6)
    grad_output = torch.randn_like(expected)
    for got, want in zip(
        torch.autograd.grad(output, inputs, grad_output),
        torch.autograd.grad(expected, inputs, grad_output),
        strict=True,
    ):
        assert torch.allclose(got, want, atol=1e-5)


@pytest.mark.parametrize("groups", [1, 3])
def test_two_phase_upsampling_matches_conv_transpose_with_gradients(groups):
    # The CPU form of the grouped up-sampling: same outputs and same gradients as PyTorch's transposed convolution.
    torch.manual_seed(0)
    upsampling = grouped_upsampling(groups, 4).to(memory_format=torch.channels_last)
    image = channels_last_image(torch.randn(5, groups * 4, 6)).requires_grad_()
    expected = F.conv_transpose2d(
        image, upsampling.weight, upsampling.bias, stride=(1, 2), padding=(0, 1), groups=groups
    )  # (B, A * ch, 1, 12)
    output = two_phase_upsampling(image, upsampling.weight, upsampling.bias, groups)
    assert output.shape == expected.shape == (5, groups * 4, 1, 12)
    assert_same_values_and_gradients(output, expected, (image, upsampling.weight, upsampling.bias))


@pytest.mark.parametrize("length", [8, 7])
def test_grouped_downsampling_matches_strided_conv_with_gradients(length):
    # Whichever form this CPU runs (the stride-1 one without AVX-512), the module is PyTorch's strided convolution.
    torch.manual_seed(0)
    downsampling = grouped_conv(3, 4, 5, stride=2).to(memory_format=torch.channels_last)
    image = channels_last_image(torch.randn(5, 3 * 4, length)).requires_grad_()
    expected = F.conv2d(image, downsampling.weight, downsampling.bias, stride=(1, 2), padding=(0, 1), groups=3)
    output = downsampling(image)
    assert output.shape == expected.shape == (5, 3 * 5, 1, (length + 1) // 2)
    assert_same_values_and_gradients(output, expected, (image, downsampling.weight, downsampling.bias))


@pytest.mark.parametrize(("groups", "length"), [(1, 8), (3, 8), (3, 7)])
def test_stride1_downsampling_matches_strided_conv_with_gradients(groups, length):
    # The form CPUs without AVX-512 run, checked on every machine.
    torch.manual_seed(0)
    downsampling = grouped_conv(groups, 4, 5, stride=2).to(memory_format=torch.channels_last)
    image = channels_last_image(torch.randn(5, groups * 4, length)).requires_grad_()
    expected = F.conv2d(image, downsampling.weight, downsampling.bias, stride=(1, 2), padding=(0, 1), groups=groups)
    output = stride1_downsampling(image, downsampling.weight, downsampling.bias, groups)
    assert output.shape == expected.shape == (5, groups * 5, 1, (length + 1) // 2)
    assert_same_values_and_gradients(output, expected, (image, downsampling.weight, downsampling.bias))


def pytorch_forward(layer: nn.Conv2d | nn.ConvTranspose2d):
    """The layer's forward as PyTorch defines it, bypassing this project's choice of form."""
    base = nn.ConvTranspose2d if isinstance(layer, nn.ConvTranspose2d) else nn.Conv2d
    return functools.partial(base.forward, layer)


@pytest.mark.parametrize(
    "make_layer",
    [
        lambda: grouped_conv(1, 3, 5),
        lambda: grouped_conv(1, 3, 5, kernel_size=1),
        lambda: grouped_conv(1, 3, 5, stride=2),
        lambda: grouped_upsampling(1, 4),
    ],
    ids=["stride-1", "1x1", "stride-2", "transposed"],
)
def test_single_group_layers_run_on_batch_rows_with_the_same_values_and_gradients(make_layer):
    # One image of B rows instead of B one-row images: the same map, and the form single-group CPU layers take.
    torch.manual_seed(0)
    layer = make_layer().to(memory_format=torch.channels_last)
    image = channels_last_image(torch.randn(6, layer.in_channels, 8)).requires_grad_()
    output = layer(image)
    assert torch.equal(output, on_batch_rows(pytorch_forward(layer), image))
    assert_same_values_and_gradients(output, pytorch_forward(layer)(image), (image, layer.weight, layer.bias))


def onednn_convolutions(run) -> int:
    """How many convolutions `run()` sends to oneDNN (the batch-rows form runs PyTorch's own im2col kernel)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
        run()
    return sum(event.count for event in profile.key_averages() if event.key == "aten::mkldnn_convolution")


def test_cpu_single_group_rows_switches_the_form_and_restores_it():
    torch.manual_seed(0)
    single = grouped_conv(1, 8, 8).to(memory_format=torch.channels_last)
    grouped = grouped_conv(2, 4, 4).to(memory_format=torch.channels_last)
    image = channels_last_image(torch.randn(64, 8, 16))
    assert onednn_convolutions(lambda: single(image)) == 0
    with cpu_single_group_rows(False):
        assert onednn_convolutions(lambda: single(image)) == 1
        with cpu_single_group_rows(None):
            assert onednn_convolutions(lambda: single(image)) == 1
    assert onednn_convolutions(lambda: single(image)) == 0
    # Grouped layers keep oneDNN's grouped kernel whatever the setting.
    with cpu_single_group_rows(True):
        assert onednn_convolutions(lambda: grouped(image)) == 1


def test_single_dimension_tokenizer_trains_alike_in_both_convolution_forms():
    # The loop baseline of the throughput benchmark: same losses and gradients whichever form its convolutions take.
    torch.manual_seed(0)
    tokenizer = MultiScaleActionTokenizer(TokenizerSpec(action_dim=1, action_horizon=8, scales=(1, 2), codebook_size=8))
    actions = torch.rand(5, 8, 1, generator=torch.Generator().manual_seed(1)) * 2 - 1
    results = []
    for rows in (True, False):
        tokenizer.zero_grad()
        with cpu_single_group_rows(rows):
            output = tokenizer(actions)
        output.loss.backward()
        gradients = [parameter.grad.clone() for parameter in tokenizer.parameters() if parameter.grad is not None]
        results.append((output, gradients))
    (with_rows, rows_gradients), (without_rows, plain_gradients) = results
    assert len(rows_gradients) == len(plain_gradients) > 0
    assert torch.allclose(with_rows.loss, without_rows.loss, atol=1e-6)
    assert all(torch.equal(a, b) for a, b in zip(with_rows.token_ids, without_rows.token_ids, strict=True))
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(rows_gradients, plain_gradients, strict=True))


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
