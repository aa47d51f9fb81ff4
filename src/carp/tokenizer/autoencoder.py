"""Per-dimension 1-D convolutional encoder and decoder, vectorized over the A action dimensions.

Layout: every tensor here is (B, A * channels, 1, T) in `torch.channels_last` memory format, with the channels of
dimension d at [d * channels, (d + 1) * channels). Memory therefore runs (B, T, A, channels): time-major, as action
chunks (B, H, A) already are, so the encoder's input and the decoder's output are views of the action tensors. A 1-D
convolution over time is a 2-D convolution with a (1, k) kernel over this height-1 image. Why not `nn.Conv1d`: oneDNN
runs grouped convolutions with a few channels per group about twice as fast (forward + backward) in channels-last
layout, which PyTorch only offers for 4-D tensors (measured in `benchmarks/tokenizer_throughput.py`).

Convolutions use `groups=A` and GroupNorm uses one group per dimension, so no weight or statistic mixes two
dimensions: the module computes A independent networks in one kernel launch per layer. A consequence used by
`carp.tokenizer.per_dimension`: every parameter is the concatenation along axis 0 of the A per-dimension parameters.

Architecture after DESIGN.md section 3, itself after the official CARP code (ZhefeiGong/carp, `svqvae/basic_vae.py`).
Deviations from CARP: two residual blocks before each down-sampling (CARP puts one before and one after), a symmetric
padded stride-2 convolution for down-sampling (CARP pads one step on the right), a kernel-4 transposed convolution for
up-sampling (CARP: kernel 3 with output padding) and a GroupNorm + SiLU before the decoder's output convolution.
"""

from collections.abc import Callable
from contextlib import AbstractContextManager

import torch
import torch.nn.functional as F
from torch import nn

from carp.cpu_kernels import KernelChoice
from carp.tokenizer.spec import TokenizerSpec

# Whether PyTorch's CPU kernels run on AVX-512 on this machine, which decides the form of the grouped stride-2
# convolutions (see below).
_CPU_HAS_AVX512 = torch.backends.cpu.get_cpu_capability().startswith("AVX512")


def grouped_norm(num_dimensions: int, channels: int) -> nn.GroupNorm:
    """GroupNorm with one group per action dimension over (B, A * channels, 1, T) tensors, keeping their layout.

    PyTorch's channels-last kernel runs on the time-major memory as it is. Copying to the contiguous layout and back
    around its contiguous kernel (what this module did on AVX-512 CPUs until 2026-11-25) no longer pays on either
    machine measured: on the AVX-512 machine training steps were 1.4% and 2.5% faster without the copies at A = 10 and
    4.0% and 5.5% at A = 1 (steps of the two rules taking turns, 40 x 8 each), and on the AVX2 machine 1.7% and 1.8%.
    """
    return nn.GroupNorm(num_groups=num_dimensions, num_channels=num_dimensions * channels, eps=1e-6)


def grouped_conv(
    num_dimensions: int, in_channels: int, out_channels: int, kernel_size: int = 3, stride: int = 1
) -> nn.Conv2d:
    """Convolution over time applied to each dimension's channels separately, (B, A * in, 1, T) -> (B, A * out, 1, T').

    Padding kernel_size // 2 keeps the length for stride 1 and halves an even length for stride 2 with kernel 3.
    """
    convolution_class = GroupedDownsampling if stride == 2 else GroupedConvolution
    return convolution_class(
        num_dimensions * in_channels,
        num_dimensions * out_channels,
        kernel_size=(1, kernel_size),
        stride=(1, stride),
        padding=(0, kernel_size // 2),
        groups=num_dimensions,
    )


def grouped_upsampling(num_dimensions: int, channels: int) -> nn.ConvTranspose2d:
    """Transposed convolution that doubles the length, (B, A * ch, 1, T) -> (B, A * ch, 1, 2T), per dimension."""
    # kernel 4, stride 2, padding 1 doubles the length exactly: (T - 1) * 2 - 2 + 4 = 2T.
    return GroupedUpsampling(
        num_dimensions * channels,
        num_dimensions * channels,
        kernel_size=(1, 4),
        stride=(1, 2),
        padding=(0, 1),
        groups=num_dimensions,
    )


# Stride-2 convolutions on CPUs without AVX-512.
#
# There oneDNN has no direct (brgemm) kernel for two grouped stride-2 ops and falls back to im2col + GEMM: a transposed
# convolution's forward and a convolution's input gradient. Both get a form that only uses stride-1 convolutions, the
# same linear maps, rounding aside, differentiated by autograd:
# - Up-sampling (transposed, kernel 4, stride 2, padding 1) splits into two phases: output step 2u + r (r = 0, 1) sees
#   input steps u - 1, u, u + 1 through kernel taps 3, 1, - (r = 0) and -, 2, 0 (r = 1). So it is one stride-1 grouped
#   convolution (kernel 3, padding 1) with two phases of `out` channels per group, and one copy that interleaves the
#   phases in time. In a training step at A = 10 on the AVX2 machine the decoder's two up-samplings took 1.1 ms of
#   forward instead of 2.0, and the whole step 1.3% less time.
# - Down-sampling (kernel 3, stride 2, padding 1) is the stride-1 convolution kept at every second step: twice the
#   forward work, but a direct backward; the step 1.2% faster.
# With AVX-512 oneDNN runs both ops directly and the stride-1 forms only add work: forward + backward at A = 10, B = 64
# on the AVX-512 machine, 827 against 547 us for a down-sampling of 4 channels x 16 steps, 1093 against 814 us for an
# up-sampling of 8 channels x 4 steps, and training steps 2% faster without them (four runs of steps taking turns,
# 30-50 x 8 each: -4.6%, -2.2%, +0.3%, -1.9%). Single-group ones (the single-dimension tokenizer) have a faster form of
# their own (below); on CUDA cuDNN has its own kernels, so both ops keep PyTorch's convolutions there, as does ONNX
# export.

# Transposed-conv tap feeding phase r from input offset d, for (r, d) in (0, 1) x (-1, 0, 1); 4 = none (zero).
# Built once: the two-phase form only runs on the CPU.
_PHASE_TAPS = torch.tensor((3, 1, 4, 4, 2, 0))


def two_phase_upsampling(
    hidden: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, groups: int
) -> torch.Tensor:
    """`F.conv_transpose2d` with kernel (1, 4), stride (1, 2), padding (0, 1), as a stride-1 convolution and a copy.

    Args:
        hidden: (B, G * in, 1, T), channels-last.
        weight: (G * in, out, 1, 4), a transposed convolution's weight.
        bias: (G * out,) or None.
        groups: G.

    Returns:
        (B, G * out, 1, 2T), channels-last.
    """
    batch, _, _, length = hidden.shape
    in_channels, out_channels = weight.shape[0] // groups, weight.shape[1]
    taps = _PHASE_TAPS.to(weight.device)  # a no-op on the CPU
    # (G, in, out, 4 taps + a zero tap) -> (G, in, out, phase, offset) -> (G * phase * out, in, 1, offset), a
    # convolution weight (cross-correlation), whose taps 0, 1, 2 read offsets -1, 0, 1.
    phase_weight = F.pad(weight.reshape(groups, in_channels, out_channels, 4), (0, 1)).index_select(3, taps)
    phase_weight = phase_weight.view(groups, in_channels, out_channels, 2, 3).permute(0, 3, 2, 1, 4)
    phase_weight = phase_weight.reshape(groups * 2 * out_channels, in_channels, 1, 3)
    phase_bias = None if bias is None else bias.view(groups, 1, out_channels).expand(-1, 2, -1).reshape(-1)
    phases = F.conv2d(hidden, phase_weight, phase_bias, padding=(0, 1), groups=groups)  # (B, G * 2 * out, 1, T)
    # Channels-last memory (B, T, G, phase, out) -> (B, T, phase, G, out), which is (B, 2T, G * out) time-major.
    phases = phases.permute(0, 2, 3, 1).reshape(batch, length, groups, 2, out_channels)
    interleaved = phases.transpose(2, 3).reshape(batch, 1, 2 * length, groups * out_channels)
    return interleaved.permute(0, 3, 1, 2)


def stride1_downsampling(
    hidden: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, groups: int
) -> torch.Tensor:
    """`F.conv2d` with kernel (1, 3), stride (1, 2), padding (0, 1): the stride-1 convolution at every second step.

    Args:
        hidden: (B, G * in, 1, T), channels-last.
        weight: (G * out, in, 1, 3).
        bias: (G * out,) or None.
        groups: G.

    Returns:
        (B, G * out, 1, ceil(T / 2)), channels-last.
    """
    # Kernel 3, padding 1: stride-2 output t is stride-1 output 2t.
    every_step = F.conv2d(hidden, weight, bias, padding=(0, 1), groups=groups)  # (B, G * out, 1, T)
    return every_step[..., ::2].contiguous(memory_format=torch.channels_last)


# Single-group convolutions on the CPU.
#
# A single-dimension tokenizer (A = 1: the loop baseline of `benchmarks/tokenizer_throughput.py`, the modules
# `carp.tokenizer.per_dimension` splits off, a one-dimensional action space) has single-group convolutions. On a
# (B, ch, 1, T) image oneDNN runs them with direct kernels that cost 160-270 us forward + backward at B = 64 whatever
# the layer's shape. The same memory read as one image of B rows, (1, ch, B, T), is a view (a (1, k) kernel never
# mixes rows), and PyTorch sends it to its own im2col + GEMM convolution instead: 50-150 us per layer, and a whole
# training step at A = 1 takes 6.2-6.6 instead of 9.1-9.6 ms on the Intel machine (5.9 instead of 8.6 ms with oneDNN
# and PyTorch limited to AVX2 there). Grouped convolutions keep oneDNN's grouped kernel, which the view does not
# speed up (training steps at A = 10: 24.2 against 19.8 ms), and CUDA and ONNX export keep PyTorch's convolution.
_CPU_SINGLE_GROUP_ROWS = KernelChoice(True)


def cpu_single_group_rows(enabled: bool | None) -> AbstractContextManager[None]:
    """Run single-group CPU convolutions on the batch as image rows (True) or as a batch of images (False).

    None leaves the choice as it is (outside any such block: rows). Meant for measuring both forms on one machine
    (`benchmarks/tokenizer_throughput.py --also-onednn-loop`).
    """
    return _CPU_SINGLE_GROUP_ROWS.overridden(enabled)


def on_batch_rows(convolution: Callable[[torch.Tensor], torch.Tensor], hidden: torch.Tensor) -> torch.Tensor:
    """Apply a (1, k)-kernel `convolution` to (B, ch, 1, T) images read as the rows of one image (1, ch, B, T).

    Returns the convolution's output as (B, ch', 1, T'), channels-last like the input, the same values (rounding aside)
    as `convolution(hidden)`.
    """
    rows = convolution(hidden.transpose(0, 2))  # (1, ch', B, T')
    return rows.transpose(0, 2).contiguous(memory_format=torch.channels_last)


def _use_batch_rows(hidden: torch.Tensor, groups: int) -> bool:
    """Whether a convolution on `hidden` runs on the batch as image rows (single-group, CPU, not exporting)."""
    return (
        _CPU_SINGLE_GROUP_ROWS.enabled
        and groups == 1
        and hidden.device.type == "cpu"
        and hidden.shape[2] == 1
        and not torch.onnx.is_in_onnx_export()
    )


class GroupedConvolution(nn.Conv2d):
    """`nn.Conv2d` over time per dimension, single-group ones run on the batch as image rows on the CPU (above)."""

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """Map (B, A * in, 1, T) to (B, A * out, 1, T)."""
        if _use_batch_rows(hidden, self.groups):
            return on_batch_rows(super().forward, hidden)
        return super().forward(hidden)


class GroupedUpsampling(nn.ConvTranspose2d):
    """`nn.ConvTranspose2d` doubling the length per dimension, in the CPU's fastest form (two notes above)."""

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """Map (B, A * ch, 1, T) to (B, A * ch, 1, 2T)."""
        if _use_batch_rows(hidden, self.groups):
            return on_batch_rows(super().forward, hidden)
        settings = (self.kernel_size, self.stride, self.padding, self.output_padding, self.dilation)
        if not _use_stride1_forms(hidden, self.groups) or settings != ((1, 4), (1, 2), (0, 1), (0, 0), (1, 1)):
            return super().forward(hidden)
        return two_phase_upsampling(hidden, self.weight, self.bias, self.groups)


class GroupedDownsampling(nn.Conv2d):
    """`nn.Conv2d` with stride 2 over time per dimension, in the CPU's fastest form (two notes above)."""

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """Map (B, A * in, 1, T) to (B, A * out, 1, ceil(T / 2))."""
        if _use_batch_rows(hidden, self.groups):
            return on_batch_rows(super().forward, hidden)
        settings = (self.kernel_size, self.stride, self.padding, self.dilation)
        if not _use_stride1_forms(hidden, self.groups) or settings != ((1, 3), (1, 2), (0, 1), (1, 1)):
            return super().forward(hidden)
        return stride1_downsampling(hidden, self.weight, self.bias, self.groups)


def _use_stride1_forms(hidden: torch.Tensor, groups: int) -> bool:
    """Whether a grouped stride-2 op on `hidden` would hit oneDNN's im2col fallback (and is not being exported)."""
    return (
        groups > 1
        and hidden.device.type == "cpu"
        and not _CPU_HAS_AVX512
        and hidden.is_contiguous(memory_format=torch.channels_last)
        and not torch.onnx.is_in_onnx_export()  # the exported graph keeps PyTorch's own convolution nodes
    )


class ResidualBlock(nn.Module):
    """Two (GroupNorm, SiLU, conv k=3) layers with a skip connection; 1x1 conv on the skip if channels change."""

    def __init__(self, num_dimensions: int, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.norm_in = grouped_norm(num_dimensions, in_channels)
        self.conv_in = grouped_conv(num_dimensions, in_channels, out_channels)
        self.norm_out = grouped_norm(num_dimensions, out_channels)
        self.conv_out = grouped_conv(num_dimensions, out_channels, out_channels)
        self.skip = (
            nn.Identity()
            if in_channels == out_channels
            else grouped_conv(num_dimensions, in_channels, out_channels, kernel_size=1)
        )

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """Map (B, A * in_channels, 1, T) to (B, A * out_channels, 1, T)."""
        update = self.conv_in(F.silu(self.norm_in(hidden)))
        update = self.conv_out(F.silu(self.norm_out(update)))
        return self.skip(hidden) + update


class ActionEncoder(nn.Module):
    """Encode each dimension's normalized action chunk (B, A, 1, H) into a latent (B, A * C, 1, l)."""

    def __init__(self, spec: TokenizerSpec) -> None:
        super().__init__()
        num_dimensions = spec.action_dim
        channels = spec.base_channels
        self.conv_in = grouped_conv(num_dimensions, 1, channels)
        levels = []
        for multiplier in spec.channel_mult:
            level_channels = spec.base_channels * multiplier
            levels.append(
                nn.Sequential(
                    ResidualBlock(num_dimensions, channels, level_channels),
                    ResidualBlock(num_dimensions, level_channels, level_channels),
                    grouped_conv(num_dimensions, level_channels, level_channels, stride=2),
                )
            )
            channels = level_channels
        self.levels = nn.Sequential(*levels)
        self.norm_out = grouped_norm(num_dimensions, channels)
        self.conv_out = grouped_conv(num_dimensions, channels, spec.latent_channels)

    def forward(self, actions: torch.Tensor) -> torch.Tensor:
        """Encode (B, A, 1, H) normalized actions (channels-last, time last) into latents (B, A * C, 1, l)."""
        hidden = self.conv_in(actions)  # (B, A * ch, 1, H)
        hidden = self.levels(hidden)  # (B, A * ch * mult[-1], 1, l)
        return self.conv_out(F.silu(self.norm_out(hidden)))  # (B, A * C, 1, l)


class ActionDecoder(nn.Module):
    """Mirror of `ActionEncoder`: decode latents (B, A * C, 1, l) into action chunks (B, A, 1, H)."""

    def __init__(self, spec: TokenizerSpec) -> None:
        super().__init__()
        num_dimensions = spec.action_dim
        level_channels = [spec.base_channels * multiplier for multiplier in spec.channel_mult]
        channels = level_channels[-1]
        self.norm_in = grouped_norm(num_dimensions, spec.latent_channels)
        self.conv_in = grouped_conv(num_dimensions, spec.latent_channels, channels)
        levels = []
        output_channels = [spec.base_channels, *level_channels[:-1]]
        for next_channels in reversed(output_channels):
            levels.append(
                nn.Sequential(
                    grouped_upsampling(num_dimensions, channels),
                    ResidualBlock(num_dimensions, channels, next_channels),
                    ResidualBlock(num_dimensions, next_channels, next_channels),
                )
            )
            channels = next_channels
        self.levels = nn.Sequential(*levels)
        self.norm_out = grouped_norm(num_dimensions, channels)
        self.conv_out = grouped_conv(num_dimensions, channels, 1)

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        """Decode latents (B, A * C, 1, l) (channels-last) into normalized actions (B, A, 1, H) (time last)."""
        hidden = self.conv_in(F.silu(self.norm_in(latent)))  # (B, A * ch * mult[-1], 1, l)
        hidden = self.levels(hidden)  # (B, A * ch, 1, H)
        return self.conv_out(F.silu(self.norm_out(hidden)))  # (B, A, 1, H)
